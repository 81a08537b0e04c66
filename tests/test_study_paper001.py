"""studies/paper001 in its smoke mode: the README's tables are the ones run.py prints (same
headers and row keys), the figures carry standard errors, the damping sweep is a table, a
smoke run writes nothing into the repository, and a run resumes from its chunks (tested
on a cheap stand-in job)."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "studies" / "paper001"
sys.path.insert(0, str(ROOT / "studies"))
import readme_tables as rt  # noqa: E402


def _run(*args):
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    p = subprocess.run([sys.executable, str(STUDY / "run.py"), "--no-progress", *args],
                       capture_output=True, text=True, env=env, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    return p


@pytest.fixture(scope="module")
def smoke():
    """One ``run.py --smoke`` (about 35 s) shared by the tests that read its tables: its
    'paper' scenario is the one a ``--scenarios paper --no-sweep`` run computes, so the
    fixed rows are the same numbers. Returns the repository folder's state before and
    after the run, and the output folder."""
    # (the chunks of a full run that may be running in the background are left out; the
    # smoke run's own chunks go under its output folder, checked to be outside the repo)
    ignore = ("results/chunks/",)
    before = rt.folder_state(STUDY, ignore)
    p = _run("--smoke")
    out = Path(re.search(r"results in (\S+)", p.stderr).group(1))
    return before, rt.folder_state(STUDY, ignore), out


# The study's whole smoke run: its cases are checked in the default suite on a few trials
# in-process (tests/test_multilaser.py) and its chunking below; CI runs these (-m slow).
@pytest.mark.slow
def test_paper001_smoke_readme(smoke):
    before, after, out = smoke
    assert after == before   # nothing written into the repository
    assert ROOT not in out.resolve().parents and (out / "chunks").is_dir()
    tables = json.loads((out / "tables.json").read_text())
    # the sphere_noise table is printed by run.py --noise-alternatives (its own run)
    _run("--noise-alternatives", "--smoke", "--out", str(out / "noise"))
    tables.update(json.loads((out / "noise" / "tables.json").read_text()))
    assert rt.check_readme_against(STUDY / "README.md", tables) == []
    assert "± " in tables["table1_paper"] and "± " in tables["cases_paper"]
    assert len(tables["damping"].splitlines()) > 2 + 6   # several damping values, not one


def _load():
    import importlib.util

    spec = importlib.util.spec_from_file_location("paper001_run", STUDY / "run.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


class _Job:
    """A cheap stand-in for a scenario: deterministic 'errors' per trial index."""

    def __init__(self, name="fake", fp="a"):
        self.name, self.labels, self._fp, self.calls = name, ["c1", "c2"], fp, []

    def fingerprint(self):
        return self._fp

    def run(self, indices):
        import numpy as np

        self.calls.append(list(indices))
        E = np.array([[[k + 1.0, 2.0 * k + c] for c in range(2)] for k in indices])
        E = np.repeat(E[:, :, :1], 5, axis=2) + np.arange(5)
        res = {"errors_um": E, "success": np.ones(E.shape[:2], bool),
               "iterations": np.ones(E.shape[:2], int),
               "geometry_mm": np.zeros(E.shape[:2] + (3,))}
        return _RUN.trial_stats(res, np.zeros(3))


_RUN = None


def test_paper001_chunks_resume_and_refuse_another_config(tmp_path):
    import numpy as np
    import pytest

    global _RUN
    _RUN = _load()
    job = _Job()
    first = _RUN.run_jobs([job], {"fake": 7}, tmp_path, 3, progress=False)["fake"][0]
    assert job.calls == [[0, 1, 2], [3, 4, 5], [6]]
    again = _Job()                                   # a new process: everything from disk
    second = _RUN.run_jobs([again], {"fake": 7}, tmp_path, 3, progress=False)["fake"][0]
    assert again.calls == []
    for k in first:
        np.testing.assert_array_equal(first[k], second[k])
    assert _RUN.available_trials(tmp_path, again) == 7
    more = _Job()                                    # more trials: only the new chunks run
    _RUN.run_jobs([more], {"fake": 10}, tmp_path, 3, progress=False)
    assert more.calls == [[6, 7, 8], [9]]
    with pytest.raises(SystemExit):                  # chunks of another configuration
        _RUN.run_jobs([_Job(fp="b")], {"fake": 7}, tmp_path, 3, progress=False)
    rows = _RUN.summarize(second, ["c1", "c2"], bootstrap=0)
    assert rows[0]["trials"] == 7 and rows[0]["mean_se_um"] > 0


@pytest.mark.slow
def test_paper001_smoke_fixed_rows_equal_the_full_run(smoke):
    # two-phase at 95 / 90 % is set by the start values: every trial gives the same numbers,
    # so a 4-trial smoke run must reproduce the README's 10,000-trial figures (printed to 6
    # digits) and its verdicts on the paper's rounding, which the README's text quotes
    out = smoke[2]
    smoke = json.loads((out / "tables.json").read_text())["table1_fixed"]
    readme = (STUDY / "README.md").read_text(encoding="utf-8")
    block = readme.split("<!-- table: table1_fixed -->")[1].split("<!-- /table -->")[0]

    def rows(md):
        return {c[0]: c[1:] for c in ([x.strip() for x in line.strip().strip("|").split("|")]
                                      for line in md.strip().splitlines()[2:])}

    got, want = rows(smoke), rows(block)
    assert set(got) == set(want) and len(got) == 8
    for key, (_paper, ours, _rnd, ok, _rel) in want.items():
        assert abs(float(got[key][1]) - float(ours)) <= 1e-5 * abs(float(ours)), key
        assert got[key][3] == ok, key
    # the paper's printed digits are met in 3 of 8 statistics, all within 1 %
    assert sum(v[3] == "yes" for v in got.values()) == 3
    assert all(abs(float(v[4])) < 1.0 for v in got.values())


def test_paper001_noise_alternatives_against_the_full_run(tmp_path):
    # the sphere intersection under the two readings of f on d12 d13 d23: 300 trials of each
    # agree with the README's 10,000-trial means within 3 of their own standard errors
    # (about 0.24 um), and per-laser phases give the larger mean (full run: 7.15 against
    # 5.87 um, i.e. about 4 combined standard errors of 300 trials apart)
    p = _run("--noise-alternatives", "--trials", "300", "--out", str(tmp_path))
    got = json.loads((tmp_path / "tables.json").read_text())["sphere_noise"]
    readme = (STUDY / "README.md").read_text(encoding="utf-8")
    block = readme.split("<!-- table: sphere_noise -->")[1].split("<!-- /table -->")[0]

    def means(md):
        out = {}
        for line in md.strip().splitlines()[3:]:
            c = [x.strip() for x in line.strip().strip("|").split("|")]
            m, se = (float(x) for x in c[3].split("±"))
            out[c[0]] = (int(c[2]), m, se)
        return out

    g, w = means(got), means(block)
    assert set(g) == set(w) == {"paper", "paper_per_laser"}, p.stdout
    for k in g:
        assert g[k][0] == 300 and w[k][0] == 10000
        assert abs(g[k][1] - w[k][1]) < 3 * g[k][2], (k, g[k], w[k])
    assert g["paper_per_laser"][1] > g["paper"][1]


def test_paper001_readme_figures_are_the_full_runs_tables():
    # every figure of the README's Monte Carlo tables, as printed, is the full run's
    # (results/tables.json, written by `run.py --update-readme` with the committed
    # 10,000-trial files; table1_fixed too, also compared with a smoke run above);
    # sphere_noise comes from its own run (--noise-alternatives), compared by value above
    tables = json.loads((STUDY / "results" / "tables.json").read_text())
    problems = rt.check_readme_against(STUDY / "README.md", tables, tolerance=0)
    assert problems == ["README table 'sphere_noise' is not printed by run.py"], problems
    assert {"table1_paper", "cases_paper", "cases_eq3", "damping"} <= set(tables)
