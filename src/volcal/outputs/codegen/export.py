"""Export of C solvers and C machine models (see :mod:`volcal.outputs.codegen`).

describe -> generate (CasADi C + hand-written driver, example, Makefile, README) ->
manifest with hashes -> build (make) -> load (:mod:`volcal.outputs.codegen.loader`).

An export folder whose manifest records the same inputs (model content, plan content,
stations table, options, volcal / CasADi versions) and whose files still have the
recorded hashes is reused: nothing is regenerated, ``make`` only rebuilds what is missing.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np
import pandas as pd

from volcal import __version__
from volcal.analysis.identify import Identifier, build_error_model, initial_stations
from volcal.base.exceptions import InputError
from volcal.measurement.budget import Budget, load_budget
from volcal.measurement.instruments import get_instrument
from volcal.measurement.tables import DataWarning, load_measurements, load_stations
from volcal.model.errors import Datum, ErrorModel
from volcal.model.machine import Machine
from volcal.model.spec import MachineSpec
from volcal.outputs.codegen import solver as S
from volcal.outputs.codegen import templates as T
from volcal.problem.residuals import Layout

log = logging.getLogger(__name__)

#: Version of the export layout (part of the manifest and of the input hash).
EXPORT_FORMAT = 1
MANIFEST = "manifest.json"
#: Strategies an export supports.
EXPORT_STRATEGIES = ("joint", "two-phase", "points-only")

#: Default run-time options baked into the C code (all can be changed at run time).
#: max_chi2 None: by strategy (MAX_CHI2), since only the joint fit reaches the noise level.
DEFAULT_OPTIONS = {
    "max_iter": 50,
    "tol_kkt": 1e-8,
    "tol_step": 1e-7,
    "tol_constraint": 1e-8,
    "max_chi2": None,
    "max_station_rms": 1.0,
}
#: Plausibility bound on chi2 per degree of freedom by strategy: the joint fit leaves the
#: noise (chi2 ~ 1 with a realistic budget); two-phase and points-only leave systematic
#: residuals of the stations fitted on nominal points (chi2 of 5-20 on the bundled example).
MAX_CHI2 = {"joint": 100.0, "two-phase": 1e4, "points-only": 1e4}

_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,40}$")


@dataclass
class ExportInfo:
    """An export folder: where, what, and whether it was reused.

    path: the folder; name: the C prefix; kind: ``"solver"`` or ``"model"``; manifest: the
    manifest as a dict; reused: True when an unchanged export was found and nothing was
    regenerated; export_seconds: time spent generating (0 when reused); build_seconds:
    time spent in ``make`` (None when not built).
    """

    path: Path
    name: str
    kind: str
    manifest: dict
    reused: bool
    export_seconds: float
    build_seconds: float | None = None

    @property
    def library(self) -> Path:
        return self.path / f"lib{self.name}.so"

    @property
    def static_library(self) -> Path:
        return self.path / f"lib{self.name}.a"

    @property
    def example(self) -> Path:
        return self.path / f"{self.name}_example"

    def load(self):
        """The compiled export as a Python object (:func:`volcal.outputs.codegen.loader.load`)."""
        from volcal.outputs.codegen.loader import load

        return load(self.path)


# ---------------------------------------------------------------------------------------
# helpers


def default_name(spec: MachineSpec) -> str:
    return "volcal_" + re.sub(r"[^A-Za-z0-9_]", "_", spec.name)


def _check_name(name: str) -> str:
    if not _NAME_RE.match(name):
        raise InputError(
            f"export name {name!r} is not a C identifier (letters, digits and "
            "'_', not starting with a digit, at most 41 characters)"
        )
    return name


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _file_sha(path: Path) -> str:
    return _sha(path.read_bytes())


def _c_str(s: str) -> str:
    return '"' + str(s).replace("\\", "\\\\").replace('"', '\\"') + '"'


def _c_list(values, fmt=str, per_line: int = 8) -> str:
    items = [fmt(v) for v in values]
    if not items:
        return "0"
    lines = [", ".join(items[i : i + per_line]) for i in range(0, len(items), per_line)]
    return "\n  " + ",\n  ".join(lines) + "\n"


def _c_double(v: float) -> str:
    return repr(float(v)) if np.isfinite(v) else "0.0"


def _generator_hash() -> str:
    """Hash of the code that writes an export (so that a changed generator never reuses an
    old export even when the version number did not change)."""
    h = hashlib.sha256()
    for mod in ("export.py", "solver.py", "templates.py"):
        h.update((Path(__file__).parent / mod).read_bytes())
    for f in T.template_files():
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def _versions() -> dict:
    return {
        "volcal": __version__,
        "casadi": ca.CasadiMeta.version(),
        "python": ".".join(map(str, sys.version_info[:3])),
        "generator": _generator_hash(),
    }


def _machine(model) -> Machine:
    return model if isinstance(model, Machine) else Machine.from_model(model)


def _model_label(model, spec: MachineSpec) -> str:
    return str(model) if isinstance(model, (str, Path)) else spec.name


def _budget_blob(b: Budget) -> str:
    return json.dumps(
        [
            [s.name, s.magnitude, s.unit, s.distribution, s.applies_to, s.k, s.per_metre]
            for s in b.sources
        ]
    )


def _load_plan(plan, spec: MachineSpec, st_table: pd.DataFrame | None):
    """(Measurements, has_lengths) from a plan: a measurement table with or without its
    length column (CSV path or DataFrame)."""
    if isinstance(plan, (str, Path)):
        path = Path(plan)
        if not path.is_file():
            raise InputError("no such plan file", source=str(plan))
        df = pd.read_csv(path, dtype={"station": str, "point": str}, skipinitialspace=True)
        name = str(path)
    elif isinstance(plan, pd.DataFrame):
        df, name = plan, "<plan DataFrame>"
    else:
        raise InputError(f"expected a plan CSV path or DataFrame, got {type(plan).__name__}")
    has_lengths = "length" in df.columns or "length_mm" in df.columns
    if not has_lengths:
        df = df.copy()
        df["length"] = 1.0  # placeholder: the layout is all that is read
    with warnings.catch_warnings():
        if not has_lengths:
            warnings.simplefilter("ignore", DataWarning)
        meas = load_measurements(df, spec, name=name, stations=st_table)
    return meas, has_lengths


def _layout_frame(meas, spec: MachineSpec) -> pd.DataFrame:
    t = meas.table
    cols = ["station", "point", *spec.axis_names, "tool_x", "tool_y", "tool_z"]
    return t[cols].copy()


def _reuse(out: Path, input_hash: str) -> dict | None:
    mf = out / MANIFEST
    if not mf.is_file():
        return None
    try:
        man = json.loads(mf.read_text())
    except (OSError, ValueError):
        return None
    if man.get("input_hash") != input_hash:
        return None
    for fname, h in man.get("files", {}).items():
        p = out / fname
        if not p.is_file() or _file_sha(p) != h:
            return None
    return man


def _write_files(out: Path, files: Mapping[str, str | bytes], manifest: dict) -> dict:
    """Write files through a temporary folder, then the manifest last (an interrupted
    export has no valid manifest and is regenerated next time)."""
    out.mkdir(parents=True, exist_ok=True)
    old = out / MANIFEST
    if old.exists():
        old.unlink()
    tmp = Path(tempfile.mkdtemp(prefix=".export-", dir=out))
    try:
        hashes = {}
        for fname, content in files.items():
            data = content.encode() if isinstance(content, str) else content
            (tmp / fname).write_bytes(data)
            hashes[fname] = _sha(data)
        for fname in files:
            os.replace(tmp / fname, out / fname)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    manifest["files"] = dict(sorted(hashes.items()))
    manifest["content_hash"] = _sha(json.dumps(manifest["files"], sort_keys=True).encode())
    fd, tmpname = tempfile.mkstemp(dir=out, suffix=".tmp")
    with os.fdopen(fd, "w") as fh:
        json.dump(manifest, fh, indent=2)
        fh.write("\n")
    os.replace(tmpname, out / MANIFEST)
    return manifest


def _generate_casadi(functions: list[ca.Function], name: str) -> dict[str, str]:
    """CasADi C for the functions: {file name: text} of <name>_generated.c/.h."""
    cg = ca.CodeGenerator(
        f"{name}_generated", {"with_header": True, "casadi_real": "double", "verbose": False}
    )
    for f in functions:
        cg.add(f)
    with tempfile.TemporaryDirectory() as d:
        cg.generate(d + os.sep)
        return {
            f"{name}_generated.c": (Path(d) / f"{name}_generated.c").read_text(),
            f"{name}_generated.h": (Path(d) / f"{name}_generated.h").read_text(),
        }


def _common(machine: Machine, em: ErrorModel, name: str, model) -> dict[str, str]:
    """The template values both exports fill: names, sizes, versions and the model
    (``model`` as the caller gave it, for its label)."""
    return {
        "volcal_version": __version__,
        "casadi_version": ca.CasadiMeta.version(),
        "model": _model_label(model, machine.spec),
        "fingerprint": machine.spec.fingerprint(),
        "NAME": name,
        "UNAME": name.upper(),
        "n_axes": str(machine.n_axes),
        "n_params": str(em.n_params),
        "n_errors": str(em.n_errors),
        "axis_names": _c_list(machine.axis_names, _c_str),
        "axis_rotary": _c_list([int(a.is_rotary) for a in machine.spec.axes]),
        "param_names": _c_list(em.param_names, _c_str),
        "param_units": _c_list(em.param_units, _c_str),
        "error_names": _c_list([s.name for s in em.errors], _c_str),
        "error_basis": em.summary(),
    }


def _manifest_model(model, machine: Machine) -> dict[str, Any]:
    """The manifest's description of the exported model."""
    spec = machine.spec
    return {
        "name": spec.name,
        "source": _model_label(model, spec),
        "fingerprint": spec.fingerprint(),
        "axes": machine.axis_names,
        "rotary": [bool(a.is_rotary) for a in spec.axes],
    }


def _reused(
    out: Path,
    name: str,
    kind: str,
    input_hash: str,
    build_it: bool,
    cc: str,
    cflags: str | None,
) -> ExportInfo | None:
    """The unchanged export of ``kind`` in ``out`` with this input hash (built again if
    asked, which ``make`` makes cheap), or None when there is none."""
    man = _reuse(out, input_hash)
    if man is None:
        return None
    info = ExportInfo(out, name, kind, man, True, 0.0)
    if build_it:
        info.build_seconds = build(out, cc=cc, cflags=cflags)
    return info


def _written(
    out: Path,
    name: str,
    kind: str,
    files: Mapping[str, str | bytes],
    manifest: dict,
    t0: float,
    build_it: bool,
    cc: str,
    cflags: str | None,
) -> ExportInfo:
    """Write the export's files and manifest (:func:`_write_files`), build if asked; ``t0``
    the export's start (``time.perf_counter``)."""
    manifest = _write_files(out, files, manifest)
    info = ExportInfo(out, name, kind, manifest, False, time.perf_counter() - t0)
    if build_it:
        info.build_seconds = build(out, cc=cc, cflags=cflags)
    return info


def _render(template: str, mapping: dict) -> str:
    return T.render(template, mapping)


# ---------------------------------------------------------------------------------------
# build


def build(path: str | Path, *, cc: str = "gcc", cflags: str | None = None, jobs: int = 2) -> float:
    """Run ``make`` in an export folder; returns the seconds it took.  ``cflags`` replaces
    the Makefile's CFLAGS (default ``-O2 -Wall -Werror``).  Raises RuntimeError with the
    compiler output when the build fails."""
    path = Path(path)
    cmd = ["make", "-C", str(path), f"-j{max(1, jobs)}", f"CC={cc}"]
    if cflags is not None:
        cmd.append(f"CFLAGS={cflags}")
    if shutil.which("make") is None or shutil.which(cc) is None:
        raise RuntimeError(f"building an export needs make and {cc} on the PATH")
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if proc.returncode:
        raise RuntimeError(f"building {path} failed:\n{proc.stdout}\n{proc.stderr}")
    return dt


# ---------------------------------------------------------------------------------------
# solver export


@dataclass
class SolverDefinition:
    """Everything an exported solver fixes (see :mod:`volcal.outputs.codegen.solver`)."""

    machine: Machine
    error_model: ErrorModel
    identifier: Identifier
    strategy: str
    budget: Budget
    layout: pd.DataFrame  # station, point, axes (file units), tool_x..z
    station_ids: list[str]
    station_index: np.ndarray
    phases: list[S.Phase]
    st_given: np.ndarray  # (K,) bool: start values from the stations table
    st_table: np.ndarray  # (K, 4)
    st0: np.ndarray  # (K, 4) start stations used for the analysis
    user_fixed: np.ndarray  # (n_x,) bool
    notes: list[str] = field(default_factory=list)

    @property
    def problem(self):
        return self.identifier.problem


def define_solver(
    model,
    plan,
    *,
    stations=None,
    strategy: str = "joint",
    degree: int = 3,
    datum: Datum = "iso230",
    budget: str | Path | Budget = "paper002",
    exact: bool = False,
) -> SolverDefinition:
    """Decide everything an exported solver fixes, from the model and the plan.

    plan: measurement table (CSV path or DataFrame) with or without lengths.  With lengths
    the start stations are computed as :func:`volcal.analysis.identify.identify` does; without,
    ``stations`` must give approximate positions (x_mm, y_mm, z_mm, dead_length_mm) of
    every station of the plan.  Stations marked ``fixed`` stay at their start values.
    """
    machine = _machine(model)
    st_table = None if stations is None else load_stations(stations)
    meas, has_lengths = _load_plan(plan, machine.spec, st_table)
    return _define(
        machine,
        meas,
        has_lengths,
        st_table,
        strategy=strategy,
        degree=degree,
        datum=datum,
        budget=budget,
        exact=exact,
    )


def _define(
    machine: Machine,
    meas,
    has_lengths: bool,
    st_table: pd.DataFrame | None,
    *,
    strategy: str,
    degree: int,
    datum: Datum,
    budget,
    exact: bool,
) -> SolverDefinition:
    if strategy not in EXPORT_STRATEGIES:
        raise InputError(
            f"strategy {strategy!r} cannot be exported; expected one of {list(EXPORT_STRATEGIES)}"
        )
    spec = machine.spec
    K = len(meas.station_ids)
    st_given = np.zeros(K, bool)
    st_tab = np.zeros((K, 4))
    st_fixed = np.zeros(K, bool)
    if st_table is not None:
        tab = st_table.set_index("station")
        for k, sid in enumerate(meas.station_ids):
            if sid in tab.index:
                row = tab.loc[sid]
                st_given[k] = True
                st_tab[k] = [row["x_mm"], row["y_mm"], row["z_mm"], row["dead_length_mm"]]
                st_fixed[k] = bool(row["fixed"])
    notes: list[str] = []
    if has_lengths:
        st0, _, n0 = initial_stations(machine, meas, st_table)
        notes += n0
    else:
        if not st_given.all():
            missing = [s for s, g in zip(meas.station_ids, st_given) if not g]
            raise InputError(
                "the plan has no lengths, so the stations table must give "
                f"approximate positions of every station; missing: {missing}"
            )
        st0 = st_tab.copy()
        notes.append("analysis at the approximate stations of the stations table")
    em = build_error_model(spec, degree=degree, datum=datum)
    bud = load_budget(budget)
    layout = Layout.from_measurements(meas)
    ider = Identifier(machine, em, layout, exact=exact)
    pr = ider.problem
    if has_lengths:
        sigma = S.analysis_sigma(machine, bud, meas, st0)
        length = meas.length
    else:
        # nominal distances stand in for the lengths (budget and analysis only)
        p0, _, _ = machine.evaluate(meas.q_internal, meas.tool, np.zeros(machine.n_errors))
        length, _ = get_instrument("tracker").evaluate(p0, st0[meas.station_index])
        sigma = S.analysis_sigma(machine, bud, dataclasses.replace(meas, length=length), st0)
    p = pr.pack_data(meas.q_internal, meas.tool, length, 1.0 / sigma)
    x0 = pr.pack_x(np.zeros(em.n_params), st0)
    user_fixed = ider.station_fixed(st_fixed)
    if strategy == "points-only":
        user_fixed[ider.is_station] = True
        notes.append("points-only: stations held at their start values")
    phases = S.plan_phases(ider, strategy, x0, p, user_fixed, solve=has_lengths)
    Cs = S.scaled_constraints(pr)
    for ph in phases:
        S.eliminate(ph, Cs)
    return SolverDefinition(
        machine,
        em,
        ider,
        strategy,
        bud,
        _layout_frame(meas, spec),
        list(meas.station_ids),
        np.asarray(meas.station_index),
        phases,
        st_given,
        st_tab,
        st0,
        user_fixed,
        notes,
    )


def solver_functions(d: SolverDefinition, name: str, *, linsol: str = "ldl") -> list[ca.Function]:
    pr, m, em = d.problem, d.machine, d.error_model
    K = len(d.station_ids)
    fs = [
        S.station_start_function(m, d.station_index, K, f"{name}_ca_station_start"),
        S.budget_sigma_function(m, d.budget, d.station_index, K, f"{name}_ca_budget_sigma"),
        S.residual_function(pr, f"{name}_ca_residual"),
        S.constraints_function(pr, f"{name}_ca_constraints"),
        S.model_function(m, em, f"{name}_ca_model", exact=pr.exact),
        S.error_values_function(m, em, f"{name}_ca_error_values"),
    ]
    for k, ph in enumerate(d.phases):
        fs.append(S.rows_function(pr, ph, f"{name}_ca_rows{k}"))
        fs.append(S.solve_function(pr, ph, f"{name}_ca_solve{k}", linsol=linsol))
        fs.append(S.project_function(pr, ph, f"{name}_ca_project{k}"))
    return fs


def export_solver(
    model,
    plan,
    out: str | Path,
    *,
    stations=None,
    strategy: str = "joint",
    degree: int = 3,
    datum: Datum = "iso230",
    budget: str | Path | Budget = "paper002",
    exact: bool = False,
    name: str | None = None,
    linsol: str = "ldl",
    options: dict | None = None,
    build_it: bool = True,
    force: bool = False,
    cc: str = "gcc",
    cflags: str | None = None,
) -> ExportInfo:
    """Export a C identification solver for a model and a plan (see the package doc).

    model: bundled model name, model file, spec or Machine; plan: measurement table (CSV
    or DataFrame; the length column, if any, is used only for the start stations of the
    export-time analysis); stations: optional stations table (start values, fixed
    stations; required when the plan has no lengths); strategy: joint, two-phase or
    points-only; degree, datum: the error model; budget: weights of readings without
    sigma; name: C prefix (default ``volcal_<model>``); linsol: CasADi linear solver of
    the Gauss-Newton system (``ldl`` or ``qr``); options: run-time option defaults baked
    into the C code (see ``DEFAULT_OPTIONS``); build_it: run ``make``; force: regenerate
    even when an unchanged export exists.
    """
    t0 = time.perf_counter()
    out = Path(out)
    machine = _machine(model)
    spec = machine.spec
    name = _check_name(name or default_name(spec))
    if linsol not in ("ldl", "qr"):
        raise InputError(f"linsol must be 'ldl' or 'qr', got {linsol!r}")
    opts: dict[str, Any] = dict(DEFAULT_OPTIONS)
    unknown = sorted(set(options or {}) - set(opts))
    if unknown:
        raise InputError(f"unknown solver option(s) {unknown}; options: {sorted(opts)}")
    opts.update(options or {})
    if opts["max_chi2"] is None:
        opts["max_chi2"] = MAX_CHI2.get(strategy, 100.0)
    bud = load_budget(budget)
    st_table = None if stations is None else load_stations(stations)
    meas, has_lengths = _load_plan(plan, spec, st_table)

    # ---- input hash (everything the generated files depend on)
    h = hashlib.sha256()
    h.update(
        json.dumps(
            {
                "format": EXPORT_FORMAT,
                "kind": "solver",
                "name": name,
                "model": spec.fingerprint(),
                "strategy": strategy,
                "degree": degree,
                "datum": datum,
                "budget": _budget_blob(bud),
                "exact": exact,
                "linsol": linsol,
                "options": opts,
                "versions": _versions(),
            },
            sort_keys=True,
        ).encode()
    )
    lay = _layout_frame(meas, spec)
    h.update(lay.to_csv(index=False).encode())
    if has_lengths:
        h.update(np.ascontiguousarray(meas.length).tobytes())
        h.update(np.ascontiguousarray(np.nan_to_num(meas.sigma, nan=-1.0)).tobytes())
    if st_table is not None:
        h.update(st_table.to_csv(index=False).encode())
    input_hash = h.hexdigest()

    if not force:
        reused = _reused(out, name, "solver", input_hash, build_it, cc, cflags)
        if reused is not None:
            return reused

    d = _define(
        machine,
        meas,
        has_lengths,
        st_table,
        strategy=strategy,
        degree=degree,
        datum=datum,
        budget=bud,
        exact=exact,
    )
    pr, em = d.problem, d.error_model
    funcs = solver_functions(d, name, linsol=linsol)
    files = _generate_casadi(funcs, name)
    K, N = len(d.station_ids), len(d.layout)
    keys = list(zip(d.layout["station"], d.layout["point"]))
    n_a = [S.theta_block(pr, ph).shape[1] for ph in d.phases]
    mp = _common(machine, em, name, model)
    mp.update(
        {
            "n_readings": str(N),
            "n_stations": str(K),
            "n_poses": str(d.layout["point"].nunique()),
            "strategy": strategy,
            "degree": str(degree),
            "datum": datum,
            "budget": bud.name,
            "n_phases": str(len(d.phases)),
            "n_x": str(pr.n_x),
            "n_p": str(pr.nlp["p"].shape[0]),
            "n_constraints": str(pr.C.shape[0]),
            "station_ids": _c_list(d.station_ids, _c_str),
            "reading_station": _c_list(d.station_index.tolist(), per_line=24),
            "reading_point": _c_list(d.layout["point"].tolist(), _c_str, per_line=10),
            "plan_keys_unique": str(int(len(set(keys)) == len(keys))),
            "scale": _c_list(pr.scale, _c_double, per_line=6),
            "st_given": _c_list(d.st_given.astype(int).tolist()),
            "st_table": _c_list(d.st_table.ravel(), _c_double, per_line=4),
            "n_z": _c_list([ph.n_z for ph in d.phases]),
            "rows_fns": ", ".join(f"{name}_ca_rows{k}" for k in range(len(d.phases))),
            "solve_fns": ", ".join(f"{name}_ca_solve{k}" for k in range(len(d.phases))),
            "n_a": _c_list(n_a),
            "n_a_max": str(max(n_a)),
            "project_fns": ", ".join(f"{name}_ca_project{k}" for k in range(len(d.phases))),
            "work_fns": ",\n  ".join(f"{f.name()}_work" for f in funcs),
            "max_iter": str(int(opts["max_iter"])),
        }
    )
    for k in ("tol_kkt", "tol_step", "tol_constraint", "max_chi2", "max_station_rms"):
        mp[k] = _c_double(opts[k])
    files[f"{name}.h"] = _render("solver.h.j2", mp)
    files[f"{name}.c"] = _render("solver.c.j2", mp)
    files["main.c"] = _render("solver_main.c.j2", mp)
    files["Makefile"] = _render("Makefile.j2", mp)
    files["plan.csv"] = d.layout.to_csv(index=False)
    names = np.asarray(pr.names)
    phases = [
        {
            "name": ph.name,
            "fixed": names[ph.fixed].tolist(),
            "zero": names[ph.zero].tolist(),
            "n_free": int((~ph.fixed).sum()),
            "n_reduced": ph.n_z,
            "basic": names[ph.basic].tolist(),
        }
        for ph in d.phases
    ]
    files["README.md"] = _readme_solver(d, name, mp, phases, opts, linsol)
    manifest = {
        "format": EXPORT_FORMAT,
        "kind": "solver",
        "name": name,
        "model": _manifest_model(model, machine),
        "plan": {
            "n_readings": N,
            "n_stations": K,
            "station_ids": d.station_ids,
            "has_lengths": has_lengths,
            "sha256": _sha(lay.to_csv(index=False).encode()),
        },
        "options": {
            "strategy": strategy,
            "degree": degree,
            "datum": datum,
            "budget": bud.name,
            "exact": exact,
            "linsol": linsol,
            "stations_table": st_table is not None,
            "runtime_defaults": opts,
        },
        "sizes": {
            "n_x": pr.n_x,
            "n_theta": pr.n_theta,
            "n_errors": em.n_errors,
            "n_axes": machine.n_axes,
            "n_constraints": int(pr.C.shape[0]),
            "n_p": int(pr.nlp["p"].shape[0]),
        },
        "parameters": {"names": list(em.param_names), "units": list(em.param_units)},
        "errors": [s.name for s in em.errors],
        "variables": list(pr.names),
        "scale": pr.scale.tolist(),
        "phases": phases,
        "start_stations": {
            "given": d.st_given.tolist(),
            "table": d.st_table.tolist(),
            "analysis": d.st0.tolist(),
        },
        "notes": d.notes,
        "versions": _versions(),
        "input_hash": input_hash,
        "export_seconds": None,
    }
    manifest["export_seconds"] = round(time.perf_counter() - t0, 3)
    return _written(out, name, "solver", files, manifest, t0, build_it, cc, cflags)


# ---------------------------------------------------------------------------------------
# model export


def export_model(
    model,
    out: str | Path,
    *,
    degree: int = 3,
    datum: Datum = "iso230",
    exact: bool = False,
    name: str | None = None,
    build_it: bool = True,
    force: bool = False,
    cc: str = "gcc",
    cflags: str | None = None,
) -> ExportInfo:
    """Export the model function alone (tool point, volumetric error and Jacobians) for
    controllers that only evaluate a compensation.  Parameters as :func:`export_solver`."""
    t0 = time.perf_counter()
    out = Path(out)
    machine = _machine(model)
    spec = machine.spec
    name = _check_name(name or default_name(spec))
    input_hash = _sha(
        json.dumps(
            {
                "format": EXPORT_FORMAT,
                "kind": "model",
                "name": name,
                "model": spec.fingerprint(),
                "degree": degree,
                "datum": datum,
                "exact": exact,
                "versions": _versions(),
            },
            sort_keys=True,
        ).encode()
    )
    if not force:
        reused = _reused(out, name, "model", input_hash, build_it, cc, cflags)
        if reused is not None:
            return reused
    em = build_error_model(spec, degree=degree, datum=datum)
    funcs = [
        S.model_function(machine, em, f"{name}_ca_model", exact=exact),
        S.error_values_function(machine, em, f"{name}_ca_error_values"),
    ]
    files = _generate_casadi(funcs, name)
    mp = _common(machine, em, name, model)
    mp.update(
        {
            "degree": str(degree),
            "datum": datum,
        }
    )
    files[f"{name}.h"] = _render("model.h.j2", mp)
    files[f"{name}.c"] = _render("model.c.j2", mp)
    files["main.c"] = _render("model_main.c.j2", mp)
    files["Makefile"] = _render("Makefile.j2", mp)
    files["README.md"] = _render("README_model.md.j2", mp)
    manifest = {
        "format": EXPORT_FORMAT,
        "kind": "model",
        "name": name,
        "model": _manifest_model(model, machine),
        "options": {"degree": degree, "datum": datum, "exact": exact},
        "sizes": {"n_theta": em.n_params, "n_errors": em.n_errors, "n_axes": machine.n_axes},
        "parameters": {"names": list(em.param_names), "units": list(em.param_units)},
        "errors": [s.name for s in em.errors],
        "versions": _versions(),
        "input_hash": input_hash,
        "export_seconds": round(time.perf_counter() - t0, 3),
    }
    return _written(out, name, "model", files, manifest, t0, build_it, cc, cflags)


def _readme_solver(
    d: SolverDefinition, name: str, mp: dict, phases: list[dict], opts: dict, linsol: str
) -> str:
    lines = []
    for k, ph in enumerate(phases):
        fixed = ", ".join(ph["fixed"]) if ph["fixed"] else "none"
        if len(ph["fixed"]) > 30:
            fixed = ", ".join(ph["fixed"][:30]) + f", ... ({len(ph['fixed'])} in all)"
        zero = ", ".join(ph["zero"]) if ph["zero"] else "none"
        lines.append(
            f"- phase {k} ({ph['name']}): {ph['n_free']} free variables, "
            f"{ph['n_reduced']} after eliminating the datum constraints; fixed: "
            f"{fixed}; of these held at zero: {zero}"
        )
    m = dict(mp)
    m["phase_lines"] = "\n".join(lines)
    m["linsol"] = linsol
    m["start_rule"] = (
        "from the stations table given at export"
        if d.st_given.all()
        else "computed from the readings on the nominal points (linear solution of the squared "
        "range equations, then Gauss-Newton on the range residual), as volcal's "
        "`identify` does"
        + (" (stations in the export's stations table: from the table)" if d.st_given.any() else "")
    )
    for k, v in opts.items():
        m[f"opt_{k}"] = str(v)
    return _render("README_solver.md.j2", m)
