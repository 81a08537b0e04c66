"""studies/paper003 in its smoke mode: volcal's ISO 230-2 regression recovers paper 003's
eq. 11-12 from data simulated on them, with k = 2 intervals that cover; the README's
tables are the ones run.py prints; a smoke run writes nothing into the repository."""
from __future__ import annotations

import importlib.util
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "studies" / "paper003"
sys.path.insert(0, str(ROOT / "studies"))
import readme_tables as rt  # noqa: E402


def _load():
    spec = importlib.util.spec_from_file_location("paper003_run", STUDY / "run.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_paper003_smoke(capsys):
    before = rt.folder_state(STUDY)
    assert _load().main(["--smoke"]) == 0
    out = Path(re.search(r"results in (\S+)", capsys.readouterr().out).group(1))
    assert rt.folder_state(STUDY) == before           # nothing written into the repository
    assert ROOT not in out.resolve().parents
    tables = json.loads((out / "tables.json").read_text())
    assert rt.check_readme_against(STUDY / "README.md", tables) == []
    # every coefficient of eq. 11-12 within 4 standard uncertainties of the paper's value,
    # and the k = 2 intervals cover in most data sets
    for line in tables["regression"].splitlines()[2:]:
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert abs(float(cells[4])) < 4.0, cells
        assert float(cells[5]) > 85.0, cells
    # eq. 13 without interactions: the chi-square test rejects a P R term, not the truth
    adeq = tables["plane_adequacy"].splitlines()[2:]
    no_int = [c.strip() for c in adeq[0].strip("|").split("|")]
    with_int = [c.strip() for c in adeq[1].strip("|").split("|")]
    assert float(no_int[2]) < 15.0 and float(with_int[2]) > 80.0
