"""Benchmark: the short whole processes of the command line, this version against another.

    python benchmarks/bench_startup.py                        # this version alone
    python benchmarks/bench_startup.py --baseline-ref main    # and main, paired

Times, as whole processes (start to exit, wall clock, ``--repeat`` runs each, the
median and the fastest kept):

* ``volcal --help``;
* ``volcal identify --model mcv754_wxyzt --data bad.csv --out DIR``, where bad.csv is
  the 10,296-reading table of ``benchmarks/compare_scipy.py`` with one bad cell in the
  middle row: the error is reported (exit 2) before the model is built and before SciPy
  is imported (the issue's goal: a CSV error in < 0.5 s);
* the same with the length column misspelled in the header: reported from the first
  line, before pandas is imported (volcal.measurement.header);
* ``volcal models``;
* with ``--good``: ``volcal -q identify ... --no-plots --force`` on the good table (exit 0),
  and the stage "reading the data" that its result.json records (the good path of the
  reading: the cells read before pandas' import and handed to the loader).

With ``--baseline-ref REF`` the same commands run from the ``src/`` of git revision REF
(``git archive`` into a temporary folder, put first on PYTHONPATH), in turn with this
version (this, baseline, this, baseline, ...), so that a change of the machine's load
affects both alike; the ratio is taken run by run and its median printed.  Both sides
are byte-compiled first, as in an installed copy.  The load average before and after is
printed with the figures: on this shared 2-core machine other jobs show in them.  Writes
the printout to ``benchmarks/results/startup.txt``.
"""

from __future__ import annotations

import argparse
import compileall
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))

#: runs ``volcal`` as its console script does (the volcal found first on sys.path)
LAUNCH = "import sys; from volcal.cli.main import main; sys.argv[0] = 'volcal'; sys.exit(main())"


def _load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def _bad_table(folder: Path) -> Path:
    from compare_scipy import make_data

    data, _, _ = make_data(10000, folder)
    lines = data.read_text(encoding="utf-8").splitlines()
    row = len(lines) // 2
    cells = lines[row].split(",")
    cells[8] = "4x5.2"  # the length column
    lines[row] = ",".join(cells)
    bad = folder / "bad.csv"
    bad.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return bad


def _bad_header(bad: Path) -> Path:
    """The same table with its length column misspelled in the header (and the bad cell):
    the header's error is the one reported."""
    text = bad.read_text(encoding="utf-8")
    head, _, body = text.partition("\n")
    path = bad.with_name("bad_header.csv")
    path.write_text(head.replace("length", "lenght") + "\n" + body, encoding="utf-8")
    return path


def _read_stage(argv: list[str]) -> float | None:
    """The "reading the data" stage (s) of an identify run, from its result.json."""
    if "--out" not in argv or "--no-plots" not in argv:
        return None
    doc = Path(argv[argv.index("--out") + 1]) / "result.json"
    return float(json.loads(doc.read_text(encoding="utf-8"))["timings_s"]["reading the data"])


def baseline_src(ref: str, work: Path) -> Path:
    """The ``src/`` folder of git revision ``ref``, extracted below ``work`` and
    byte-compiled (as an installed copy is): the folder to put first on PYTHONPATH."""
    base = work / "baseline"
    base.mkdir()
    archive = subprocess.run(
        ["git", "-C", str(REPO), "archive", ref, "src"], check=True, capture_output=True
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(base)], input=archive, check=True)
    compileall.compile_dir(base / "src", quiet=1)
    return base / "src"


def write_printout(lines: list[str], out: Path) -> None:
    """Print the lines and write them to ``out`` (its folder made when missing)."""
    text = "\n".join(lines) + "\n"
    print(text, end="")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")


def _time(argv: list[str], src: Path | None, expect: int) -> float:
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = str(src) + os.pathsep + env.get("PYTHONPATH", "")
    t0 = time.perf_counter()
    r = subprocess.run(
        [sys.executable, "-c", LAUNCH, *argv], env=env, capture_output=True, text=True
    )
    wall = time.perf_counter() - t0
    if r.returncode != expect:
        raise RuntimeError(f"{argv}: exit {r.returncode}, expected {expect}: {r.stderr[-2000:]}")
    return wall


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=10, help="runs per command and version")
    ap.add_argument("--baseline-ref", metavar="REF", help="git revision to compare with")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "startup.txt")
    ap.add_argument("--good", action="store_true", help="also identify the good table (--no-plots)")
    a = ap.parse_args(argv)
    import volcal

    compileall.compile_dir(Path(volcal.__file__).parent, quiet=1)
    lines = [
        "python benchmarks/bench_startup.py"
        + (f" --baseline-ref {a.baseline_ref}" if a.baseline_ref else "")
        + f" --repeat {a.repeat}"
        + (" --good" if a.good else ""),
        f"{platform.platform()}, {os.cpu_count()} CPUs, Python {platform.python_version()}",
        f"load average before: {_load()}",
    ]
    with tempfile.TemporaryDirectory(prefix="volcal-startup-") as tmp:
        work = Path(tmp)
        bad = _bad_table(work)
        commands = {
            "volcal --help": (["--help"], 0),
            "volcal identify, bad CSV (exit 2)": (
                ["identify", "--model", "mcv754_wxyzt", "--data", str(bad), "--out",
                 str(work / "out")],
                2,
            ),
            "volcal identify, bad header (exit 2)": (
                ["identify", "--model", "mcv754_wxyzt", "--data", str(_bad_header(bad)),
                 "--out", str(work / "out")],
                2,
            ),
            "volcal models": (["models"], 0),
        }  # fmt: skip
        if a.good:
            good = work / "data.csv"  # _bad_table's source
            commands["volcal identify, good, --no-plots"] = (
                ["-q", "identify", "--model", "mcv754_wxyzt", "--data", str(good), "--out",
                 str(work / "good"), "--no-plots", "--force"],
                0,
            )  # fmt: skip
        sides: dict[str, Path | None] = {"this": None}
        if a.baseline_ref:
            sides["baseline"] = baseline_src(a.baseline_ref, work)
        times: dict[tuple[str, str], list[float]] = {}
        stages: dict[str, list[float]] = {}
        for name, (args, code) in commands.items():
            for src in sides.values():
                _time(args, src, code)  # one warm-up run each: the file cache
            for _ in range(a.repeat):
                for side, src in sides.items():
                    times.setdefault((name, side), []).append(_time(args, src, code))
                    stage = _read_stage(args)
                    if stage is not None:
                        stages.setdefault(side, []).append(stage)
    lines.append(f"load average after: {_load()}")
    lines.append("")
    head = f"{'command':38s} {'version':9s} {'median s':>9s} {'fastest s':>10s}"
    lines.append(head + ("  this / baseline (median of run pairs)" if a.baseline_ref else ""))
    for name in commands:
        for side in sides:
            t = times[(name, side)]
            row = f"{name:38s} {side:9s} {statistics.median(t):9.3f} {min(t):10.3f}"
            if side == "baseline":
                pairs = [x / y for x, y in zip(times[(name, "this")], t)]
                row += f"  {statistics.median(pairs):.3f}"
            lines.append(row)
    if stages:
        lines.append("")
        lines.append("the good table's stage 'reading the data' (result.json):")
        for side, t in stages.items():
            row = f"{'reading the data':38s} {side:9s} {statistics.median(t):9.3f} {min(t):10.3f}"
            if side == "baseline":
                pairs = [x / y for x, y in zip(stages["this"], t)]
                row += f"  {statistics.median(pairs):.3f}"
            lines.append(row)
    write_printout(lines, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
