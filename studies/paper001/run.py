"""Paper 001 study: multilateration with the simultaneous three-laser instrument (HPTI).

Monte Carlo of section 5 of Aguado et al. 2021 (IOP Conf. Ser. Mater. Sci. Eng. 1193
012061): the 60-point mesh, the instrument's own inter-laser distances, the drift /
vibration f(t) of eq. (2), and the multilateration strategies of Table 1 (sphere
intersection, points-only, two-phase, joint) at initial accuracies 100 / 95 / 90 %, plus
our variants, and a sweep of the joint strategy over the damping and the variable scaling
that choose its answer.  Everything is configured in config.toml; the simulator, the noise
model and the solvers are in hpti.py (this folder), the trials run through volcal's
seeded-chunk runner (:func:`volcal.analysis.uncertainty.parallel.run_chunks`).

    python studies/paper001/run.py [--smoke] [--trials N] [--workers K] [--out DIR]
                                   [--config FILE] [--scenarios NAME ...]
                                   [--summarize-only] [--update-readme]

Long runs: results are saved per chunk of trials (``<out>/chunks/<job>/``); a run that is
stopped resumes from the chunks on disk, and the scenarios advance chunk by chunk in turn,
so a run cut short has the same number of trials for each.  ``--summarize-only`` writes the
tables from the complete chunks on disk without computing any (the trial count is then what
was actually run).  In the background, on one core:

    nohup nice -n 19 python studies/paper001/run.py > paper001.log 2>&1 &

Trial k of every scenario uses the generator SeedSequence(seed, spawn_key=(k,)), and one
solver is built per worker process (not per trial), so the results for a seed are the same
whatever the number of workers or chunks.

Standard errors: mean and standard deviation by the jackknife over trials (the 60 points of
one trial share the drift draw, so trials, not points, are the independent units); maximum
and minimum by a bootstrap over trials (a rough guide for extremes).

Output (DIR; default studies/paper001/results, with --smoke a new temporary folder):
  tables.md / tables.json        every printed table (the README's marked tables)
  table_<scenario>.csv / .md     point error (um) per case, with standard errors
  jacobian.csv / .md             unknowns, readings, rank, redundancy, condition per step
  trials_<scenario>.csv.gz       per trial and case: mean / max error (um), success
  errors_<scenario>.png          error distributions per strategy and initial accuracy
  summary.md, meta.json          all tables; trials, workers, wall time, versions
"""
from __future__ import annotations

import os

# small matrices: one BLAS thread per process (set before numpy is imported; the worker
# processes inherit it)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import copy  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import tomllib  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from volcal.analysis.uncertainty.parallel import run_chunks  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))
import hpti  # noqa: E402
import readme_tables as rt  # noqa: E402

# histogram bins of the point errors (um) for the plots; zeros go to the first bin
BINS = np.logspace(-11, 6, 8 * 17 + 1)


def load_config(path: str | Path | None = None) -> dict:
    with open(path or HERE / "config.toml", "rb") as fh:
        return tomllib.load(fh)


def _chunks(n: int, size: int) -> list[list[int]]:
    return [list(range(i, min(n, i + size))) for i in range(0, n, size)]


def run_scenario(cfg: dict, scenario: str, trials, workers: int = 1, *,
                 progress: bool = True, runner: hpti.StudyRunner | None = None) -> dict:
    """Run the trials ``trials`` (a count: 0..trials-1, or a sequence of indices) of one
    scenario; returns stacked arrays in that order.

    workers = 1 runs in this process (on ``runner`` if given); more run the trials in
    chunks on local worker processes through
    :func:`volcal.analysis.uncertainty.parallel.run_chunks`, each worker building one
    :class:`hpti.StudyRunner` (one IPOPT build) for its first chunk.  Trial k's data come
    from its own seed (:func:`hpti.trial_rng`), whoever runs it."""
    from tqdm import tqdm

    idx = list(range(trials)) if isinstance(trials, (int, np.integer)) else list(trials)
    pos = {k: i for i, k in enumerate(idx)}
    results: list[dict | None] = [None] * len(idx)
    bar = tqdm(total=len(idx), desc=scenario, unit="trial", disable=not progress,
               file=sys.stderr, dynamic_ncols=True)
    if workers <= 1:
        runner = runner or hpti.StudyRunner(cfg, scenario)
        labels = runner.case_labels()
        for k in idx:
            results[pos[k]] = runner.trial(k)
            bar.update(1)
    else:
        labels = [c.label for c in hpti.cases_from_config(cfg)]
        size = max(1, min(25, len(idx) // (workers * 8) or 1))
        chunks = [idx[i:i + size] for i in range(0, len(idx), size)]
        kernel = hpti.TrialKernel(cfg, scenario)
        for _, part in run_chunks(kernel, chunks, workers=workers):
            for r in part:
                results[pos[r["index"]]] = r
                bar.update(1)
    bar.close()
    out = {key: np.stack([r[key] for r in results]) for key in
           ("errors_um", "success", "iterations", "geometry_mm")}
    out["labels"] = labels
    return out


# --------------------------------------------------------------------------------------
# per-trial statistics (what a chunk file holds) and their summaries


def trial_stats(res: dict, truth_geometry_mm) -> dict:
    """Reduce stacked trial results to per-trial sums (T, C), the geometry error (T, C, 3)
    um and the histogram of all errors (C, bins)."""
    E = np.asarray(res["errors_um"], float)            # (T, C, N)
    fin = np.isfinite(E)
    E0 = np.where(fin, E, 0.0)
    hist = np.stack([np.histogram(np.clip(E[:, c][fin[:, c]], BINS[0], BINS[-1]),
                                  bins=BINS)[0] for c in range(E.shape[1])])
    return {"s1": E0.sum(axis=2), "s2": (E0 ** 2).sum(axis=2), "n": fin.sum(axis=2),
            "mx": np.where(fin, E, -np.inf).max(axis=2),
            "mn": np.where(fin, E, np.inf).min(axis=2),
            "success": np.asarray(res["success"], bool),
            "iterations": np.asarray(res["iterations"], float),
            "geometry_error_um": 1e3 * (np.asarray(res["geometry_mm"], float)
                                        - np.asarray(truth_geometry_mm, float)),
            "hist": hist}


def concat_stats(parts: list[dict]) -> dict:
    out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0] if k != "hist"}
    out["hist"] = np.sum([p["hist"] for p in parts], axis=0)
    return out


def _jackknife(values_loo: np.ndarray) -> np.ndarray:
    """Jackknife standard error from leave-one-out estimates (T, C)."""
    T = values_loo.shape[0]
    if T < 2:
        return np.full(values_loo.shape[1], np.nan)
    d = values_loo - values_loo.mean(axis=0)
    return np.sqrt((T - 1) / T * np.sum(d * d, axis=0))


def summarize(stats: dict, labels: list[str], bootstrap: int = 200, seed: int = 0) -> list[dict]:
    """Pooled statistics of the point errors per case, with standard errors."""
    s1, s2, n = stats["s1"], stats["s2"], stats["n"].astype(float)
    T = s1.shape[0]
    S1, S2, Nn = s1.sum(0), s2.sum(0), n.sum(0)
    mean = S1 / Nn
    std = np.sqrt(np.maximum(S2 / Nn - mean ** 2, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        lm = (S1 - s1) / (Nn - n)
        ls = np.sqrt(np.maximum((S2 - s2) / (Nn - n) - lm ** 2, 0.0))
    mean_se, std_se = _jackknife(lm), _jackknife(ls)
    mx, mn = stats["mx"].max(0), stats["mn"].min(0)
    if T >= 2 and bootstrap > 0:
        rng = np.random.default_rng(seed)
        bmx, bmn = [], []
        for _ in range(bootstrap):
            i = rng.integers(0, T, T)
            bmx.append(stats["mx"][i].max(0))
            bmn.append(stats["mn"][i].min(0))
        mx_se, mn_se = np.std(bmx, axis=0, ddof=1), np.std(bmn, axis=0, ddof=1)
    else:
        mx_se = mn_se = np.full(len(labels), np.nan)
    g = stats["geometry_error_um"]
    g_rms = np.sqrt(np.nanmean(g ** 2, axis=0))        # (C, 3)
    rows = []
    for c, lab in enumerate(labels):
        rows.append({"label": lab, "trials": T, "mean_um": mean[c], "mean_se_um": mean_se[c],
                     "std_um": std[c], "std_se_um": std_se[c], "max_um": mx[c],
                     "max_se_um": mx_se[c], "min_um": mn[c], "min_se_um": mn_se[c],
                     "max_trial_mean_um": float(np.max(s1[:, c] / n[:, c])),
                     "success_pct": 100.0 * float(np.mean(stats["success"][:, c])),
                     "iterations_mean": float(np.mean(stats["iterations"][:, c])),
                     "x1_error_rms_um": g_rms[c, 0], "x2_error_rms_um": g_rms[c, 1],
                     "y2_error_rms_um": g_rms[c, 2]})
    return rows


def summary_table(res: dict, cases: list) -> list[dict]:
    """Per case: statistics of the point error (um) pooled over all points of all trials
    (with standard errors), the largest per-trial mean, the success rate and the mean
    iterations (stacked results of :func:`run_scenario`)."""
    st = trial_stats(res, np.zeros(3))
    rows = summarize(st, [c.label for c in cases], bootstrap=0)
    for r, case in zip(rows, cases):
        r.update(case=case.name, strategy=case.strategy,
                 initial_accuracy_pct="" if case.accuracy is None else round(100 * case.accuracy))
    return rows


# --------------------------------------------------------------------------------------
# jobs: the scenarios and the damping sweep, run chunk by chunk


class ScenarioJob:
    def __init__(self, cfg: dict, scenario: str, workers: int = 1):
        self.cfg, self.scenario, self.workers = cfg, scenario, workers
        self.name = scenario
        self.cases = hpti.cases_from_config(cfg)
        self.labels = [c.label for c in self.cases]
        self._runner = None

    @property
    def runner(self) -> hpti.StudyRunner:
        if self._runner is None:
            self._runner = hpti.StudyRunner(self.cfg, self.scenario)
        return self._runner

    def truth_geometry(self):
        return hpti.experiment_from_config(self.cfg, self.scenario).instrument.geometry

    def fingerprint(self) -> str:
        keep = {k: self.cfg.get(k) for k in ("mesh", "instrument", "case")}
        keep["scenario"] = self.cfg.get("scenario", {}).get(self.scenario)
        st = self.cfg.get("study", {})
        keep["study"] = {k: st.get(k) for k in ("seed", "initial_accuracy_percent",
                                                "initial_accuracy_applies_to")}
        if st.get("estimator", "core") != "study":
            # the core's chunks say so; the study's estimator keeps the fingerprint its
            # chunks had before the core computed the tables (they stay readable)
            keep["study"]["estimator"] = st.get("estimator", "core")
        return _hash(keep)

    def run(self, indices: list[int]) -> dict:
        if self.workers > 1:
            res = run_scenario(self.cfg, self.scenario, indices, self.workers, progress=False)
        else:
            res = run_scenario(self.cfg, self.scenario, indices, 1, progress=False,
                               runner=self.runner)
        return trial_stats(res, self.truth_geometry())


class DampingJob:
    """The joint strategy of the paper (points + frame + x1 x2 y2) at every damping and
    scaling of ``[damping_sweep]``, on the trials of its scenario."""

    def __init__(self, cfg: dict):
        self.cfg = cfg
        sw = cfg["damping_sweep"]
        self.scenario = sw.get("scenario", "paper")
        self.name = "damping"
        self.dampings = [float(d) for d in sw["damping_rel"]]
        self.scalings = list(sw.get("scaling", ["units"]))
        sub = copy.deepcopy(cfg)
        sub["case"] = [{"name": f"joint {s}", "strategy": "joint",
                        "groups": list(sw.get("groups", ["points", "frame", "geometry"])),
                        "scaling": s} for s in self.scalings]
        self.sub = sub
        self.cases = hpti.cases_from_config(sub)
        self.keys = [(c, d) for c in self.cases for d in self.dampings]
        self.labels = [f"{c.scaling} | {d:g} | {100 * c.accuracy:g}" for c, d in self.keys]
        self._runner = None

    @property
    def runner(self) -> hpti.StudyRunner:
        if self._runner is None:
            self._runner = hpti.StudyRunner(self.sub, self.scenario)
        return self._runner

    def truth_geometry(self):
        return hpti.experiment_from_config(self.cfg, self.scenario).instrument.geometry

    def fingerprint(self) -> str:
        keep = {k: self.cfg.get(k) for k in ("mesh", "instrument", "damping_sweep")}
        keep["scenario"] = self.cfg.get("scenario", {}).get(self.scenario)
        st = self.cfg.get("study", {})
        keep["study"] = {k: st.get(k) for k in ("seed", "initial_accuracy_percent",
                                                "initial_accuracy_applies_to")}
        if st.get("estimator", "core") != "study":
            # the core's chunks say so; the study's estimator keeps the fingerprint its
            # chunks had before the core computed the tables (they stay readable)
            keep["study"]["estimator"] = st.get("estimator", "core")
        keep["damping_sweep"] = {k: v for k, v in keep["damping_sweep"].items()
                                 if k not in ("trials", "smoke_trials")}
        return _hash(keep)

    def run(self, indices: list[int]) -> dict:
        r = self.runner
        n, N = len(self.keys), r.experiment.n_points
        out = {"errors_um": np.full((len(indices), n, N), np.nan),
               "success": np.zeros((len(indices), n), bool),
               "iterations": np.zeros((len(indices), n), int),
               "geometry_mm": np.full((len(indices), n, 3), np.nan)}
        for t, k in enumerate(indices):
            data = r.simulate(k)
            for j, (case, d) in enumerate(self.keys):
                e = r.estimate(data, case, damping_rel=d)
                out["errors_um"][t, j] = e.errors_um(data)
                out["success"][t, j] = e.success
                out["iterations"][t, j] = e.iterations
                out["geometry_mm"][t, j] = e.instrument.geometry
        return trial_stats(out, self.truth_geometry())


def _hash(obj) -> str:
    return hashlib.sha1(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _chunk_path(root: Path, job, a: int, b: int) -> Path:
    return root / "chunks" / job.name / f"{a:06d}-{b:06d}.npz"


def _load_chunk(path: Path, job) -> dict | None:
    if not path.is_file():
        return None
    z = np.load(path, allow_pickle=False)
    if str(z["fingerprint"]) != job.fingerprint() or list(z["labels"]) != job.labels:
        raise SystemExit(f"{path}: written with another configuration; delete "
                         f"{path.parent} to recompute")
    return {k: z[k] for k in z.files if k not in ("fingerprint", "labels")}


def _save_chunk(path: Path, job, st: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez_compressed(tmp, fingerprint=job.fingerprint(), labels=np.array(job.labels),
                        **st)
    os.replace(tmp, path)


def run_jobs(jobs: list, trials: dict[str, int], out: Path, chunk: int, *,
             progress: bool = True, compute: bool = True) -> dict[str, tuple[dict, float]]:
    """Run (or load) the chunks of every job, the jobs' chunks in turn; returns per job the
    stacked statistics of the complete prefix of chunks and the seconds spent computing.
    With ``compute=False`` only chunks already on disk are used."""
    from tqdm import tqdm

    plan = {j.name: [(a[0], a[-1] + 1) for a in _chunks(trials[j.name], chunk)] for j in jobs}
    parts = {j.name: {} for j in jobs}
    todo = []
    for j in jobs:
        for a, b in plan[j.name]:
            st = _load_chunk(_chunk_path(out, j, a, b), j)
            if st is not None:
                parts[j.name][a] = st
            elif compute:
                todo.append((a, j, b))
    todo.sort(key=lambda t: t[0])                  # chunk by chunk, the jobs in turn
    seconds = {j.name: 0.0 for j in jobs}
    bar = tqdm(total=sum(b - a for a, _, b in todo), unit="trial", disable=not progress,
               file=sys.stderr, dynamic_ncols=True, desc="paper001")
    for a, j, b in todo:
        t0 = time.perf_counter()
        st = j.run(list(range(a, b)))
        seconds[j.name] += time.perf_counter() - t0
        _save_chunk(_chunk_path(out, j, a, b), j, st)
        parts[j.name][a] = st
        bar.set_postfix_str(f"{j.name} {b}/{trials[j.name]}")
        bar.update(b - a)
    bar.close()
    res = {}
    for j in jobs:
        got = []
        for a, _ in plan[j.name]:                   # the complete prefix only
            if a not in parts[j.name]:
                break
            got.append(parts[j.name][a])
        res[j.name] = (concat_stats(got) if got else None, seconds[j.name])
    return res


def available_trials(out: Path, job) -> int:
    """Trials in the complete prefix of chunk files on disk for ``job``."""
    d = out / "chunks" / job.name
    spans = sorted(tuple(int(x) for x in p.stem.split("-")) for p in d.glob("*-*.npz")
                   if ".tmp" not in p.name) if d.is_dir() else []
    n = 0
    for a, b in spans:
        if a == n:
            n = b
    return n


# --------------------------------------------------------------------------------------
# tables


def _pm(v, se) -> str:
    s = rt._fmt(v)
    return s if not np.isfinite(se) else f"{s} ± {rt._fmt(se)}"


def case_rows(rows: list[dict], cases: list) -> list[dict]:
    for r, case in zip(rows, cases):
        r.update(case=case.name, strategy=case.strategy,
                 initial_accuracy_pct="" if case.accuracy is None else round(100 * case.accuracy))
    return rows


def cases_markdown(rows: list[dict]) -> str:
    tab = [{"case": r["case"], "acc": r["initial_accuracy_pct"] if r["initial_accuracy_pct"]
            != "" else "-", "mean": _pm(r["mean_um"], r["mean_se_um"]),
            "std": _pm(r["std_um"], r["std_se_um"]), "max": _pm(r["max_um"], r["max_se_um"]),
            "min": rt._fmt(r["min_um"]), "mtm": rt._fmt(r["max_trial_mean_um"]),
            "succ": rt._fmt(r["success_pct"]), "it": rt._fmt(r["iterations_mean"])}
           for r in rows]
    return rt.markdown(tab, ["case", "acc", "mean", "std", "max", "min", "mtm", "succ", "it"],
                       ["case", "initial accuracy %", "mean ± SE um", "std ± SE um",
                        "max ± SE um", "min um", "largest trial mean um", "success %",
                        "iterations"])


def _printed(s) -> tuple[float, float]:
    """Value of a number as printed in the paper and half a unit of its last digit."""
    s = str(s).strip()
    mant, _, exp = s.lower().partition("e")
    dec = len(mant.split(".")[1]) if "." in mant else 0
    return float(s), 0.5 * 10.0 ** (int(exp or 0) - dec)


FIXED_STATS = (("mean", "mean_um"), ("std", "std_um"), ("max", "max_um"), ("min", "min_um"))


def fixed_markdown(rows: list[dict], paper: list[dict]) -> str:
    """The Table 1 rows whose trials do not scatter (SE below 1e-6 of the mean: the result is
    set by the start values, so every trial and the paper's run give the same numbers),
    statistic by statistic: the paper's printed value, ours to six digits, and whether ours
    lies within half a unit of the paper's last printed digit."""
    ours = {(r["case"], str(r["initial_accuracy_pct"])): r for r in rows}
    tab = []
    for p in paper:
        key = (p["case"], str(p.get("accuracy", "")))
        r = ours.get(key)
        if r is None or not (0 < r["mean_um"] and r["mean_se_um"] <= 1e-6 * r["mean_um"]):
            continue
        for stat, col in FIXED_STATS:
            pv, rnd = _printed(p[stat])
            diff = abs(float(r[col]) - pv)
            tab.append({"row": f"{p['case']} @ {key[1]} %: {stat}", "paper": str(p[stat]),
                        "ours": f"{float(r[col]):.6g}", "rnd": f"{rnd:.3g}",
                        "ok": "yes" if diff <= rnd else "no",
                        "rel": f"{100 * (float(r[col]) - pv) / pv:+.3f}"})
    return rt.markdown(tab, ["row", "paper", "ours", "rnd", "ok", "rel"],
                       ["statistic (trials do not scatter)", "paper um", "ours um",
                        "half a unit of the paper's last digit, um", "within the rounding",
                        "(ours - paper) / paper %"])


def fixed_from_csv(csv: Path, cfg: dict) -> str:
    """:func:`fixed_markdown` from a run's table_paper.csv (no computation)."""
    import pandas as pd

    rows = pd.read_csv(csv, keep_default_na=False).to_dict("records")
    for r in rows:
        r["initial_accuracy_pct"] = str(r["initial_accuracy_pct"])
    return fixed_markdown(rows, cfg["paper_table1"])


#: point errors below this are the rounding of the estimates (the exact answer is 0: the
#: two-phase strategy at 100 % initial accuracy recovers the points to ~1e-12 um); a gap in
#: standard errors of such a mean would count rounding errors, not a difference, um
ROUNDING_UM = 1e-9


def table1_markdown(rows: list[dict], paper: list[dict]) -> str:
    """Paper 001 Table 1 next to ours (scenario `paper`).  The gap of the means is given in
    standard errors of ours, after allowing for the rounding of the paper's printed value:
    (|ours - paper| - rounding) / SE, 0 when within the rounding; '-' where the trials do
    not scatter (SE below 1e-6 of the value: the result is set by the start values) or
    scatter by rounding only (mean below ROUNDING_UM: the exact answer is 0)."""
    ours = {(r["case"], str(r["initial_accuracy_pct"])): r for r in rows}
    tab = []
    for p in paper:
        key = (p["case"], str(p.get("accuracy", "")))
        r = ours.get(key)
        if r is None:
            continue
        pm, rnd = _printed(p["mean"])
        se = r["mean_se_um"]
        excess = max(abs(r["mean_um"] - pm) - rnd, 0.0)
        if (np.isfinite(se) and se > 1e-6 * max(abs(r["mean_um"]), 1e-300)
                and abs(r["mean_um"]) > ROUNDING_UM):
            gap = f"{np.sign(r['mean_um'] - pm) * excess / se:+.1f}"
        else:
            gap = "-"
        tab.append({"case": p["case"], "acc": key[1] or "-", "pm": str(p["mean"]),
                    "om": _pm(r["mean_um"], se), "rel": f"{100 * (r['mean_um'] - pm) / pm:+.2f}",
                    "gap": gap, "pmax": str(p["max"]),
                    "omax": _pm(r["max_um"], r["max_se_um"]),
                    "pmin": str(p["min"]), "omin": r["min_um"], "pstd": str(p["std"]),
                    "ostd": _pm(r["std_um"], r["std_se_um"])})
    return rt.markdown(tab, ["case", "acc", "pm", "om", "rel", "gap", "pmax", "omax", "pmin",
                             "omin", "pstd", "ostd"],
                       ["method", "init. acc. %", "paper mean", "ours mean ± SE",
                        "(ours - paper) / paper %", "gap beyond the paper's rounding, in SE",
                        "paper max", "ours max ± SE", "paper min", "ours min", "paper std",
                        "ours std ± SE"])


def instrument_markdown(rows: list[dict]) -> str:
    tab = [{"case": r["case"], "acc": r["initial_accuracy_pct"] if r["initial_accuracy_pct"]
            != "" else "-", "x1": r["x1_error_rms_um"], "x2": r["x2_error_rms_um"],
            "y2": r["y2_error_rms_um"]} for r in rows]
    return rt.markdown(tab, ["case", "acc", "x1", "x2", "y2"],
                       ["case", "initial accuracy %", "x1 error RMS um", "x2 error RMS um",
                        "y2 error RMS um"])


def damping_markdown(rows: list[dict]) -> str:
    tab = []
    for r in rows:
        sc, d, acc = (s.strip() for s in r["label"].split("|"))
        tab.append({"key": f"{sc} / {d} / {acc}", "mean": _pm(r["mean_um"], r["mean_se_um"]),
                    "std": rt._fmt(r["std_um"]), "max": rt._fmt(r["max_um"]),
                    "x1": r["x1_error_rms_um"], "x2": r["x2_error_rms_um"],
                    "y2": r["y2_error_rms_um"], "succ": r["success_pct"],
                    "it": r["iterations_mean"]})
    return rt.markdown(tab, ["key", "mean", "std", "max", "x1", "x2", "y2", "succ", "it"],
                       ["scaling / damping_rel / initial accuracy %", "mean ± SE um",
                        "std um", "max um", "x1 error RMS um", "x2 error RMS um",
                        "y2 error RMS um", "success %", "iterations"])


def plot_errors(path: Path, hist: np.ndarray, cases: list, scenario: str, trials: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    accs = sorted({c.accuracy for c in cases if c.accuracy is not None}, reverse=True)
    names = list(dict.fromkeys(c.name for c in cases))
    colors = dict(zip(names, plt.rcParams["axes.prop_cycle"].by_key()["color"] * 3))
    used = np.nonzero(hist.sum(0))[0]
    lo, hi = (used.min(), used.max() + 1) if used.size else (0, len(BINS) - 1)
    lo = max(lo, np.searchsorted(BINS, 1e-4) - 1)
    fig, axes = plt.subplots(len(accs), 1, figsize=(9, 2.8 * len(accs)), sharex=True)
    axes = np.atleast_1d(axes)
    for ax, a in zip(axes, accs):
        for c, case in enumerate(cases):
            if case.accuracy not in (a, None):
                continue
            h = hist[c].astype(float)
            h[lo] += h[:lo].sum()
            tot = max(h.sum(), 1.0)
            ax.stairs(h[lo:hi] / tot, BINS[lo:hi + 1], lw=1.4, color=colors[case.name],
                      ls="--" if case.strategy == "sphere" else "-", label=case.name)
        ax.set_xscale("log")
        ax.set_ylabel("fraction of points")
        ax.set_title(f"initial accuracy {100 * a:g} %", fontsize=10)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, ncol=2)
    axes[-1].set_xlabel("point error |P_est - P_true| in the instrument frame (um); errors "
                        "below the left edge are piled into the first bin;\nsphere (dashed) "
                        "and points-only give the same errors and overlap")
    fig.suptitle(f"paper 001 study, scenario '{scenario}', {trials} trials x 60 points",
                 fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def jacobian_rows(cfg: dict, scenario: str) -> list[dict]:
    runner = hpti.StudyRunner(cfg, scenario, estimator="study")  # its rank reports
    rows = []
    for case, rep in runner.jacobian_reports():
        d = rep.as_dict()
        d.pop("gauge")
        rows.append({"case": case.label, **d})
    return rows


def write_csv(path: Path, rows: list[dict]) -> None:
    import pandas as pd

    pd.DataFrame(rows).to_csv(path, index=False)


NOISE_SCENARIOS = ("paper", "paper_per_laser")


def noise_alternatives(cfg: dict, args) -> int:
    """The sphere intersection's errors under the two readings of how f(t) enters d12, d13,
    d23 (one phase set for the three lasers, or one per laser), next to the paper's Table 1
    sphere row: the table ``sphere_noise``."""
    cfg = dict(cfg)
    cfg["case"] = [c for c in cfg["case"] if c["strategy"] == "sphere"]
    st = cfg.setdefault("study", {})
    trials = args.trials or (int(st.get("smoke_trials", 4)) if args.smoke else 1000)
    out = rt.output_folder(args.out, True, HERE / "results", "paper001-noise")
    out.mkdir(parents=True, exist_ok=True)
    jobs = [ScenarioJob(cfg, sc) for sc in NOISE_SCENARIOS]
    stats = run_jobs(jobs, {j.name: trials for j in jobs}, out,
                     int(st.get("chunk_trials", 250)), progress=not args.no_progress)
    paper = next(p for p in cfg["paper_table1"] if p["case"] == "sphere")
    tab = [{"s": "paper 001, Table 1", "mode": "-", "n": 10000, "mean": paper["mean"],
            "std": paper["std"], "max": paper["max"]}]
    for j in jobs:
        r = summarize(stats[j.name][0], j.labels, bootstrap=int(st.get("bootstrap", 200)),
                      seed=int(st.get("seed", 1)))[0]
        tab.append({"s": j.name, "mode": cfg["scenario"][j.name]["drift_mode"],
                    "n": r["trials"], "mean": _pm(r["mean_um"], r["mean_se_um"]),
                    "std": _pm(r["std_um"], r["std_se_um"]),
                    "max": _pm(r["max_um"], r["max_se_um"])})
    md = rt.markdown(tab, ["s", "mode", "n", "mean", "std", "max"],
                     ["scenario", "f on d12 d13 d23", "trials", "sphere: mean ± SE um",
                      "std ± SE um", "max ± SE um"])
    rt.write_tables(out, {"sphere_noise": md})
    print(md)
    print(f"results in {out}", file=sys.stderr)
    if args.update_readme:
        if args.smoke:
            raise SystemExit("--update-readme with --smoke would put smoke figures in the README")
        rt.update_readme(HERE / "README.md", {"sphere_noise": md})
    return 0


def _core_rows(runner: hpti.StudyRunner, keys: list, trials: int, scenario: str) -> list[dict]:
    """:func:`core_check` for the (case, damping_rel) pairs ``keys`` of one runner."""
    acc = {k: [0.0, 0.0, 0.0, 0.0] for k in range(len(keys))}
    for t in range(trials):
        data = runner.simulate(t)
        for k, (c, d) in enumerate(keys):
            t0 = time.perf_counter()
            ref = runner.estimate(data, c, damping_rel=d, by="study")
            t1 = time.perf_counter()
            got = runner.estimate(data, c, damping_rel=d, by="core")
            t2 = time.perf_counter()
            r = acc[k]
            r[0] = max(r[0], float(np.max(np.abs(got.errors_um(data) - ref.errors_um(data)))))
            r[1] = max(r[1], 1e3 * float(np.max(np.abs(
                np.subtract(got.instrument.geometry, ref.instrument.geometry)))))
            r[2] += t1 - t0
            r[3] += t2 - t1
    return [{"scenario": scenario,
             "case": c.label if len({d for _, d in keys}) == 1 else f"{c.label}, damping {d:g}",
             "trials": trials, "point": f"{r[0]:.2g}", "geometry": f"{r[1]:.2g}",
             "study_s": f"{r[2]:.2f}", "core_s": f"{r[3]:.2f}",
             "ratio": f"{r[3] / r[2]:.1f}" if r[2] > 0 else "-"}
            for (c, d), r in zip(keys, acc.values())]


def _cells(md: str) -> tuple[list[str], list[list[str]]]:
    """(header, rows) of a markdown table's cells, as printed."""
    rows = [[c.strip() for c in line.strip().strip("|").split("|")]
            for line in md.splitlines() if line.startswith("|")]
    return rows[0], rows[2:]


def _number(cell: str) -> float | None:
    """The value of a printed cell (before a '±'), None for text."""
    try:
        return float(cell.split("±")[0].strip())
    except ValueError:
        return None


def compare_tables(old: Path, new: Path) -> str:
    """Where two runs' tables (``tables.json`` files or the folders holding them) differ in
    their printed digits: per table and column, the cells that differ and the largest
    relative difference, with the row where it is largest (markdown)."""
    def load(path: Path) -> dict:
        f = path / "tables.json" if path.is_dir() else path
        if not f.is_file():
            raise SystemExit(f"{f}: no tables.json (a folder written by run.py, or the file)")
        return json.loads(f.read_text(encoding="utf-8"))

    a, b = load(old), load(new)
    rows = []
    for name in a:
        if name not in b:
            continue
        head, ra = _cells(a[name])
        head_b, rb = _cells(b[name])
        if head != head_b or len(ra) != len(rb):
            rows.append({"table": name, "column": "(layout)", "n": "-", "rel": "-",
                         "where": "headers or row count differ"})
            continue
        for j, col in enumerate(head):
            diff = []
            for x, y in zip(ra, rb):
                if x[j] == y[j]:
                    continue
                u, v = _number(x[j]), _number(y[j])
                d = abs(v - u) if u is not None and v is not None else np.inf
                diff.append((d / abs(u) if u else np.inf, d, x, y))
            if not diff:
                continue
            r, d, x, y = max(diff, key=lambda t: (t[0], t[1]))
            rows.append({"table": name, "column": col, "n": f"{len(diff)} of {len(ra)}",
                         "rel": f"{r:.3g}", "abs": f"{max(t[1] for t in diff):.3g}",
                         "where": f"{' / '.join(x[:2])}: {x[j]} -> {y[j]}"})
    if not rows:
        return "every printed cell of every table is the same"
    return rt.markdown(rows, ["table", "column", "n", "rel", "abs", "where"],
                       ["table", "column", "cells that differ", "largest relative difference",
                        "largest absolute difference", "where the relative one is (first "
                        "columns: old -> new)"])


def core_check(cfg: dict, trials: int, scenarios: list[str]) -> str:
    """Every NLP case (points-only, two-phase, joint) of the first ``trials`` trials of
    every scenario, and the damping sweep on its scenario, solved by the study's estimator
    and by volcal's core (:class:`hpti.CoreEstimator`): a markdown table of the largest
    difference of the point errors and of x1 x2 y2 (um), and the seconds each spent (one
    process; the ratio is the point, the machine's load sets the seconds)."""
    rows = []
    for sc in scenarios:
        runner = hpti.StudyRunner(cfg, sc, estimator="core")
        keys = [(c, 1e-5) for c in runner.cases if c.strategy != "sphere"]
        rows += _core_rows(runner, keys, trials, sc)
    if cfg.get("damping_sweep"):
        sweep = DampingJob(cfg)
        rows += _core_rows(sweep.runner, sweep.keys, trials, f"{sweep.scenario} (sweep)")
    total = [sum(float(r[k]) for r in rows) for k in ("study_s", "core_s")]
    rows.append({"scenario": "all", "case": "all", "trials": trials, "point": "-",
                 "geometry": "-", "study_s": f"{total[0]:.2f}", "core_s": f"{total[1]:.2f}",
                 "ratio": f"{total[1] / total[0]:.1f}" if total[0] > 0 else "-"})
    return rt.markdown(rows, ["scenario", "case", "trials", "point", "geometry", "study_s",
                              "core_s", "ratio"],
                       ["scenario", "case", "trials", "max abs point error diff um",
                        "max abs x1 x2 y2 diff um", "study s", "core s", "core / study"])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--smoke", action="store_true", help="a handful of trials (config "
                    "study.smoke_trials), output to a temporary folder unless --out is given")
    ap.add_argument("--trials", type=int, default=None, help="trials per scenario "
                    "(default: config study.trials)")
    ap.add_argument("--sweep-trials", type=int, default=None,
                    help="trials of the damping sweep (default: config damping_sweep.trials)")
    ap.add_argument("--workers", type=int, default=1, help="local worker processes")
    ap.add_argument("--out", type=Path, default=None, help="output folder")
    ap.add_argument("--config", type=Path, default=HERE / "config.toml")
    ap.add_argument("--scenarios", nargs="+", default=None,
                    help="scenario names (default: config study.scenarios)")
    ap.add_argument("--no-sweep", action="store_true", help="skip the damping sweep")
    ap.add_argument("--initial-accuracy-applies-to", choices=("points", "points+instrument"),
                    default=None, help="override study.initial_accuracy_applies_to")
    ap.add_argument("--summarize-only", action="store_true",
                    help="tables from the complete chunks on disk; compute nothing")
    ap.add_argument("--update-readme", action="store_true",
                    help="copy the tables into README.md's marked tables")
    ap.add_argument("--fixed-from", type=Path, default=None, metavar="CSV",
                    help="print (and with --update-readme write) the table1_fixed table "
                         "from a finished run's table_paper.csv; compute nothing")
    ap.add_argument("--noise-alternatives", action="store_true",
                    help="only the sphere intersection, on scenario `paper` (one f for the "
                         "three lasers) and `paper_per_laser` (own phases per laser); "
                         "--trials of each (default 1000)")
    ap.add_argument("--core-check", type=int, default=None, metavar="N",
                    help="print how far volcal's core (identify's problem and solvers) "
                         "agrees with the study's estimator on the points-only and two-phase "
                         "cases of trials 0..N-1; compute nothing else")
    ap.add_argument("--compare-tables", nargs=2, type=Path, default=None,
                    metavar=("OLD", "NEW"),
                    help="print where two runs' tables (tables.json or its folder) differ "
                         "in their printed digits; compute nothing")
    ap.add_argument("--estimator", choices=hpti.ESTIMATORS, default=None,
                    help="who solves the NLP strategies: volcal's core (default, config "
                         "study.estimator) or the study's own IPOPT problem; the chunks "
                         "record it")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    if args.compare_tables is not None:
        print(compare_tables(*args.compare_tables))
        return 0
    if args.core_check is not None:
        if args.core_check < 1:
            ap.error("--core-check: expected a number of trials >= 1")
        cfg = load_config(args.config)
        names = args.scenarios or list(cfg.get("study", {}).get("scenarios", ["paper"]))
        print(core_check(cfg, args.core_check, names))
        return 0
    if args.fixed_from is not None:
        tab = fixed_from_csv(args.fixed_from, load_config(args.config))
        print(tab)
        if args.update_readme:
            rt.update_readme(HERE / "README.md", {"table1_fixed": tab})
        return 0

    cfg = load_config(args.config)
    if args.noise_alternatives:
        return noise_alternatives(cfg, args)
    st = cfg.setdefault("study", {})
    if args.estimator:
        st["estimator"] = args.estimator
    if st.setdefault("estimator", "core") not in hpti.ESTIMATORS:
        raise SystemExit(f"{args.config}: study.estimator must be one of {hpti.ESTIMATORS}, "
                         f"got {st['estimator']!r}")
    if args.initial_accuracy_applies_to:
        st["initial_accuracy_applies_to"] = args.initial_accuracy_applies_to
    trials = args.trials or (int(st.get("smoke_trials", 4)) if args.smoke
                             else int(st.get("trials", 10000)))
    sw = cfg.get("damping_sweep")
    sweep_trials = args.sweep_trials or (int(sw.get("smoke_trials", 2)) if args.smoke
                                         else int(sw.get("trials", 300))) if sw else 0
    out = rt.output_folder(args.out, args.smoke, HERE / "results", "paper001")
    out.mkdir(parents=True, exist_ok=True)
    scenarios = args.scenarios or list(st.get("scenarios", cfg.get("scenario", {}).keys()))
    jobs = [ScenarioJob(cfg, sc, args.workers) for sc in scenarios]
    if sw and not args.no_sweep:
        jobs.append(DampingJob(cfg))
    want = {j.name: (sweep_trials if isinstance(j, DampingJob) else trials) for j in jobs}
    configured = dict(want)
    if args.summarize_only:
        want = {j.name: min(want[j.name], available_trials(out, j)) for j in jobs}
    chunk = int(st.get("chunk_trials", 250))
    B = int(st.get("bootstrap", 200))
    meta = {"trials": want, "workers": args.workers, "seed": int(st.get("seed", 1)),
            "estimator": st["estimator"],
            "chunk_trials": chunk,
            "initial_accuracy_applies_to": st.get("initial_accuracy_applies_to", "points"),
            "scenarios": {}, "python": platform.python_version(),
            "platform": platform.platform(), "cpu_count": os.cpu_count()}
    try:
        import casadi

        meta["casadi"] = casadi.__version__
    except Exception:  # pragma: no cover
        pass
    meta["numpy"] = np.__version__
    t_all = time.perf_counter()
    stats = run_jobs(jobs, want, out, chunk, progress=not args.no_progress,
                     compute=not args.summarize_only)

    tables: dict[str, str] = {}
    runinfo = []
    md = [f"# paper 001 study results\n\nseed {meta['seed']}, initial accuracy applied to "
          f"{meta['initial_accuracy_applies_to']}.\n"]
    for j in jobs:
        s, secs = stats[j.name]
        n = 0 if s is None else int(s["s1"].shape[0])
        runinfo.append({"job": j.name, "trials": n, "configured": configured[j.name],
                        "seconds": secs})
        if s is None:
            continue
        rows = summarize(s, j.labels, bootstrap=B, seed=meta["seed"])
        if isinstance(j, ScenarioJob):
            rows = case_rows(rows, j.cases)
            write_csv(out / f"table_{j.name}.csv", rows)
            tables[f"cases_{j.name}"] = cases_markdown(rows)
            tables[f"instrument_{j.name}"] = instrument_markdown(rows)
            (out / f"table_{j.name}.md").write_text(tables[f"cases_{j.name}"] + "\n",
                                                    encoding="utf-8")
            if j.name == "paper" and cfg.get("paper_table1"):
                tables["table1_paper"] = table1_markdown(rows, cfg["paper_table1"])
                tables["table1_fixed"] = fixed_markdown(rows, cfg["paper_table1"])
            per_trial = [{"trial": k, "case": lab, "mean_um": float(s["s1"][k, c] / s["n"][k, c]),
                          "max_um": float(s["mx"][k, c]), "success": bool(s["success"][k, c])}
                         for k in range(n) for c, lab in enumerate(j.labels)]
            write_csv(out / f"trials_{j.name}.csv.gz", per_trial)
            plot_errors(out / f"errors_{j.name}.png", s["hist"], j.cases, j.name, n)
            desc = cfg.get("scenario", {}).get(j.name, {}).get("description", "")
            meta["scenarios"][j.name] = {"trials": n, "seconds_this_run": secs,
                                         "description": desc}
        else:
            write_csv(out / "table_damping.csv", rows)
            tables["damping"] = damping_markdown(rows)
    jrows = jacobian_rows(cfg, scenarios[0] if scenarios else None)
    write_csv(out / "jacobian.csv", jrows)
    jtable = rt.markdown(jrows, ["case", "step", "unknowns", "readings", "rank", "redundancy",
                                 "null", "condition", "gauge_fixed", "unidentifiable"])
    (out / "jacobian.md").write_text(jtable + "\n", encoding="utf-8")
    tables["jacobian"] = jtable
    meta["seconds_computed_this_call"] = {r["job"]: r["seconds"] for r in runinfo}
    tables["runinfo"] = rt.markdown(runinfo, ["job", "trials", "configured"],
                                    ["job", "trials run", "trials configured"])
    for name, tab in tables.items():
        md.append(f"## {name}\n\n{tab}\n")
    meta["seconds_total"] = time.perf_counter() - t_all
    rt.write_tables(out, tables)
    (out / "summary.md").write_text("\n".join(md), encoding="utf-8")
    (out / "meta.json").write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
    print("\n".join(md))
    if args.update_readme:
        if args.smoke:
            raise SystemExit("--update-readme with --smoke would put smoke figures in the README")
        done = rt.update_readme(HERE / "README.md", tables)
        print(f"README.md: updated {', '.join(done) or 'nothing'}", file=sys.stderr)
    print(f"results in {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
