"""The scipy comparison benchmark runs (smoke size, no timing assertions) and its table has
the columns the README quotes."""

import importlib.util
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]


def test_compare_scipy_smoke(tmp_path, capsys):
    spec = importlib.util.spec_from_file_location("compare_scipy",
                                                  ROOT / "benchmarks" / "compare_scipy.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--smoke", "--out", str(tmp_path)]) == 0
    df = pd.read_csv(tmp_path / "compare_scipy.csv")
    for col in ("readings", "threads", "volcal_s", "volcal_no_plots_s", "scipy_s",
                "volcal_solve_s", "scipy_solve_s", "volcal_MiB", "scipy_MiB", "ratio_whole",
                "ratio_solve"):
        assert col in df.columns
    assert (df[["volcal_s", "scipy_s", "volcal_solve_s", "scipy_solve_s"]] > 0).all().all()
    assert "ratio_whole" in capsys.readouterr().out
