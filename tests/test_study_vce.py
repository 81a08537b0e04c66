"""studies/vce: the README's vce table is the one run.py makes of the committed run
(studies/vce/results.csv), figure for figure, and ``--table-from`` prints it; the smoke
run (one seed) goes through every scenario on the independent simulator and writes a
table with the same rows.  (The full run takes tens of minutes and is not repeated here.)"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "studies" / "vce"
sys.path.insert(0, str(ROOT / "studies"))
import readme_tables as rt  # noqa: E402


def _load():
    spec = importlib.util.spec_from_file_location("vce_run", STUDY / "run.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_vce_readme_is_the_committed_run(capsys):
    mod = _load()
    res = pd.read_csv(STUDY / "results.csv")
    tab = mod.results_table(res)
    assert rt.check_readme_against(STUDY / "README.md", {"vce": tab}, tolerance=0.0) == []
    assert mod.main(["--table-from", str(STUDY / "results.csv")]) == 0
    assert capsys.readouterr().out.strip() == tab.strip()
    # the committed run: every fit succeeded, every seed has every scenario and table
    assert res["success"].all()
    assert len(res) == res["seed"].nunique() * len(mod.SCENARIOS) * 2


def test_vce_smoke_run(tmp_path):
    mod = _load()
    assert mod.main(["--smoke", "--out", str(tmp_path)]) == 0
    res = pd.read_csv(tmp_path / "results.csv")
    assert len(res) == len(mod.SCENARIOS) * 2 and res["success"].all()
    # the wrong budget's factor is near 2, the others near 1 (one seed: loosely)
    for _, r in res.iterrows():
        assert abs(r["scale_factor"] / r["true_scale"] - 1) < 0.5, r
    got = rt.table_keys((tmp_path / "tables.md").read_text(encoding="utf-8"), key_cols=2)
    readme = rt.readme_tables((STUDY / "README.md").read_text(encoding="utf-8"))["vce"]
    assert got == rt.table_keys(readme, key_cols=2)
