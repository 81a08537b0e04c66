"""studies/fusion: the README's fusion_gain table (and the project README's copy) is the one
run.py makes of the committed run (studies/fusion/results.csv), figure for figure.  (The
fusion itself is tested by tests/test_fusion.py; the study's run is not repeated here.)"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "studies" / "fusion"
sys.path.insert(0, str(ROOT / "studies"))
import readme_tables as rt  # noqa: E402


def test_fusion_readme_is_the_committed_run():
    spec = importlib.util.spec_from_file_location("fusion_run", STUDY / "run.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    tab = mod.results_table(pd.read_csv(STUDY / "results.csv"))
    for readme in (STUDY / "README.md", ROOT / "README.md"):
        marked = rt.readme_tables(readme.read_text(encoding="utf-8"))
        assert "fusion_gain" in marked, readme
        got = rt.check_readme_against(readme, {**marked, "fusion_gain": tab}, tolerance=0.0)
        assert got == [], (readme, got)
