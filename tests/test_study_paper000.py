"""The paper 000 study runs in its smoke mode and shows the paper's findings."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]


def _load():
    spec = importlib.util.spec_from_file_location("paper000_run", ROOT / "studies/paper000/run.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_paper000_smoke(tmp_path):
    mod = _load()
    assert mod.main(["--smoke", "--out", str(tmp_path), "--no-progress"]) == 0
    st = pd.read_csv(tmp_path / "stations_summary.csv").set_index("method")
    pt = pd.read_csv(tmp_path / "points_summary.csv").set_index("method")
    assert (tmp_path / "paper000_methods.png").stat().st_size > 10_000
    # paper 000, section 3.1.2: Case B's 5x5 system matrix is ill-conditioned, Theorem 1's
    # lower bound is at least 1e3, the true condition number orders of magnitude above it
    assert st.loc["linear", "condition_lower_bound_median"] >= 1e3
    assert st.loc["linear", "condition_median"] > 1e3 * st.loc["linear",
                                                               "condition_lower_bound_median"]
    # the sqrt residual (Case A) is better conditioned than the squared one (eq. 7 vs 8)
    assert st.loc["sqrt", "condition_median"] < st.loc["squared", "condition_median"]
    # every method converged on every station and point
    assert (st["converged"] == 1).all() and (pt["converged"] == 1).all()
    # the one-step identification does not carry the station self-calibration bias
    for m in ("sqrt", "squared", "linear", "linear_taylor"):
        assert pt.loc["volcal joint", "rigid_removed_rms_um"] < \
            0.2 * pt.loc[m, "rigid_removed_rms_um"]
    assert pt.loc["volcal joint", "rigid_removed_rms_um"] < 1.0
