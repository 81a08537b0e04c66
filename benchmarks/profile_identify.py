"""Profiles of ``volcal identify`` (cProfile), kept in benchmarks/profiles/.

    python benchmarks/profile_identify.py                 # 1,000 and 10,000 readings
    python benchmarks/profile_identify.py --sizes 30000

Runs the command line in this process under cProfile on the data of
``benchmarks/compare_scipy.py`` (the bundled MCV 754 example), once without plots (the
parent's work: the plots are drawn by child processes, which cProfile does not see) and
writes, per size, the 40 most expensive functions by cumulative and by own time to
``benchmarks/profiles/identify_<readings>.txt``.  Read them with the per-stage table of
compare_scipy.py: the profile says which function inside a stage costs.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from compare_scipy import make_data  # noqa: E402


def profile(n: int, out_dir: Path) -> Path:
    from volcal.base.threads import set_blas_threads
    from volcal.cli.main import main

    set_blas_threads(1)
    with tempfile.TemporaryDirectory(prefix="volcal-prof-") as tmp:
        data, _, N = make_data(n, Path(tmp))
        argv = ["-q", "identify", "--model", "mcv754_wxyzt", "--data", str(data),
                "--out", str(Path(tmp) / "out"), "--no-plots"]
        main(argv)  # once to fill the model cache, as a user's second run finds it
        pr = cProfile.Profile()
        pr.enable()
        main([*argv, "--force"])
        pr.disable()
    text = io.StringIO()
    st = pstats.Stats(pr, stream=text)
    text.write(f"volcal identify, {N} readings, --no-plots, 1 BLAS thread (cProfile)\n\n")
    st.sort_stats("cumulative").print_stats(40)
    st.sort_stats("tottime").print_stats(40)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"identify_{N}.txt"
    # paths of this machine shortened to the package-relative part
    path.write_text(
        "\n".join(
            line.replace(str(Path(sys.prefix)), "<venv>").replace(str(HERE.parent), "<repo>")
            for line in text.getvalue().splitlines()
        )
        + "\n"
    )
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--out", type=Path, default=HERE / "profiles")
    a = ap.parse_args(argv)
    for n in a.sizes:
        print(profile(n, a.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
