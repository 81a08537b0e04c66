"""The scipy comparison benchmark runs (smoke size, no timing assertions) and its table has
the columns the README quotes."""

import importlib.util
from pathlib import Path

import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]


# The benchmark's whole smoke run (volcal and every scipy configuration, each in processes
# of its own, about 12 s): run by hand for its figures, its table's columns checked in CI's
# slow step (-m slow); the profiling benchmark's smoke run below stays in the default suite.
@pytest.mark.slow
def test_compare_scipy_smoke(tmp_path, capsys):
    spec = importlib.util.spec_from_file_location("compare_scipy",
                                                  ROOT / "benchmarks" / "compare_scipy.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--smoke", "--out", str(tmp_path)]) == 0
    df = pd.read_csv(tmp_path / "compare_scipy.csv")
    for col in ("readings", "threads", "volcal_s", "volcal_no_plots_s", "scipy_s",
                "volcal_solve_s", "scipy_solve_s", "volcal_MiB", "scipy_MiB", "ratio_whole",
                "ratio_solve", "volcal_tree_MiB", "scipy_tree_MiB", "volcal_cpu_s",
                "scipy_cpu_s"):
        assert col in df.columns
    cols = ["volcal_s", "scipy_s", "volcal_solve_s", "scipy_solve_s", "volcal_MiB",
            "scipy_MiB", "volcal_tree_MiB", "scipy_tree_MiB", "volcal_cpu_s", "scipy_cpu_s"]
    assert (df[cols] > 0).all().all()
    # a process's peak is measured on its own, not from this (larger) benchmark process
    assert (df["scipy_MiB"] < 1000).all()
    out = capsys.readouterr().out
    assert "ratio_whole" in out and "tree_MiB" in out


def test_profile_identify_smoke(tmp_path):
    spec = importlib.util.spec_from_file_location("profile_identify",
                                                  ROOT / "benchmarks" / "profile_identify.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--sizes", "100", "--out", str(tmp_path)]) == 0
    (f,) = tmp_path.glob("identify_*.txt")
    text = f.read_text()
    assert "cumulative" in text and "volcal/analysis/identify.py" in text
