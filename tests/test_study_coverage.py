"""studies/coverage: the README's results table is the one run.py makes of the committed full
run (results/coverage_full.json), figure for figure, and its other figures are that file's.
(The coverage computation itself is tested by tests/test_coverage.py; the full run takes
minutes and is not repeated here.)"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "studies" / "coverage"
sys.path.insert(0, str(ROOT / "studies"))
import readme_tables as rt  # noqa: E402


def _load():
    spec = importlib.util.spec_from_file_location("coverage_run", STUDY / "run.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_coverage_readme_is_the_committed_run(capsys):
    summ = json.loads((STUDY / "results" / "coverage_full.json").read_text(encoding="utf-8"))
    tab = _load().results_table(summ)
    # every figure as printed (tolerance 0), headers and row keys equal
    assert rt.check_readme_against(STUDY / "README.md", {"results": tab}, tolerance=0.0) == []
    # --table-from prints the same table and computes nothing
    assert _load().main(["--table-from", str(STUDY / "results" / "coverage_full.json")]) == 0
    assert capsys.readouterr().out.strip() == tab.strip()
    readme = (STUDY / "README.md").read_text(encoding="utf-8")
    # the bullets' figures are the same file's
    assert f"standard deviation {summ['parameters']['z_std']:.3f}" in readme
    r = summ["u_mc_over_u_linear"]
    assert f"ratio {r['median']:.4f}, range {r['min']:.2f} .. {r['max']:.2f}" in readme
    assert f"{summ['seconds_total']:.0f} s for the {summ['n']} experiments" in readme
    assert summ["succeeded"] == summ["n"] and summ["mc_trials_not_converged"] == 0
