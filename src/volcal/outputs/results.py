"""The outputs of an identification: the result folder, and predictions from it.

:func:`save_result` writes the folder DESIGN.md fixes for ``volcal identify``:

=========================  ==================================================================
file                       content
=========================  ==================================================================
``parameters.csv``         ``name, value, unit, u, identifiable, imposed``: every parameter
                           (basis coefficient of an error quantity) in um / urad (``unit``
                           says which); ``u`` its standard uncertainty (empty for
                           unidentifiable parameters: their values are one representative
                           of what the data allow, not determined);
                           ``imposed``: set to zero by the datum (a convention, u = 0, not
                           a measurement; the conditions are in ``datum.csv``)
``stations.csv``           the identified stations: ``station, x_mm, y_mm, z_mm,
                           dead_length_mm`` (+ their standard uncertainties ``u_x_um`` ...
                           ``u_dead_length_um``, ``fixed``)
``residuals.csv``          the validated input rows plus ``residual_um`` (model - measured),
                           ``normalised_residual`` (residual / sigma) and ``rejected``
``component_errors.csv``   per axis, on a grid over its travel: ``axis``, ``position_mm``
                           (linear axes) or ``position_deg`` (rotary axes), then one column
                           per component error motion of that axis with its unit
                           (``EXX_um``, ``EAX_urad``) and its standard uncertainty
                           (``u_EXX_um``); cells of other axes' errors are empty
``error_motions.csv``      per component error motion: ``axis``, ``error_motion``,
                           ``description``, ``unit`` (um / urad), ``peak_to_peak_in_unit``
                           over the travel and its standard uncertainty, the extremes and
                           where they lie (``axis_unit``: mm / deg)
``volumetric_grid.csv``    a grid over the box of the linear axes and, on a coarse grid,
                           the rotary axes' whole travel (tool offset (0, 0, 0) mm): axis columns
                           (mm / deg), ``dx_um, dy_um, dz_um``, ``u_dx_um, u_dy_um,
                           u_dz_um`` and ``norm_um``
``report.md``              the human-readable report (links the plots)
``result.json``            everything :func:`load_result` needs to predict (no pickle)
``instruments.csv``        only with several tables (:mod:`volcal.analysis.fusion`): per
                           table its instrument, readings, degrees of freedom, chi2/dof,
                           its 99.9 % interval, verdict and (``--variance-components``)
                           the budget's scale factor with its uncertainty
``order_selection.csv``    only with ``--degree auto``: every candidate order per axis and
                           its criterion value (:mod:`volcal.workflow.orders`)
``component_errors.png``   the component error motions with +-2 u bands
``volumetric_map.png``     2-D slice maps of the volumetric error (|d| in colour, in-plane
                           arrows): XY at several heights, and per rotary axis at several
                           angles
``residuals.png``          residual histogram, normal QQ plot of the standardised
                           residuals, residuals per reading by station
``correlations.png``       correlations of the identifiable parameters (basis coefficients)
``residuals_vs_axes.png``  normalised residuals against each axis position, binned means
=========================  ==================================================================

The report opens with the **model adequacy** test (:mod:`volcal.analysis.adequacy`):
chi2/dof against its 99.9 % interval and, when outside, the likely cause (residual
structure against one axis, outliers, the uncertainty budget); result.json holds it under
``adequacy``.

Every value is an **error** (actual - nominal, ISO 230-1); a correction is its negative.
Uncertainties are standard uncertainties (k = 1) of the linearised covariance.  A
component error motion that involves an unidentifiable parameter has no uncertainty
(empty ``u_`` cells): the data do not determine it.  Volumetric uncertainties propagate
the identifiable parameters only (as :meth:`IdentificationResult.predict` does).

Writing is atomic: everything goes into a hidden temporary folder next to ``out_dir``
that is renamed into place once complete; an existing ``out_dir`` is replaced only after
that, and only if it is empty or a previous result folder.

:func:`load_result` reads ``result.json`` back (machine rebuilt from the saved model
document, error model from the saved forms and datum) into a :class:`LoadedResult`
whose :meth:`~LoadedResult.predict` takes a points table in file units (mm / deg).
"""

from __future__ import annotations

import json
import logging
import math
import platform
import re
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from json.encoder import encode_basestring_ascii as _encode_str
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from volcal import __version__
from volcal.analysis.adequacy import STRUCTURE_P, assess
from volcal.analysis.identifiability import FieldNullSpace
from volcal.analysis.identify import IdentificationResult, SolverState, predict_volumetric
from volcal.base import progress
from volcal.base.exceptions import InputError
from volcal.base.units import REPORT
from volcal.model.errors import ErrorForm, ErrorModel
from volcal.model.machine import Machine
from volcal.model.spec import MachineSpec, machine_from_dict, spec_to_dict

if TYPE_CHECKING:
    from volcal.outputs.plot_process import PlotProcess

log = logging.getLogger(__name__)

__all__ = [
    "save_result",
    "load_result",
    "LoadedResult",
    "check_out_dir",
    "read_points",
    "component_error_table",
    "error_motion_table",
    "error_motions_at_positions",
    "positions_text",
    "volumetric_grid_table",
    "RESULT_FORMAT",
    "RESULT_FORMAT_VERSION",
    "DATA_FILES",
    "PLOT_FILES",
    "RESULT_FILES",
]

#: ``format`` marker of result.json
RESULT_FORMAT = "volcal-identification-result"
#: version of the result.json layout this module writes and reads
RESULT_FORMAT_VERSION = 3  # 2: datum conditions and the null space's action on the field
# 3: solver_state.npz (unknowns, held set, weights, datum in force, problem fingerprint)
DATA_FILES = (
    "parameters.csv",
    "stations.csv",
    "residuals.csv",
    "datum.csv",
    "component_errors.csv",
    "error_motions.csv",
    "volumetric_grid.csv",
    "report.md",
    "result.json",
)
PLOT_FILES = (
    "component_errors.png",
    "volumetric_map.png",
    "residuals.png",
    "residuals_vs_axes.png",
    "correlations.png",
)
RESULT_FILES = DATA_FILES + PLOT_FILES
#: written only by some runs (``order_selection.csv``: ``--degree auto``)
OPTIONAL_FILES = ("order_selection.csv", "solver_state.npz")

#: positions per linear axis of the volumetric grid
GRID_POINTS = 7
#: at most this many positions per linear axis of the volumetric grid of a model with
#: rotary axes (whose grid also spans the rotary axes' travel: 40-48 rotary poses per
#: linear position)
GRID_POINTS_WITH_ROTARY = 5
#: positions per axis of the component error table
COMPONENT_POINTS = 41
#: positions per axis on which the peak-to-peak value of each error motion is found
PEAK_POINTS = 401
#: positions per axis of the printed error-motion tables (report.md, HTML report): every
#: tenth of the travel, as ISO 230-1 reports and tracker software print them
TABLE_POSITIONS = 11

_VOL = ["dx_um", "dy_um", "dz_um"]
_UVOL = ["u_dx_um", "u_dy_um", "u_dz_um"]


def _unit_factor(unit: str) -> tuple[float, str]:
    """Internal unit (mm / rad) -> (factor, report unit) (um / urad)."""
    return REPORT[unit]


def _axis_unit(spec: MachineSpec, name: str) -> str:
    return "deg" if spec.axis(name).is_rotary else "mm"


# --------------------------------------------------------------------------------------
# tables


def _axis_sweeps(error_model: ErrorModel, n: int):
    """Per axis with component error motions: (axis spec, positions (n,) in file units
    mm / deg over its travel, indices of its component errors, their rows of the basis
    (n, len(indices), n_params) at those positions with the other axes at their
    reference).  The one set-up of :func:`component_error_table` and
    :func:`error_motion_table`."""
    em = error_model
    spec = em.spec
    ref = np.array([np.deg2rad(a.reference) if a.is_rotary else a.reference for a in spec.axes])
    for j, a in enumerate(spec.axes):
        comps = [k for k, s in enumerate(em.errors) if s.axis == a.name and s.kind == "component"]
        if not comps:
            continue
        pos = np.linspace(a.travel[0], a.travel[1], n)
        q = np.tile(ref, (n, 1))
        q[:, j] = np.deg2rad(pos) if a.is_rotary else pos
        yield a, pos, comps, em.basis(q, comps)


def component_error_table(
    error_model: ErrorModel,
    theta: np.ndarray,
    cov_theta: np.ndarray | None = None,
    identifiable: np.ndarray | None = None,
    n: int = COMPONENT_POINTS,
) -> pd.DataFrame:
    """Component error motions on ``n`` positions over each axis' travel.

    Columns: ``axis``, ``position_mm`` and/or ``position_deg`` (file units), then per
    component error of every axis (chain order) ``<name>_um`` or ``<name>_urad``, then
    the standard uncertainties ``u_<name>_<unit>`` (present when ``cov_theta`` is given).
    Cells of errors that belong to another axis are NaN, and so is the uncertainty of an
    error that involves a parameter marked not ``identifiable``.  Location errors
    (constants) are not listed here: they are in the parameter table.
    """
    em = error_model
    spec = em.spec
    theta = np.asarray(theta, float)
    ident = np.ones(em.n_params, bool) if identifiable is None else np.asarray(identifiable, bool)
    cov = None if cov_theta is None else np.nan_to_num(np.asarray(cov_theta, float))
    frames, value_cols, u_cols, pos_cols = [], [], [], []
    for a, pos, comps, B in _axis_sweeps(em, n):
        unit = _axis_unit(spec, a.name)
        df = pd.DataFrame({"axis": a.name, f"position_{unit}": pos})
        if f"position_{unit}" not in pos_cols:
            pos_cols.append(f"position_{unit}")
        for i, k in enumerate(comps):
            s = em.errors[k]
            f, u_name = _unit_factor(s.unit)
            col = f"{s.name}_{u_name}"
            df[col] = B[:, i, :] @ theta * f
            value_cols.append(col)
            if cov is not None:
                var = np.einsum("np,pq,nq->n", B[:, i, :], cov, B[:, i, :])
                u = np.sqrt(np.clip(var, 0.0, None)) * f
                if not ident[em.param_error_arr == k].all():
                    u[:] = np.nan
                df[f"u_{col}"] = u
                u_cols.append(f"u_{col}")
        frames.append(df)
    pos_cols = [c for c in ("position_mm", "position_deg") if c in pos_cols]
    cols = ["axis", *pos_cols, *value_cols, *u_cols]
    if not frames:
        return pd.DataFrame(columns=cols)
    return pd.concat(frames, ignore_index=True)[cols]


def describe_error_motion(spec: MachineSpec, symbol: Any) -> str:
    """What an ISO 230-1 component error motion is, in words (``EXX``: "positioning error
    of X"; ``EYX``: "straightness of X in Y"; ``EBX``: "tilt of X about B")."""
    axis = spec.axis(symbol.axis)
    own = symbol.component == axis.dir_index
    letter = ("XYZ" if symbol.quantity == "translation" else "ABC")[symbol.component]
    if not axis.is_rotary:
        if symbol.quantity == "translation":
            return (
                f"positioning error of {axis.name}"
                if own
                else (f"straightness of {axis.name} in {letter}")
            )
        return f"roll of {axis.name}" if own else f"tilt of {axis.name} about {letter}"
    if symbol.quantity == "translation":
        if own:
            return f"axial motion of {axis.name}"
        return f"radial motion of {axis.name} in {letter}"
    return (
        f"angular positioning error of {axis.name}"
        if own
        else (f"tilt of {axis.name} about {letter}")
    )


def error_motion_table(
    error_model: ErrorModel,
    theta: np.ndarray,
    cov_theta: np.ndarray | None = None,
    identifiable: np.ndarray | None = None,
    n: int = PEAK_POINTS,
) -> pd.DataFrame:
    """The peak-to-peak value of every component error motion over its axis' travel (other
    axes at their reference), as ISO 230-1 reports it: one row per motion, chain order.

    Columns: ``axis``, ``error_motion`` (ISO name), ``description``, ``unit`` (um or urad:
    the unit of every ``*_in_unit`` column), ``peak_to_peak_in_unit`` (largest minus
    smallest value on ``n`` evenly spaced positions), ``u_peak_to_peak_in_unit`` (its
    standard uncertainty, k = 1, propagated through the two positions; empty where the
    motion involves an unidentifiable parameter or without ``cov_theta``),
    ``min_in_unit``, ``max_in_unit``, ``axis_unit`` (mm or deg) and
    ``position_of_min_in_axis_unit``, ``position_of_max_in_axis_unit``.  Location errors
    (constants) have no peak-to-peak value and are not listed."""
    em = error_model
    spec = em.spec
    theta = np.asarray(theta, float)
    ident = np.ones(em.n_params, bool) if identifiable is None else np.asarray(identifiable, bool)
    cov = None if cov_theta is None else np.nan_to_num(np.asarray(cov_theta, float))
    rows = []
    for a, pos, comps, B in _axis_sweeps(em, n):
        for i, k in enumerate(comps):
            s = em.errors[k]
            f, u_name = _unit_factor(s.unit)
            y = B[:, i, :] @ theta * f
            y[np.abs(y) < 1e-9] = 0.0  # rounding noise of a value the datum makes zero
            lo, hi = int(np.argmin(y)), int(np.argmax(y))
            u = float("nan")
            if cov is not None and ident[em.param_error_arr == k].all():
                d = B[hi, i, :] - B[lo, i, :]
                u = float(np.sqrt(max(float(d @ cov @ d), 0.0))) * f
            rows.append(
                {
                    "axis": a.name,
                    "error_motion": s.name,
                    "description": describe_error_motion(spec, s),
                    "unit": u_name,
                    "peak_to_peak_in_unit": float(y[hi] - y[lo]),
                    "u_peak_to_peak_in_unit": u,
                    "min_in_unit": float(y[lo]),
                    "max_in_unit": float(y[hi]),
                    "axis_unit": _axis_unit(spec, a.name),
                    "position_of_min_in_axis_unit": float(pos[lo]),
                    "position_of_max_in_axis_unit": float(pos[hi]),
                }
            )
    cols = [
        "axis",
        "error_motion",
        "description",
        "unit",
        "peak_to_peak_in_unit",
        "u_peak_to_peak_in_unit",
        "min_in_unit",
        "max_in_unit",
        "axis_unit",
        "position_of_min_in_axis_unit",
        "position_of_max_in_axis_unit",
    ]
    return pd.DataFrame(rows, columns=cols)


def error_motions_at_positions(
    component_table: pd.DataFrame, n: int = TABLE_POSITIONS
) -> list[tuple[str, pd.DataFrame]]:
    """The printed tables of the error motions at positions along each axis: per axis
    ``(axis, table)`` with the position column and that axis' error-motion columns of
    ``component_table`` (:func:`component_error_table`, e.g. read back from
    component_errors.csv), on ``n`` of its rows evenly spread over the travel (every fourth
    of the 41 rows by default: exact rows, nothing interpolated)."""
    out = []
    t = component_table
    axes = t["axis"].astype(str).to_numpy()
    # the position and motion columns, tested for NaN once for the whole table (pandas'
    # operations on each axis' rows and column cost more than the rest of the report)
    cands = [c for c in t.columns if c != "axis" and not str(c).startswith("u_")]
    missing = t[cands].isna().to_numpy()
    for axis in dict.fromkeys(axes.tolist()):
        at = np.flatnonzero(axes == axis)
        full = ~missing[at].any(axis=0)
        keep = [c for c, ok in zip(cands, full) if ok]
        if len(keep) < 2:  # a position column and at least one motion
            continue
        rows = np.unique(np.round(np.linspace(0, len(at) - 1, min(n, len(at)))).astype(int))
        out.append((axis, t.iloc[at[rows]][keep].reset_index(drop=True)))
    return out


def positions_text(table: pd.DataFrame) -> str:
    """How the positions of one table of :func:`error_motions_at_positions` are spread,
    computed from them: ``every 50 mm (a tenth of the travel)`` when evenly spaced, else
    ``at the positions listed (not evenly spaced: the table's rows do not divide the
    travel into equal steps)``."""
    pos = table.iloc[:, 0].to_numpy(float)
    unit = str(table.columns[0]).rpartition("_")[2]
    if len(pos) < 2:
        return "at one position"
    step = np.diff(pos)
    span = pos[-1] - pos[0]
    if not np.allclose(step, step[0], rtol=1e-6, atol=1e-9 * max(abs(span), 1.0)):
        return (
            "at the positions listed (not evenly spaced: the table's rows do not divide the "
            "travel into equal steps)"
        )
    parts = len(step)
    share = {2: "half", 4: "quarter", 10: "tenth"}.get(parts, f"1/{parts}")
    return f"every {step[0]:g} {unit} (a {share} of the travel)"


def volumetric_grid_table(
    machine: Machine,
    error_model: ErrorModel,
    theta: np.ndarray,
    cov_theta: np.ndarray | None = None,
    n: int = GRID_POINTS,
    *,
    rotary: bool = True,
) -> pd.DataFrame:
    """Volumetric error on a grid over the workspace, tool offset (0, 0, 0) mm: ``n`` positions per
    linear axis over its travel (at most :data:`GRID_POINTS_WITH_ROTARY` for a model with
    rotary axes) and, with ``rotary`` (default), the rotary axes over their whole travel
    on the coarse grid of :func:`volcal.measurement.plans.summary_grid` (8 angles 45 deg apart for a
    full turn; 5 evenly spaced angles plus the reference for a partial travel); without
    ``rotary`` the rotary axes stay at their reference.  Columns: the axes (mm / deg),
    ``dx_um, dy_um, dz_um``, ``u_dx_um, u_dy_um, u_dz_um`` (with ``cov_theta``) and
    ``norm_um`` (length of the error vector)."""
    from volcal.measurement.plans import grid_plan, summary_grid

    spec = machine.spec
    if rotary and any(a.is_rotary for a in spec.axes):
        grid = summary_grid(spec, min(int(n), GRID_POINTS_WITH_ROTARY))
    else:
        grid = grid_plan(spec, {a.name: (1 if a.is_rotary else n) for a in spec.axes})
    q = machine.axis_to_internal(grid.to_numpy(float))
    pred = predict_volumetric(machine, error_model, theta, cov_theta, q)
    out = grid.copy()
    for c in pred.columns:
        out[c] = pred[c].to_numpy()
    out["norm_um"] = np.linalg.norm(pred[_VOL].to_numpy(), axis=1)
    return out


# --------------------------------------------------------------------------------------
# points table (input of predict)


def read_points(
    points: str | Path | pd.DataFrame, spec: MachineSpec, *, name: str | None = None
) -> tuple[pd.DataFrame, np.ndarray, np.ndarray]:
    """Validate a points table for prediction (CSV path or DataFrame; never modified).

    Columns: one per model axis (``X`` or ``X_mm``, ``B`` or ``B_deg``; mm / deg,
    required), ``tool_x, tool_y, tool_z`` (or ``tool_x_mm`` ...; mm, optional, default
    0) and ``point`` (text id, optional).  Any other column is an error, as are missing
    or non-numeric values and axis positions outside the travel (tolerance
    :data:`volcal.measurement.tables.TRAVEL_TOLERANCE` x travel range): :class:`InputError`
    naming the file, row (header = row 1) and column.

    Returns (table with the input's columns and names in input order, q (N, n_axes) in
    file units, tool (N, 3) mm).
    """
    from volcal.measurement import tables as _data

    raw = _data.read_raw(points, name, "points table")
    problems = _data.Problems(raw.name)
    schema = [_data.Column("point", (), False, "id")]
    for a in spec.axes:
        u = _axis_unit(spec, a.name)
        schema.append(_data.Column(a.name, (f"{a.name}_{u}",), True, "float", u))
    schema += [_data.Column(f"tool_{c}", (f"tool_{c}_mm",), False, "float", "mm") for c in "xyz"]
    pos = _data.resolve_columns(
        raw, schema, problems, axis_names=spec.axis_names, model_name=spec.name
    )
    body, rows = raw.body, raw.rows
    values: dict[str, np.ndarray] = {}
    q = np.empty((len(rows), len(spec.axes)))
    for j, a in enumerate(spec.axes):
        label = raw.header[pos[a.name]]
        u = _axis_unit(spec, a.name)
        v = _data.parse_float(body[pos[a.name]], rows, label, u, False, problems)
        lo, hi = a.travel
        tol = _data.TRAVEL_TOLERANCE * (hi - lo)
        _data.report_rows(
            problems,
            rows,
            (v < lo - tol) | (v > hi + tol),
            label,
            lambda k, v=v, a=a, lo=lo, hi=hi, u=u: (
                f"{a.name} = {v[k]:g} {u} is outside the travel [{lo:g}, {hi:g}] {u} "
                f"of axis {a.name}; the identified error model does not extrapolate"
            ),
        )
        q[:, j] = v
        values[a.name] = v
    tool = np.zeros((len(rows), 3))
    for j, c in enumerate(("tool_x", "tool_y", "tool_z")):
        if c in pos:
            tool[:, j] = _data.parse_float(
                body[pos[c]], rows, raw.header[pos[c]], "mm", False, problems
            )
            values[c] = tool[:, j]
    if "point" in pos:
        values["point"] = _data.parse_ids(
            body[pos["point"]], rows, raw.header[pos["point"]], problems
        )
    problems.raise_if_any()
    order = sorted(pos, key=lambda c: pos[c])
    table = pd.DataFrame({raw.header[pos[c]]: values[c] for c in order})
    return table, q, tool


# --------------------------------------------------------------------------------------
# result.json


#: characters that make the csv module (pandas' writer) quote a field
_CSV_SPECIAL = (",", '"', "\n", "\r")
_CSV_QUOTED = '[,"\n\r]'


def write_table(table: pd.DataFrame, path: str | Path) -> None:
    """``table.to_csv(path, index=False)``, byte for byte, about twice as fast for the
    long per-reading tables (residuals.csv: 200,000 rows took 8 s in pandas' writer,
    most of it converting floats to text row block by row block).  Every column is
    turned into its text at once (floats by ``repr``, the shortest text that reads back
    to the same number, as pandas writes them; NaN as an empty field) and the lines are
    joined without Python code per row.  Tables with other column types, or text that
    would need quoting, are written by pandas."""
    names = [str(c) for c in table.columns]
    if any(ch in n for n in names for ch in _CSV_SPECIAL) or _column_texts(table[:1]) is None:
        table.to_csv(path, index=False)
        return
    import os

    nl = os.linesep  # pandas' line terminator
    # a block of rows at a time: the texts of a whole 10^6-row table are some 14 million
    # Python strings (about 1 GB), a block's a few tens of MB
    with open(path, "w", encoding="utf-8", newline="") as fh:
        fh.write(",".join(names) + nl)
        for start in range(0, len(table), _WRITE_BLOCK_ROWS):
            texts = _column_texts(table[start : start + _WRITE_BLOCK_ROWS])
            if texts is None:  # text further down needs quoting: pandas writes it all
                break
            fh.write(nl.join(map(",".join, zip(*texts))) + nl)
        else:
            return
    table.to_csv(path, index=False)


#: rows of a table turned into text at once by :func:`write_table`
_WRITE_BLOCK_ROWS = 65536


def _column_texts(table: pd.DataFrame) -> list[list[str]] | None:
    """Every column of ``table`` as the texts pandas' to_csv writes for it, or None when
    a column is of another type or holds text that would need quoting (see
    :func:`write_table`)."""
    if len(table) == 0 or not table.columns.is_unique:
        return None
    texts: list[list[str]] = []
    for c in table.columns:
        col = table[c]
        dt = col.dtype
        if isinstance(dt, np.dtype) and dt == np.float64:
            v = col.to_numpy()
            t = _float_texts(v)
            for i in np.flatnonzero(np.isnan(v)):
                t[i] = ""
        elif isinstance(dt, np.dtype) and dt.kind == "b":
            t = np.where(col.to_numpy(), "True", "False").tolist()
        elif isinstance(dt, np.dtype) and dt.kind in "iu":
            t = list(map(str, col.to_numpy().tolist()))
        elif pd.api.types.infer_dtype(col, skipna=True) == "string":
            t = col.astype(object).where(col.notna(), "").tolist()
            # one search of the joined text, not one per cell (pandas' .str.contains)
            if re.search(_CSV_QUOTED, "".join(t)):
                return None
        else:
            return None
        texts.append(t)
    return texts


def _float_texts(v: np.ndarray) -> list[str]:
    """``repr`` of every value of a float array.  A column of few distinct values (the
    axis positions and tool offsets of the readings: a handful for 10^4 rows) has each
    distinct value turned into text once; ``repr`` took most of the time of writing
    residuals.csv.  (-0.0, which np.unique takes for 0.0, keeps one text per value.)"""
    n = len(v)
    if n >= 256 and len(np.unique(v[:256])) <= 32 and not np.any((v == 0) & np.signbit(v)):
        uniq, inv = np.unique(v, return_inverse=True)
        if len(uniq) <= n // 8:
            return np.array(list(map(repr, uniq.tolist())), dtype=object)[inv.ravel()].tolist()
    return list(map(repr, v.tolist()))


def _json_safe(obj: Any) -> Any:
    """numpy -> Python; NaN / inf -> None (JSON has neither)."""
    if isinstance(obj, Mapping):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _json_safe(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if obj is None or isinstance(obj, str):
        return obj
    if isinstance(obj, Path):
        return str(obj)
    return str(obj)


def json_text(obj: Any) -> str:
    """``json.dumps(_json_safe(obj), indent=1, allow_nan=False)``, the same text, written
    without json's pure-Python indenting encoder (which an indent selects) going through
    every number of a covariance matrix one generator step at a time: float arrays are
    turned into their texts at once (``repr``, as json writes floats; NaN / inf as
    null).  result.json holds a few thousand numbers (cov_theta, the null space)."""
    return _json_text(obj, 0)


def _json_text(obj: Any, level: int) -> str:
    if isinstance(obj, str):
        return _encode_str(obj)
    if obj is None:
        return "null"
    if isinstance(obj, (bool, np.bool_)):
        return "true" if obj else "false"
    if isinstance(obj, (int, np.integer)):
        return int.__repr__(int(obj))
    if isinstance(obj, (float, np.floating)):
        x = float(obj)
        return float.__repr__(x) if math.isfinite(x) else "null"
    if isinstance(obj, np.ndarray) and obj.ndim >= 1 and obj.dtype.kind in "fiub":
        if len(obj) == 0:
            return "[]"
        if obj.ndim > 1:
            items = [_json_text(row, level + 1) for row in obj]
        elif obj.dtype.kind == "f":
            v = obj.astype(float, copy=False)
            items = list(map(float.__repr__, v.tolist()))
            for i in np.flatnonzero(~np.isfinite(v)):
                items[i] = "null"
        elif obj.dtype.kind == "b":
            items = ["true" if b else "false" for b in obj.tolist()]
        else:
            items = list(map(int.__repr__, obj.tolist()))
        return _json_join("[", items, "]", level)
    if isinstance(obj, np.ndarray):
        return _json_text(obj.tolist(), level)
    if isinstance(obj, Mapping):
        if not obj:
            return "{}"
        named = {str(k): v for k, v in obj.items()}  # keys equal as text: the last value
        items = [_encode_str(k) + ": " + _json_text(v, level + 1) for k, v in named.items()]
        return _json_join("{", items, "}", level)
    if isinstance(obj, (list, tuple)):
        if not obj:
            return "[]"
        if all(type(v) is float for v in obj):  # a list of numbers (an array's tolist())
            items = list(map(float.__repr__, obj))
            if "nan" in items or "inf" in items or "-inf" in items:
                items = [t if math.isfinite(v) else "null" for t, v in zip(items, obj)]
        else:
            items = [_json_text(v, level + 1) for v in obj]
        return _json_join("[", items, "]", level)
    return _encode_str(str(obj))


def _json_join(open_: str, items: list[str], close: str, level: int) -> str:
    """Items laid out as json.dumps(..., indent=1) lays them out at depth ``level``."""
    inner = "\n" + " " * (level + 1)
    return open_ + inner + ("," + inner).join(items) + "\n" + " " * level + close


def _forms(em: ErrorModel) -> list[dict[str, Any]]:
    return [
        {
            "error": s.name,
            "kind": f.kind,
            "degree": int(f.degree),
            "knots": [float(k) for k in f.knots],
            "segments": int(f.segments),
        }
        for s, f in zip(em.errors, em.forms)
    ]


def _versions() -> dict[str, str]:
    import casadi

    return {
        "volcal": __version__,
        "casadi": casadi.CasadiMeta.version(),
        "numpy": np.__version__,
        "python": platform.python_version(),
    }


def _grid_axes(spec: MachineSpec, grid: pd.DataFrame) -> list[str]:
    """The axes that take more than one position in a grid of poses."""
    return [a for a in spec.axis_names if a in grid and grid[a].nunique() > 1]


def _grid_coverage(spec: MachineSpec, grid: pd.DataFrame) -> str:
    """Which axes a volumetric grid spans, in words (for the report and the terminal)."""
    moving = _grid_axes(spec, grid)
    fixed = [a.name for a in spec.axes if a.name not in moving]
    text = f"grid over {', '.join(moving) or 'no axis'}"
    if fixed:
        text += f"; {', '.join(fixed)} at reference"
    return text + ", tool offset (0, 0, 0) mm"


def _result_document(
    result: IdentificationResult,
    *,
    data_name: str,
    options: Mapping[str, Any] | None,
    grid: pd.DataFrame,
    created: str,
) -> dict[str, Any]:
    em = result.error_model
    spec = result.machine.spec
    ident = result.identifiability
    imax = int(np.argmax(grid["norm_um"].to_numpy())) if len(grid) else None
    return {
        "format": RESULT_FORMAT,
        "format_version": RESULT_FORMAT_VERSION,
        "created": created,
        "versions": _versions(),
        "data": data_name,
        "options": dict(options or {}),
        "units": "theta and cov_theta in internal units: mm for translational, rad for "
        "angular parameters (param_units); every value is an error (actual - "
        "nominal), a correction is its negative",
        "model": spec_to_dict(spec),
        "model_fingerprint": spec.fingerprint(),
        "error_model": {"datum": em.datum, "forms": _forms(em)},
        "param_names": list(em.param_names),
        "param_units": list(em.param_units),
        "theta": result.theta,
        "cov_theta": result.cov_theta,
        "identifiable": result.identifiable,
        "imposed": (
            np.zeros(len(result.theta), bool)
            if getattr(result, "imposed", None) is None
            else np.asarray(result.imposed, bool)
        ),
        "strategy": result.strategy,
        "status": result.status,
        "success": result.success,
        "phases": [
            {
                "status": o.status,
                "success": o.success,
                "iterations": o.iterations,
                "seconds": o.seconds,
                "objective": o.f,
                "gauss_newton_polish_steps": o.polish_steps,
                "objective_after_polish": o.polish_f,
            }
            for o in result.outcomes
        ],
        "seconds": result.seconds,
        "sigma_source": result.sigma_source,
        "n_readings": int(len(result.residuals)),
        "n_rejected": int(np.asarray(result.residuals["rejected"], bool).sum()),
        "residual_rms_um": result.residual_rms_um,
        "chi2_per_dof": result.conditions.get("chi2_per_dof"),
        "conditions": result.conditions,
        "max_volumetric_um": float(grid["norm_um"].iloc[imax]) if imax is not None else None,
        "max_volumetric_pose": (
            {a: float(grid[a].iloc[imax]) for a in spec.axis_names} if imax is not None else None
        ),
        # the axes the volumetric grid (and so max_volumetric_um) spans, tool offset (0, 0, 0) mm
        "max_volumetric_axes": _grid_axes(spec, grid),
        "adequacy": assess(result).to_dict(),
        # several instruments' tables: each one's chi2/dof, verdict (and variance component)
        "instruments": _instrument_records(result),
        "unidentifiable": list(np.asarray(em.param_names)[~np.asarray(result.identifiable)]),
        "null_space": (list(ident.unidentifiable_combinations) if ident is not None else []),
        "gauge": (list(ident.gauge_combinations) if ident is not None else []),
        # why parameters are left out and what to measure (None: all identifiable, or no
        # known cause)
        "unidentifiable_explanation": (
            result.unidentifiable_explanation()
            if hasattr(result, "unidentifiable_explanation")
            else None
        ),
        "datum": (result.datum.to_dict(orient="records") if result.datum is not None else None),
        "null_space_field": (
            result.null_space.to_dict() if result.null_space is not None else None
        ),
        "frame": result.frame,
        "stations": result.stations.to_dict(orient="records"),
        "notes": list(result.notes),
    }


@dataclass(eq=False)
class LoadedResult:
    """An identification result read back from its folder (:func:`load_result`).

    machine, error_model: rebuilt from the saved model document, forms and datum;
    theta (mm / rad), cov_theta (NaN where the saved value was null), identifiable:
    as identified; meta: the whole parsed result.json; path: the folder.
    """

    path: Path
    machine: Machine = field(repr=False)
    error_model: ErrorModel = field(repr=False)
    theta: np.ndarray = field(repr=False)
    cov_theta: np.ndarray = field(repr=False)
    identifiable: np.ndarray = field(repr=False)
    meta: dict[str, Any] = field(repr=False)
    null_space: FieldNullSpace | None = field(default=None, repr=False)
    #: the solver state saved with the result (format 3; None for older folders)
    state: SolverState | None = field(default=None, repr=False)

    @property
    def datum(self) -> pd.DataFrame | None:
        """Every candidate datum condition, imposed or not, with its value (um / urad)."""
        rec = self.meta.get("datum")
        return pd.DataFrame(rec) if rec else None

    @property
    def spec(self) -> MachineSpec:
        return self.machine.spec

    @property
    def adequacy(self) -> dict[str, Any] | None:
        """The saved model adequacy test (:meth:`volcal.analysis.adequacy.Adequacy.to_dict`:
        ``verdict``, ``chi2_per_dof``, ``interval``, ``causes`` ...); None for a result
        written before the test existed."""
        return self.meta.get("adequacy")

    @property
    def imposed(self) -> np.ndarray:
        """Parameters the datum set to zero (all False for results saved without it)."""
        rec = self.meta.get("imposed")
        n = len(self.theta)
        return np.asarray(rec, bool) if rec is not None and len(rec) == n else np.zeros(n, bool)

    def parameters(self) -> pd.DataFrame:
        """``name, value, unit, u, identifiable, imposed`` in um / urad (as parameters.csv)."""
        units = self.error_model.param_units
        f = np.array([_unit_factor(u)[0] for u in units])
        std = np.sqrt(np.clip(np.diag(self.cov_theta), 0, None)) * f
        std[~self.identifiable] = np.nan
        return pd.DataFrame(
            {
                "name": self.error_model.param_names,
                "value": self.theta * f,
                "unit": [_unit_factor(u)[1] for u in units],
                "u": std,
                "identifiable": self.identifiable,
                "imposed": self.imposed,
            }
        )

    def predict_internal(
        self, q: np.ndarray, tool: np.ndarray | None = None, *, with_uncertainty: bool = True
    ) -> pd.DataFrame:
        """As :meth:`IdentificationResult.predict`: poses q (N, n_axes) in mm / rad."""
        return predict_volumetric(
            self.machine,
            self.error_model,
            self.theta,
            self.cov_theta if with_uncertainty else None,
            q,
            tool,
            null_space=self.null_space,
        )

    def predict(
        self,
        points: pd.DataFrame | str | Path,
        *,
        name: str | None = None,
        with_uncertainty: bool = True,
    ) -> pd.DataFrame:
        """Volumetric errors at the poses of a points table (see :func:`read_points`;
        axes in mm / deg, tool offsets optional).  Returns the input columns plus
        ``dx_um, dy_um, dz_um`` (and ``u_dx_um, u_dy_um, u_dz_um``): errors, actual -
        nominal tool point in the machine frame."""
        table, q, tool = read_points(points, self.spec, name=name)
        pred = self.predict_internal(
            self.machine.axis_to_internal(q), tool, with_uncertainty=with_uncertainty
        )
        out = table.copy()
        for c in pred.columns:
            out[c] = pred[c].to_numpy()
        return out


def load_result(path: str | Path) -> LoadedResult:
    """Read a result folder written by :func:`save_result` (or its ``result.json``)."""
    path = Path(path)
    file = path if path.suffix == ".json" else path / "result.json"
    folder = file.parent
    if not file.is_file():
        raise InputError(
            "no result.json here; expected a folder written by `volcal identify`",
            source=str(folder if path.suffix != ".json" else file),
        )
    # a folder edited after it was written, or mixed from two runs, is refused
    from volcal.base.folders import verify_manifest

    verify_manifest(folder)
    try:
        doc = json.loads(file.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"cannot read result file: {exc}", source=str(file)) from None
    if not isinstance(doc, dict) or doc.get("format") != RESULT_FORMAT:
        raise InputError(
            f'not a volcal identification result (expected "format": "{RESULT_FORMAT}")',
            source=str(file),
        )
    version = doc.get("format_version")
    if not isinstance(version, int) or version > RESULT_FORMAT_VERSION:
        raise InputError(
            f"result format version {version!r} is not supported by volcal "
            f"{__version__} (reads up to {RESULT_FORMAT_VERSION})",
            source=str(file),
        )
    try:
        spec = machine_from_dict(doc["model"], where=f"{file} (model)")
        forms = {
            f["error"]: ErrorForm(
                f["kind"],
                int(f["degree"]),
                tuple(float(k) for k in f["knots"]),
                int(f.get("segments", 4)),
            )
            for f in doc["error_model"]["forms"]
        }
        datum = doc["error_model"]["datum"]
        names = list(doc["param_names"])
        theta = np.array([np.nan if v is None else v for v in doc["theta"]], float)
        cov = np.array(
            [[np.nan if v is None else v for v in row] for row in doc["cov_theta"]], float
        ).reshape(len(theta), len(theta))
        identifiable = np.array(doc["identifiable"], bool)
        nsf = doc.get("null_space_field")
        null_space = FieldNullSpace.from_dict(nsf) if nsf else None
    except InputError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise InputError(
            f"incomplete or malformed result file ({type(exc).__name__}: {exc})", source=str(file)
        ) from None
    if doc.get("model_fingerprint") not in (None, spec.fingerprint()):
        raise InputError(
            "the model document does not match its fingerprint; the file was edited or is corrupt",
            source=str(file),
        )
    em = ErrorModel(spec, forms, datum=datum)
    if em.param_names != names:
        raise InputError(
            "the saved parameter names do not match the error model rebuilt from the saved forms",
            source=str(file),
        )
    if len(identifiable) != len(theta) or not np.all(np.isfinite(theta)):
        raise InputError("theta / identifiable are inconsistent or not finite", source=str(file))
    machine = Machine.from_model(spec)
    state = (
        _load_state(folder / "solver_state.npz") if (folder / "solver_state.npz").exists() else None
    )
    return LoadedResult(folder, machine, em, theta, cov, identifiable, doc, null_space, state)


def _save_state(state: SolverState, path: Path) -> None:
    """The solver state as plain arrays (no pickled objects)."""
    with open(path, "wb") as fh:
        np.savez(
            fh,
            x=state.x,
            fixed=state.fixed,
            weights=state.weights,
            datum_active=state.datum_active,
            names=np.array(state.names, dtype=str),
            solver=np.array(state.solver),
            instrument=np.array(state.instrument),
            fingerprint=np.array(state.fingerprint),
        )


def _load_state(path: Path) -> SolverState:
    try:
        with np.load(path, allow_pickle=False) as z:
            return SolverState(
                np.array(z["x"], float),
                np.array(z["fixed"], bool),
                np.array(z["weights"], float),
                np.array(z["datum_active"], bool),
                [str(s) for s in z["names"]],
                str(z["solver"]),
                str(z["instrument"]),
                str(z["fingerprint"]),
            )
    except (OSError, KeyError, ValueError) as exc:
        raise InputError(
            f"unreadable solver state ({type(exc).__name__}: {exc})", source=str(path)
        ) from None


# --------------------------------------------------------------------------------------
# report


def _fmt(v: Any, spec: str = ".4g") -> str:
    if v is None:
        return ""
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return "" if not np.isfinite(v) else format(float(v), spec)
    return str(v).replace("|", "\\|")


def _md_table(df: pd.DataFrame, spec: str = ".4g") -> str:
    head = "| " + " | ".join(map(str, df.columns)) + " |"
    rule = "|" + "|".join("---" for _ in df.columns) + "|"
    body = [
        "| " + " | ".join(_fmt(v, spec) for v in row) + " |"
        for row in df.itertuples(index=False, name=None)
    ]
    return "\n".join([head, rule, *body])


def _report(
    result: IdentificationResult,
    *,
    data_name: str,
    created: str,
    options: Mapping[str, Any],
    grid: pd.DataFrame,
    n_grid: int,
    n_comp: int,
    plots: bool,
    comp: pd.DataFrame | None = None,
    motions: pd.DataFrame | None = None,
    timings: Mapping[str, float] | None = None,
) -> str:
    em = result.error_model
    spec = result.machine.spec
    res = result.residuals
    rej = np.asarray(res["rejected"], bool)
    vers = _versions()
    L: list[str] = []
    add = L.append
    add(f"# volcal identification: {spec.name}")
    add("")
    add(f"Written {created} by volcal {vers['volcal']} (CasADi {vers['casadi']}).")
    add("")
    add(
        "All values are **errors**: error = actual - nominal (ISO 230-1), for error motions "
        "and for the volumetric error (actual minus nominal tool point, machine frame). A "
        "correction (what a controller compensation table holds) is the negative of an "
        "error; nothing in this folder is a correction. Uncertainties are standard "
        "uncertainties (k = 1); plot bands are +-2 u."
    )
    add("")
    add("## Summary")
    add("")
    imax = int(np.argmax(grid["norm_um"].to_numpy())) if len(grid) else None
    unid = list(np.asarray(em.param_names)[~np.asarray(result.identifiable)])
    rows = [
        ("solver status", result.status + (" (success)" if result.success else " (FAILED)")),
        ("residual RMS", f"{result.residual_rms_um:.4g} um"),
        ("chi2 / dof", _fmt(result.conditions.get("chi2_per_dof"))),
    ]
    adequacy = assess(result)
    rows.append(
        (
            "model adequacy",
            (adequacy.summary if adequacy.adequate else f"**{adequacy.summary}**")
            + " (see Model adequacy)",
        )
    )
    if imax is not None:
        pose = ", ".join(
            f"{a} = {grid[a].iloc[imax]:g} {_axis_unit(spec, a)}" for a in spec.axis_names
        )
        rows.append(
            (
                "largest volumetric error",
                f"{grid['norm_um'].iloc[imax]:.4g} um at "
                f"{pose} ({_grid_coverage(spec, grid)}; see Volumetric error)",
            )
        )
    rows += [
        ("unidentifiable parameters", str(len(unid))),
        ("rejected readings", str(int(rej.sum()))),
        (
            "identification time",
            f"{result.seconds:.3g} s (reading and checking the readings, building and solving "
            "the problem, uncertainty; not writing this folder)",
        ),
    ]
    add(_md_table(pd.DataFrame(rows, columns=["quantity", "value"])))
    add("")
    add(_adequacy_section(adequacy, plots))
    if getattr(result, "instruments", None) is not None:
        add(_instruments_section(result.instruments))

    add("## Model")
    add("")
    add(
        f"Machine model `{spec.name}`" + (f": {spec.description}" if spec.description else "") + "."
    )
    add("")
    ax_rows = [
        (
            a.name,
            a.kind,
            a.direction,
            a.branch,
            f"{a.travel[0]:g} .. {a.travel[1]:g} {_axis_unit(spec, a.name)}",
            f"{a.reference:g}",
        )
        for a in spec.axes
    ]
    add(
        _md_table(
            pd.DataFrame(
                ax_rows, columns=["axis", "kind", "direction", "branch", "travel", "reference"]
            )
        )
    )
    add("")
    kinds: dict[str, list[str]] = {}
    for s, f in zip(em.errors, em.forms):
        if s.kind == "location":
            label = "constant (location error)"
        else:
            label = f.describe()
        kinds.setdefault(label, []).append(s.name)
    add(
        f"{em.n_errors} error quantities (component error motions and location errors, ISO "
        f"230-1 names), {em.n_params} parameters (the coefficients of their bases, which "
        f"the identification fits), datum convention `{em.datum}`:"
    )
    add("")
    for label, names in kinds.items():
        add(f"- {label}: {', '.join(names)}")
    add("")
    L.extend(_order_selection_lines(result))

    add("## Data")
    add("")
    n_st = res["station"].nunique()
    n_pt = res["point"].nunique() if "point" in res else 0
    add(f"- data: `{data_name or '(in memory)'}`")
    add(f"- {len(res)} readings, {n_st} stations, {n_pt} points")
    add(f"- reading uncertainties from: {result.sigma_source}")
    tools = res[["tool_x", "tool_y", "tool_z"]].drop_duplicates() if "tool_x" in res else None
    if tools is not None:
        add(
            "- tool offsets (mm): "
            + "; ".join(f"({x:g}, {y:g}, {z:g})" for x, y, z in tools.to_numpy())
        )
    add("")

    add("## Identification")
    add("")
    add(f"Strategy `{result.strategy}`.")
    if options:
        add("")
        add("Options: " + ", ".join(f"`{k}={v}`" for k, v in options.items()))
    add("")
    ph = [
        (
            k + 1,
            o.status,
            "yes" if o.success else "no",
            o.iterations,
            o.polish_steps,
            f"{o.seconds:.3g}",
        )
        for k, o in enumerate(result.outcomes)
    ]
    add(
        _md_table(
            pd.DataFrame(
                ph,
                columns=[
                    "phase",
                    "solver status",
                    "success",
                    "iterations",
                    "Gauss-Newton polish steps",
                    "time (s)",
                ],
            )
        )
    )
    add("")
    add(
        "IPOPT stops once the objective stalls (`Solved_To_Acceptable_Level` is then the "
        "usual status: at the minimum the gradient of a whitened sum of squares is at "
        "rounding level, not zero); the Gauss-Newton polish steps under the datum then end "
        "at the minimiser to working precision."
    )
    add("")
    m = result.machine
    add(
        f"Timings: identification {result.seconds:.3g} s (solver phases "
        f"{sum(o.seconds for o in result.outcomes):.3g} s of it); machine functions "
        f"{'loaded from the cache' if m.from_cache else 'built'} in {m.build_seconds:.3g} s."
        + (
            " Per stage, until this report was written: "
            + "; ".join(f"{k} {v:.3g} s" for k, v in timings.items())
            + "."
            if timings
            else ""
        )
    )
    add("")
    add("### Condition numbers")
    add("")
    cond = [(k, v) for k, v in result.conditions.items() if k != "chi2_per_dof"]
    add(
        _md_table(pd.DataFrame(cond, columns=["system", "condition number"]))
        if cond
        else "(none reported)"
    )
    add("")

    add("## Identifiability")
    add("")
    ident = result.identifiability
    if ident is not None:
        add(
            f"Rank {ident.rank}, {ident.n_null} null direction(s) (tolerance "
            f"{ident.tol:.2e}) of the scaled Jacobian (errors, stations and frame together)."
        )
        add("")
    if unid:
        add(
            "Unidentifiable parameters: " + ", ".join(f"`{n}`" for n in unid) + ". The data "
            "do not determine them: the variable leading each null-space combination below "
            "was held at zero and the others took the values that fit given that choice, "
            "so their values are one representative among equally good ones and they have "
            "no uncertainty (empty `std`, `u_` cells; dashed in the plot)."
        )
        why = result.unidentifiable_explanation()
        if why is not None:
            add("")
            add(f"**Why, and what to measure:** {_sentence(why['text'])}")
    else:
        add("Every parameter is identifiable from these data.")
    add("")
    if result.datum is not None:
        add(_datum_section(result))
    if ident is not None and ident.unidentifiable_combinations:
        add(
            "Unidentifiable combinations (they change the volumetric error somewhere in the "
            "declared travel at the measured tool offsets, but the data cannot see them; "
            "the leading variable of each was held, and `predict` flags the poses whose "
            "error depends on them):"
        )
        add("")
        for c in ident.unidentifiable_combinations:
            add(f"- `{c}`")
        add("")
    if ident is not None and ident.gauge_combinations:
        add(
            "Gauge freedoms held (they move the volumetric error at most rigidly, which no "
            "multilateration sees: the rigid motion between the station frame and the "
            "machine frame, and parameters that duplicate each other):"
        )
        add("")
        for c in ident.gauge_combinations:
            add(f"- `{c}`")
        add("")
    if ident is not None and ident.weak:
        add("Weakly determined directions (small singular value):")
        add("")
        for sv, c in ident.weak:
            add(f"- s = {sv:.2e}: `{c}`")
        add("")

    add("## Rejected readings")
    add("")
    if rej.any():
        cols = [
            c
            for c in ("row", "station", "point", "length", "residual_um", "normalised_residual")
            if c in result.rejected.columns
        ]
        add(
            f"{int(rej.sum())} reading(s) rejected by the robust option (|normalised "
            "residual| above the threshold); row = row in the data file (header = row 1):"
        )
        add("")
        add(_md_table(result.rejected[cols]))
    else:
        add("None" + ("" if options.get("robust", True) else " (robust rejection was off)") + ".")
    add("")

    add("## Component error motions")
    add("")
    add(
        f"`component_errors.csv`: every component error motion on {n_comp} positions over "
        "its axis' travel (other axes at their reference), with standard uncertainties "
        "(`u_` columns; empty where the error involves an unidentifiable parameter). "
        "Location errors are constants: see the parameter table."
    )
    add("")
    if plots:
        add("![component error motions](component_errors.png)")
        add("")
    L.extend(_error_motion_lines(spec, comp, motions))

    add("## Volumetric error")
    add("")
    covered = []
    for a in spec.axes:
        v = np.unique(grid[a.name].to_numpy(float)) if a.name in grid else np.array([])
        u = _axis_unit(spec, a.name)
        covered.append(
            f"{a.name}: {len(v)} positions {v.min():g} .. {v.max():g} {u}"
            if len(v) > 1
            else f"{a.name} at {a.reference:g} {u}"
        )
    rot = [a for a in spec.axes if a.is_rotary]
    at_ref = np.ones(len(grid), bool)
    for a in rot:
        at_ref &= np.isclose(grid[a.name].to_numpy(float), a.reference)
    add(
        f"`volumetric_grid.csv` covers {', '.join(_grid_axes(spec, grid)) or 'no axis'}: "
        f"{'; '.join(covered)}; tool offset (0, 0, 0) mm; {len(grid)} poses. Largest error "
        f"{grid['norm_um'].max():.4g} um, RMS of the norm "
        f"{float(np.sqrt(np.mean(grid['norm_um'] ** 2))):.4g} um"
        + (
            f"; with the rotary axes {', '.join(a.name for a in rot)} at their reference "
            f"the largest error is {grid['norm_um'][at_ref].max():.4g} um"
            if rot and at_ref.any() and len(_grid_axes(spec, grid)) > len(spec.axes) - len(rot)
            else ""
        )
        + ". Uncertainties propagate the identifiable parameters; the rigid motion between "
        "station frame and machine frame is not determined by multilateration."
    )
    add("")
    if plots:
        add(
            "![volumetric error map](volumetric_map.png)"
            + (
                ""
                if not rot
                else f"\n\n(XY slices at several heights with "
                f"{', '.join(a.name for a in rot)} at their reference, then slices at "
                "several angles of each rotary axis.)"
            )
        )
        add("")

    add("## Residuals")
    add("")
    add(
        "`residuals.csv`: the input rows with `residual_um` (model - measured), "
        "`normalised_residual` (residual / standard uncertainty) and `rejected`."
    )
    add("")
    if plots:
        add("![residuals](residuals.png)")
        add("")

    add("## Parameters")
    add("")
    add(
        "Values and standard uncertainties in um (translational) or urad (angular); "
        "`parameters.csv` holds them at full precision. Names: `<error>_<k>` is the k-th "
        "Legendre coefficient on the normalised travel, `<error>_0`, `<error>_c<k>`, "
        "`<error>_s<k>` the Fourier coefficients of 1, cos(k x), sin(k x), `<error>_b<j>` "
        "the j-th B-spline coefficient, `<error>@<pos>` a table value, `<error>` a "
        "constant. `imposed`: set to zero by the datum (a convention with u = 0, not a "
        "measurement; the conditions are in `datum.csv`)."
    )
    add("")
    add(_md_table(result.parameters()))
    add("")

    add("## Stations")
    add("")
    add(_md_table(result.stations, ".6g"))
    add("")

    add("## Notes")
    add("")
    if result.notes:
        for n in result.notes:
            add(f"- {n}")
    else:
        add("- none")
    add("")
    add("## Files")
    add("")
    add(
        "`parameters.csv`, `stations.csv`, `residuals.csv`, `component_errors.csv`, "
        "`error_motions.csv`, `volumetric_grid.csv`, `result.json` (everything "
        "`volcal predict --result` needs)"
        + (
            ", `component_errors.png`, `volumetric_map.png`, `residuals.png`, "
            "`residuals_vs_axes.png`, `correlations.png`"
            if plots
            else " (plots not written: --no-plots)"
        )
        + "."
    )
    add("")
    return "\n".join(L)


def _error_motion_lines(
    spec: MachineSpec, comp: pd.DataFrame | None, motions: pd.DataFrame | None
) -> list[str]:
    """Report text: peak-to-peak per error motion (error_motions.csv) and the error motions
    at positions along each axis (rows of component_errors.csv)."""
    L: list[str] = []
    if motions is not None and len(motions):
        L += [
            "### Peak-to-peak per error motion",
            "",
            f"`error_motions.csv`: largest minus smallest value of each error motion over "
            f"its axis' travel ({PEAK_POINTS} positions, other axes at their reference), "
            "with its standard uncertainty and where the extremes lie.",
            "",
        ]
        view = pd.DataFrame(
            {
                "error motion": motions["error_motion"],
                "what": motions["description"],
                "peak-to-peak": motions["peak_to_peak_in_unit"],
                "u (k = 1)": motions["u_peak_to_peak_in_unit"],
                "unit": motions["unit"],
                "min at": [
                    f"{p:g} {u}"
                    for p, u in zip(motions["position_of_min_in_axis_unit"], motions["axis_unit"])
                ],
                "max at": [
                    f"{p:g} {u}"
                    for p, u in zip(motions["position_of_max_in_axis_unit"], motions["axis_unit"])
                ],
            }
        )
        L += [_md_table(view, ".3g"), ""]
    if comp is not None and len(comp):
        L += [
            "### Error motions at positions along each axis",
            "",
            "Rows of `component_errors.csv` evenly spread over each axis' travel (other "
            "axes at their reference); um for translational, urad for angular motions.",
            "",
        ]
        for axis, table in error_motions_at_positions(comp):
            where = positions_text(table)
            table = table.copy()
            pos = table.columns[0]
            table[pos] = [f"{v:g}" for v in table[pos]]  # positions in full, not 3 digits
            vals = table.columns[1:]
            v = table[vals].to_numpy(float)
            table[vals] = np.where(np.abs(v) < 1e-9, 0.0, v)
            L += [f"Axis {axis}, {where}:", "", _md_table(table, ".3g"), ""]
    return L


def _write_order_selection(result: IdentificationResult, folder: Path) -> None:
    """``order_selection.csv`` when the orders were chosen from the data (``--degree
    auto``, :mod:`volcal.workflow.orders`)."""
    table = getattr(result, "order_selection", None)
    if table is not None:
        table.to_csv(folder / "order_selection.csv", index=False)


def _order_selection_lines(result: IdentificationResult) -> list[str]:
    """The report section on the orders chosen from the data (empty when not chosen)."""
    t = getattr(result, "order_selection", None)
    if t is None or not len(t):
        return []
    crit = str(t["criterion"].iloc[0])
    what = (
        "BIC = chi2 + k ln N on the whitened residuals (k the rank of the "
        "identification, N the readings used)"
        if crit == "bic"
        else "the chi2 of held-out readings in K-fold cross-validation over the poses"
    )
    chosen = t.loc[t["chosen"], "orders"]
    L = [
        "### Orders chosen from the data",
        "",
        f"`--degree auto`: per-axis orders by {what}, smaller is better; greedy search one "
        "axis at a time (`order_selection.csv` lists every candidate). Chosen: "
        f"`{chosen.iloc[0] if len(chosen) else '?'}`.",
        "",
    ]
    per = t[t["axis"] != ""]
    if len(per):
        best = per.groupby(["sweep", "axis"])["value"].transform("min")
        view = per.assign(delta=per["value"] - best)[
            ["sweep", "axis", "kind", "order", "n_params", "value", "delta", "k"]
        ]
        L += [_md_table(view.rename(columns={"value": crit, "delta": f"{crit} - best"}), ".6g"), ""]
    return L


# --------------------------------------------------------------------------------------
# writing


def _sentence(text: str) -> str:
    """A message as a sentence: capital first letter, full stop."""
    return (text[:1].upper() + text[1:]).rstrip(".") + "."


def _instrument_records(result) -> list[dict[str, Any]] | None:
    """Each table's row of ``result.instruments`` (None for a single table)."""
    table = getattr(result, "instruments", None)
    return None if table is None else table.to_dict(orient="records")


def _instruments_section(table: pd.DataFrame) -> str:
    """Report text: the adequacy check of every instrument's table (and its variance
    component when estimated), see :mod:`volcal.analysis.fusion`."""
    lines = ["## Instruments", ""]
    lines.append(
        "One problem over every table; each table's chi2/dof is the sum of its squared "
        "normalised residuals over its share of the degrees of freedom (the sum of its "
        "readings' redundancy numbers), checked against its own 99.9 % interval (chi2 "
        "with dof_check degrees of freedom, Satterthwaite's for a share of the residuals)."
    )
    lines.append("")
    cols = ["data", "instrument", "n_readings", "dof", "chi2_per_dof", "chi2_low", "chi2_high"]
    cols += ["verdict", "sigma_source"]
    extra = ["chi2_per_dof_given", "verdict_given", "scale_factor", "dof_vce"]
    extra += ["u_scale_factor", "scale_low_95", "scale_high_95"]
    extra += ["determined_alone", "field_u_cumulative_um"]
    cols += [c for c in extra if c in table.columns]
    t = table[cols].copy()
    for c in ("dof", "chi2_per_dof", "chi2_low", "chi2_high", *extra):
        if c in t.columns and c not in ("determined_alone", "verdict_given"):
            t[c] = t[c].map(lambda v: f"{v:.4g}")
    lines.append(_md_table(t))
    if "undetermined_alone" in table.columns:
        lines.append("")
        lines.append(
            "determined_alone: the error parameters each table determines by itself (with "
            "the datum in force); field_u_cumulative_um: the RMS standard uncertainty of "
            "the volumetric error over the measured poses with the tables up to that row "
            "(empty while some parameter is undetermined). Left undetermined by each table "
            "alone:"
        )
        lines.append("")
        for _, row in table.iterrows():
            lines.append(
                f"- {row['data']} ({row['instrument']}): {row['undetermined_alone'] or 'none'}"
            )
    if "scale_factor" in table.columns:
        lines.append("")
        lines.append(
            "Variance components (Helmert): each table's standard uncertainties were scaled "
            "by its scale_factor, after which every chi2/dof is 1 (chi2_per_dof_given and "
            "verdict_given: the check with the budgets as given); u: its standard "
            "uncertainty, 95 % interval from chi2 with dof_vce degrees of freedom "
            "(Satterthwaite's, from REML's information: fewer than dof where the tables "
            "share their redundancy; coverage measured by studies/vce)."
        )
    lines.append("")
    return "\n".join(lines)


def _adequacy_section(ad, plots: bool) -> str:
    """Report text: the model adequacy test (see :mod:`volcal.analysis.adequacy`)."""
    lo, hi = ad.interval
    lines = ["## Model adequacy", ""]
    if ad.verdict == "fits":
        lines.append(
            f"**The model fits the data within their uncertainty**: chi2/dof = "
            f"{ad.chi2_per_dof:.4g} lies inside its 99.9 % interval "
            f"[{lo:.4g}, {hi:.4g}] for {ad.dof} degrees of freedom "
            f"({ad.n_readings} readings used), and no residual structure is significant "
            f"(p < {STRUCTURE_P:g})."
        )
    elif ad.verdict == "budget_pessimistic":
        lines.append(
            f"**The model fits; the uncertainty budget is pessimistic.** {_sentence(ad.message)}"
        )
        lines += ["", "The reported uncertainties are conservative; the result can be used as is."]
    else:
        where = "above" if ad.chi2_per_dof > hi else "below" if ad.chi2_per_dof < lo else "inside"
        sig = [s.label for s in ad.significant_structure]
        lines.append(
            f"**WARNING: the model does not fit the data within their uncertainty.** "
            f"chi2/dof = {ad.chi2_per_dof:.4g} lies {where} its 99.9 % interval "
            f"[{lo:.4g}, {hi:.4g}] for {ad.dof} degrees of freedom "
            f"({ad.n_readings} readings used)"
            + (
                f"; the residuals are structured (F-test p < {STRUCTURE_P:g} against "
                + ", ".join(sig)
                + ")"
                if sig
                else ""
            )
            + ". The identified errors and their uncertainties are not to be trusted until "
            "the cause is removed."
        )
        lines += ["", "Likely cause" + ("s, most likely first:" if len(ad.causes) > 1 else ":"), ""]
        lines += [f"- **{c.kind}**: {c.text}" for c in ad.causes]
    lines.append("")
    for w in ad.warnings:
        lines += [f"**Warning:** {w}.", ""]
    o = ad.outliers
    lines += [
        "| check | value |",
        "|---|---|",
        f"| largest abs. normalised residual | {_fmt(o['max_abs'])} |",
        f"| readings beyond 5 robust sigma / 5 budget sigma | "
        f"{o['n_beyond_5_robust']} / {o['n_beyond_5_sigma']} |",
        f"| excess kurtosis of the normalised residuals | {_fmt(o['excess_kurtosis'])} |",
        f"| budget factor (sigma multiplier the residuals call for) | {_fmt(ad.budget_factor)}"
        + (
            " (not a property of the budget while the residuals are structured) |"
            if ad.significant_structure
            else " |"
        ),
    ]
    lines += [
        "",
        "Residual structure (nested F-tests: against an axis' position, the tool offset "
        "or the time of the reading, the group means per station against the station "
        "means; against the station, the station means against the overall mean; "
        f"significant below p = {STRUCTURE_P:g}; share: of the residual sum of squares "
        "the group means explain beyond chance):",
        "",
        "| against | groups | F | p-value | share | significant |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for st in ad.structure:
        p = f"{st.p_value:.2g}" if st.log10_p > -300 else "< 1e-300"
        lines.append(
            f"| {st.label} | {st.n_bins} | {st.f:.3g} | {p} | "
            f"{100 * st.explained_share:.1f} % | {'**yes**' if st.significant else 'no'} |"
        )
    lines.append("")
    if plots:
        lines += [
            "![normalised residuals against each axis](residuals_vs_axes.png)",
            "",
            "![correlations of the identifiable parameters](correlations.png)",
            "",
        ]
    return "\n".join(lines)


def _datum_section(result: IdentificationResult) -> str:
    """Report text: which datum conditions hold exactly and which take other values."""
    tab = result.datum
    assert tab is not None  # the caller writes this section only for results with a datum
    imp = tab[tab["imposed"]]
    free = tab[~tab["imposed"]]
    lines = [
        f"### Datum ({result.error_model.datum})",
        "",
        f"{len(imp)} of {len(tab)} candidate conditions are imposed: each removes a "
        "direction the data cannot see, so together they fix the gauge without "
        "changing the fit (the weighted residuals are those of the fit without datum).",
    ]
    if len(free):
        lines += [
            "The other conditions would have constrained combinations the data "
            "determine; they are not imposed and take these values:",
            "",
            "| condition | value | unit |",
            "|---|---:|---|",
        ]
        lines += [f"| {r.condition} | {r.value:.4g} | {r.unit} |" for r in free.itertuples()]
    else:
        lines.append("Every candidate condition holds exactly.")
    return "\n".join(lines) + "\n"


def check_out_dir(out_dir: str | Path) -> Path:
    """Raise :class:`InputError` unless ``out_dir`` can be written: it must not exist, or
    be an empty folder or a previous result folder (which is then replaced)."""
    from volcal.base.folders import check_out_dir as _check

    return _check(out_dir, RESULT_FILES + OPTIONAL_FILES, "an identification", marker="result.json")


def save_result(
    result: IdentificationResult,
    out_dir: str | Path,
    *,
    data_name: str = "",
    plots: bool = True,
    options: Mapping[str, Any] | None = None,
    grid_points: int = GRID_POINTS,
    component_points: int = COMPONENT_POINTS,
    force: bool | None = None,
    plotter: PlotProcess | None = None,
    held: Mapping[str, int] | None = None,
) -> Path:
    """Write the result folder (see the module docstring) and return its path.

    data_name: the data file name recorded in result.json and the report; plots: write
    the PNG plots; options: the identification options to record (e.g. the CLI's);
    grid_points: positions per linear axis of volumetric_grid.csv; component_points:
    positions per axis of component_errors.csv.

    Atomic: built in a temporary folder next to ``out_dir`` and renamed into place; a
    failure leaves ``out_dir`` as it was (absent or the previous result).  An existing
    ``out_dir`` that is neither empty nor a previous result raises :class:`InputError`;
    a previous result is replaced unless ``force`` is False (see
    :func:`volcal.base.folders.check_out_dir`; the command line needs ``--force``).
    plotter: a :class:`volcal.outputs.plot_process.PlotProcess` started early (the
    command line does) that draws the plots while this process writes the rest; the
    folder is renamed into place only once every plot is written.  held: the figures
    ``plotter``'s children drew before the folder existed and keep in memory, ``{file
    name: child}`` (:func:`volcal.outputs.plots.hold_solved_plots`): written into the
    folder, not drawn again.
    """
    t0 = time.perf_counter()
    from volcal.base.folders import write_folder

    if grid_points < 1 or component_points < 2:
        raise InputError(
            f"expected grid_points >= 1 and component_points >= 2, got "
            f"{grid_points} and {component_points}"
        )
    options = dict(options or {})

    def writer(tmp: Path) -> None:
        em, machine = result.error_model, result.machine
        created = datetime.now(UTC).isoformat(timespec="seconds")
        comp = component_error_table(
            em, result.theta, result.cov_theta, result.identifiable, component_points
        )
        requests = []
        if plots:
            from volcal.outputs import plots as P

            with progress.stage("plotting"):
                # the figures' data first, each sent as soon as it is ready: the plotting
                # children (when there are some) draw them while this process prepares
                # the next and then writes the tables and the report; those drawn already
                # (held in memory by the children that drew them) are only written
                skip = dict(held or {}) if plotter is not None else {}
                if plotter is not None and skip:
                    from volcal.outputs.figures import write_held

                    for name, child in skip.items():
                        plotter.draw(write_held, name, tmp / name, cost=0.0, child=child)
                for name, draw, data, cost in P.iter_plot_requests(result, comp, skip=skip):
                    requests.append((name, draw, data, cost))
                    if plotter is not None:
                        plotter.draw(draw, data, tmp / name, cost=cost)
        log.info("writing the result tables (temporary folder %s)", tmp)
        with progress.stage("writing the tables"):
            result.parameters().to_csv(tmp / "parameters.csv", index=False)
            result.stations.to_csv(tmp / "stations.csv", index=False)
            write_table(result.residuals, tmp / "residuals.csv")
            by_instrument = getattr(result, "instruments", None)
            if by_instrument is not None:
                by_instrument.to_csv(tmp / "instruments.csv", index=False)
            _write_order_selection(result, tmp)
            if result.state is not None:
                _save_state(result.state, tmp / "solver_state.npz")
            if result.datum is not None:
                result.datum.rename(columns={"value": "value_in_unit"}).to_csv(
                    tmp / "datum.csv", index=False
                )
            comp.to_csv(tmp / "component_errors.csv", index=False)
            motions = error_motion_table(em, result.theta, result.cov_theta, result.identifiable)
            motions.to_csv(tmp / "error_motions.csv", index=False)
            log.info("evaluating the volumetric error on the grid")
            grid = volumetric_grid_table(machine, em, result.theta, result.cov_theta, grid_points)
            # all floats: write_table's text in about half of pandas' time (small tables
            # with text columns are faster in pandas)
            write_table(grid, tmp / "volumetric_grid.csv")
        # the adequacy test (kept on the result) is a pass over every reading: a stage of
        # its own, so that its time is recorded rather than hidden in the document's
        with progress.stage("testing the model's adequacy"):
            assess(result)
        doc = _result_document(
            result, data_name=data_name, options=options, grid=grid, created=created
        )
        # seconds per stage of this process so far (a benchmark takes the plots' cost
        # from a run without them)
        doc["timings_s"] = progress.timings()
        (tmp / "result.json").write_text(json_text(doc) + "\n", encoding="utf-8")
        (tmp / "report.md").write_text(
            _report(
                result,
                data_name=data_name,
                created=created,
                options=options,
                grid=grid,
                n_grid=grid_points,
                n_comp=component_points,
                plots=plots,
                comp=comp,
                motions=motions,
                timings=doc["timings_s"],
            ),
            encoding="utf-8",
        )
        if plots:
            log.info("plotting")
            with progress.stage("plotting"):
                if plotter is not None:
                    plotter.wait()
                else:
                    for name, draw, data, _ in requests:
                        draw(data, tmp / name)

    out = write_folder(
        out_dir,
        RESULT_FILES + OPTIONAL_FILES,
        "an identification",
        writer,
        marker="result.json",
        force=force,
    )
    log.info("wrote %s in %.2f s", out, time.perf_counter() - t0)
    return out
