"""Compensation files that controllers read, from an identification result.

``compensate(result, format, out_dir)`` writes one of

* ``"isg"``: Beckhoff TwinCAT CNC volumetric compensation (TF5280, ISG kernel): ISG CSV
  parameter files (component error motions per axis, position errors and ISG
  parameters) and the ``.lis`` configuration list (:mod:`.isg`);
* ``"siemens"``: SINUMERIK 840D sl / 828D interpolatory compensation: CEC tables (sag /
  angularity, with table multiplication for the lever-arm products) and LEC tables
  (leadscrew / encoder) as init programs (:mod:`.siemens`);
* ``"heidenhain"``: HEIDENHAIN nonlinear axis error compensation: ``*.COM`` tables and
  the ``*.CMA`` assignment (:mod:`.heidenhain`);
* ``"generic"``: per-axis component error tables under ISO 230-1 names and a volumetric
  correction grid over every axis (CSV and a binary ``.npz`` with its metadata)
  (:mod:`.generic`);

plus ``compensation.md`` and ``compensation.json`` (what was written, the grid spacing,
the interpolation error, what the format cannot carry and the residual volumetric error
it leaves over the workspace and the tool offsets of the measurement).

Every file states in its header whether it holds errors (actual - nominal, ISO 230-1) or
corrections (-error), and what it cannot carry.  Node spacing comes from the curvature of
what is tabulated so that linear interpolation between nodes stays within
``tolerance_um`` at the tool point (:mod:`.grid`).  docs/compensation.md describes each
format.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from volcal.base.exceptions import InputError

from .errorfield import ErrorField, as_field_input
from .grid import LimitError, workspace_sample

__all__ = ["compensate", "Compensation", "FORMATS", "LimitError", "COMPENSATION_FILES"]

FORMATS = ("isg", "siemens", "heidenhain", "generic")
#: written into every output folder besides the format's files
COMPENSATION_FILES = ("compensation.md", "compensation.json")
#: poses of the residual check (plus the corners of the travel box)
CHECK_POSES = 1500
WHAT = "a compensation export (volcal compensate)"

_TITLES = {
    "isg": "Beckhoff TwinCAT CNC volumetric compensation (TF5280, ISG kernel): ISG CSV "
    "parameter files and .lis configuration",
    "siemens": "SINUMERIK 840D sl / 828D interpolatory compensation: CEC and LEC tables "
    "(init programs)",
    "heidenhain": "HEIDENHAIN nonlinear axis error compensation: *.COM tables and *.CMA assignment",
    "generic": "generic: per-axis ISO 230-1 error tables and a volumetric correction grid",
}


@dataclass
class Context:
    """What a format builder gets (internal units: mm / rad)."""

    field: ErrorField
    tolerance_um: float
    tools: np.ndarray  # (K, 3) tool offsets of the residual report (and the generic grids)
    table_tool: np.ndarray  # (3,) the tool offset the 1-D tables are built for
    sign: str  # "correction" or "error" for formats whose values are corrections
    options: dict[str, Any]
    created: str
    source: str


@dataclass
class Built:
    """A format's compensation before it is written: ``residual(q, tool)`` gives the
    volumetric error (N, 3) mm left after the compensation (NaN where it does not apply);
    ``render(summary)`` the files {name: text or bytes}."""

    residual: Callable[[np.ndarray, np.ndarray], np.ndarray]
    render: Callable[[Compensation], Mapping[str, str | bytes]]
    values: str
    spacing: dict[str, float]
    bound_um: float
    measured_um: float | None
    not_carried: list[str]
    tables: list[dict[str, Any]]
    limits: dict[str, Any]
    notes: list[str] = field(default_factory=list)
    table_tool: np.ndarray | None = None
    #: the tolerance the format chose itself (generic grid with no tolerance given)
    tolerance_um: float | None = None
    #: the names of the files ``render`` writes, when known without rendering them
    file_names: list[str] | None = None


@dataclass
class Compensation:
    """What :func:`compensate` wrote and how well it corrects the identified model.

    Residual figures are over ``n_poses`` poses of the travel box (a Halton sample plus
    its corners) at each tool offset of ``per_tool``: the uncorrected volumetric error
    and the one left after applying the files as the controller does (first-order model;
    RMS of the length of the error vector, and its largest length), in um.
    """

    format: str
    title: str
    path: Path | None
    files: list[str]
    values: str
    tolerance_um: float
    spacing: dict[str, str]
    interpolation_bound_um: float
    interpolation_max_um: float | None
    per_tool: pd.DataFrame
    not_carried: list[str]
    tables: list[dict[str, Any]]
    limits: dict[str, Any]
    n_poses: int
    model: str
    fingerprint: str
    source: str
    created: str
    table_tool: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)
    #: the rigid motion of the workpiece frame in the residual: translation (3,) um and
    #: rotation (3,) urad about the centroid of the check points, and the centroid (3,) mm
    rigid_translation_um: np.ndarray | None = None
    rigid_rotation_urad: np.ndarray | None = None
    rigid_centre_mm: np.ndarray | None = None

    @property
    def uncorrected_rms_um(self) -> float:
        return _pooled(self.per_tool, "uncorrected_rms_um")

    @property
    def residual_rms_um(self) -> float:
        return _pooled(self.per_tool, "residual_rms_um")

    @property
    def residual_mod_rigid_rms_um(self) -> float:
        """Residual RMS after removing the one rigid motion of the workpiece frame."""
        return _pooled(self.per_tool, "residual_mod_rigid_rms_um")

    @property
    def residual_max_um(self) -> float:
        v = self.per_tool["residual_max_um"].to_numpy(float)
        return float(np.nanmax(v)) if np.isfinite(v).any() else math.nan

    @property
    def ratio(self) -> float:
        """Residual RMS / uncorrected RMS over the covered tool offsets."""
        ok = np.isfinite(self.per_tool["residual_rms_um"].to_numpy(float))
        if not ok.any():
            return math.nan
        return _pooled(self.per_tool[ok], "residual_rms_um") / _pooled(
            self.per_tool[ok], "uncorrected_rms_um"
        )

    def residual_line(self) -> str:
        return (
            f"residual volumetric error after compensation: RMS {self.residual_rms_um:.3f} "
            f"um ({100 * self.ratio:.2f} % of the uncorrected {self.uncorrected_rms_um:.3f}"
            f" um RMS), max {self.residual_max_um:.3f} um; {self.n_poses} poses over the "
            f"travel x {len(self.per_tool)} tool offset(s)"
        )

    def setup_lines(self) -> list[str]:
        """The statement of the setup part every file carries."""
        t = self.rigid_translation_um if self.rigid_translation_um is not None else np.zeros(3)
        w = self.rigid_rotation_urad if self.rigid_rotation_urad is not None else np.zeros(3)
        return [
            "SETUP PART: multilateration does not determine one rigid motion (a translation "
            "and a small rotation) of the workpiece frame relative to the machine; the "
            "identification fixed it by its datum only. These files do not correct it: "
            "after applying them the machine keeps the part of its error that is such a "
            "motion, and the work offset (G54 ...) and the workpiece alignment (probing, "
            "rotation of the coordinate system) take it up",
            "residual modulo that rigid motion (one motion fitted over every tool offset "
            f"together): RMS {self.residual_mod_rigid_rms_um:.3f} um "
            f"(raw, for the datum in force: {self.residual_rms_um:.3f} um RMS, of which a "
            "rigid motion of translation (" + ", ".join(f"{v:.3f}" for v in t) + ") um and "
            "rotation (" + ", ".join(f"{v:.3f}" for v in w) + ") urad)",
        ]

    def spacing_line(self) -> str:
        sp = ", ".join(f"{a} {v}" for a, v in self.spacing.items())
        meas = (
            ""
            if self.interpolation_max_um is None
            else f", measured {self.interpolation_max_um:.3g} um"
        )
        return (
            f"node spacing {sp}: chosen from the curvature of the tabulated errors for an "
            f"interpolation error of at most {self.tolerance_um:g} um at the tool point "
            f"(bound {self.interpolation_bound_um:.3g} um{meas})"
        )

    def to_dict(self) -> dict[str, Any]:
        def tool(t):
            return None if t is None else [float(v) for v in t]

        return {
            "format": "volcal-compensation",
            "format_version": 1,
            "compensation_format": self.format,
            "title": self.title,
            "files": self.files,
            "values": self.values,
            "tolerance_um": self.tolerance_um,
            "spacing": self.spacing,
            "interpolation_bound_um": self.interpolation_bound_um,
            "interpolation_max_um": self.interpolation_max_um,
            "table_tool_mm": tool(self.table_tool),
            "uncorrected_rms_um": self.uncorrected_rms_um,
            "residual_rms_um": self.residual_rms_um,
            "residual_max_um": self.residual_max_um,
            "residual_mod_rigid_rms_um": self.residual_mod_rigid_rms_um,
            "rigid_translation_um": self.rigid_translation_um,
            "rigid_rotation_urad": self.rigid_rotation_urad,
            "rigid_centre_mm": self.rigid_centre_mm,
            "setup_part": self.setup_lines()[0],
            "ratio": self.ratio,
            "per_tool": _records(self.per_tool),
            "not_carried": self.not_carried,
            "tables": _records(pd.DataFrame(self.tables)),
            "limits": self.limits,
            "n_poses": self.n_poses,
            "model": self.model,
            "model_fingerprint": self.fingerprint,
            "source": self.source,
            "created": self.created,
            "notes": self.notes,
        }

    def header(self) -> list[str]:
        """The lines every file of the export starts with (without comment marks)."""
        from volcal import __version__

        lines = [
            f"volcal {__version__} compensation export: {self.title}",
            f"model {self.model} (fingerprint {self.fingerprint}); identification "
            f"result {self.source}; created {self.created}",
            f"VALUES: {self.values}",
        ]
        if self.table_tool is not None:
            lines.append(
                "tables built for the tool offset ("
                + ", ".join(f"{v:g}" for v in self.table_tool)
                + ") mm (tool frame)"
            )
        lines.append(self.spacing_line())
        lines.append(self.residual_line())
        lines += self.setup_lines()
        for n in self.not_carried:
            lines.append(f"NOT CARRIED: {n}")
        if not self.not_carried:
            lines.append(
                "NOT CARRIED: nothing of the identified model; what remains is the "
                "interpolation error (residual above)"
            )
        lines.append("conventions: docs/compensation.md and docs/conventions.md of volcal")
        return lines


def rigid_split(
    r: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Split residuals r (N, 3) mm at nominal points (N, 3) mm into the least-squares
    small rigid motion t + w x (p - centroid) and the rest: (rest (N, 3) mm, t (3,) mm,
    w (3,) rad, centroid (3,) mm).  The rigid motion is the one multilateration does not
    determine.  Rows where r is not finite (a format that does not apply at that tool
    offset) take no part: neither in the fit nor in the centroid, and stay NaN."""
    from volcal.analysis.identifiability import rigid_columns

    r = np.asarray(r, float)
    points = np.asarray(points, float)
    ok = np.all(np.isfinite(r), axis=1)
    n = int(ok.sum())
    if n == 0:
        return r.copy(), np.zeros(3), np.zeros(3), np.full(3, np.nan)
    centre = points[ok].mean(axis=0)
    if n < 3:
        return r.copy(), np.zeros(3), np.zeros(3), centre
    A = rigid_columns(points[ok] - centre)
    # translations (mm) and rotations (rad) differ in scale by the lever arm: unit columns
    col = np.linalg.norm(A, axis=0)
    col[col == 0] = 1.0
    sol = np.linalg.lstsq(A / col, r[ok].ravel(), rcond=None)[0] / col
    out = r.copy()
    out[ok] = r[ok] - (A @ sol).reshape(n, 3)
    return out, sol[:3], sol[3:], centre


def _pooled(df: pd.DataFrame, col: str) -> float:
    v = df[col].to_numpy(float)
    ok = np.isfinite(v)
    return float(np.sqrt(np.mean(v[ok] ** 2))) if ok.any() else math.nan


def _records(df: pd.DataFrame) -> list[dict[str, Any]]:
    out = []
    for rec in df.to_dict(orient="records"):
        out.append(
            {
                k: (
                    None
                    if isinstance(v, float) and not math.isfinite(v)
                    else v.item()
                    if isinstance(v, np.generic)
                    else v
                )
                for k, v in rec.items()
            }
        )
    return out


def _parse_tool(t, where: str) -> np.ndarray:
    a = np.asarray(t, float).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InputError(
            f"expected a tool offset of three finite numbers (mm), got {t!r}", source=where
        )
    return a


TEMPLATE_DIR = Path(__file__).parent / "templates"


def render_template(template: str, /, **mapping: Any) -> str:
    """The Jinja2 template ``templates/<template>`` rendered with ``mapping`` (undefined
    variables are errors, nothing is escaped, the last newline is kept)."""
    import jinja2

    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(TEMPLATE_DIR)),
        undefined=jinja2.StrictUndefined,
        autoescape=False,
        keep_trailing_newline=True,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    return env.get_template(template).render(mapping)


def check_poses(fld: ErrorField) -> np.ndarray:
    """The poses of the residual check: a Halton sample of the travel box and its corners."""
    return workspace_sample(fld.lower, fld.upper, CHECK_POSES, skip=1000)


def rms_um(v_mm: np.ndarray) -> float:
    """RMS of the length of error vectors (N, 3) mm, in um."""
    return float(np.sqrt(np.mean(np.sum(np.asarray(v_mm) ** 2, axis=1)))) * 1e3


def table_residuals(
    fld: ErrorField, tables, ctx: Context
) -> tuple[float, list[tuple[float, np.ndarray]]]:
    """What 1-D tables leave: (RMS um at the tables' tool offset, [(RMS um, tool offset)]
    at every other tool offset of the plan), over the check poses."""
    from volcal.outputs.compensation.grid import correction_residual

    q = check_poses(fld)
    at_table = rms_um(correction_residual(fld, tables, q, ctx.table_tool))
    others = [
        (rms_um(correction_residual(fld, tables, q, t)), t)
        for t in ctx.tools
        if np.abs(t - ctx.table_tool).max() > 1e-9
    ]
    return at_table, others


def one_axis_built(
    ctx: Context,
    tables,
    spacing,
    render: Callable[[Compensation], Mapping[str, str | bytes]],
    values: str,
    not_carried: list[str],
    summary: list[dict[str, Any]],
    limits: dict[str, Any],
    notes: list[str],
) -> Built:
    """The :class:`Built` of a format of 1-D tables (siemens, heidenhain): its residual is
    what the axis corrections of ``tables`` leave (first order), ``spacing`` (a
    :class:`~volcal.outputs.compensation.grid.Spacing`) the node spacing over every axis,
    for the tables' tool offset ``ctx.table_tool``."""
    from volcal.outputs.compensation.grid import correction_residual

    fld = ctx.field

    def residual(q, t):
        return correction_residual(fld, tables, q, t)

    return Built(
        residual,
        render,
        values,
        {a.name: spacing.h[i] for i, a in enumerate(fld.axes)},
        spacing.bound_um,
        None,
        not_carried,
        summary,
        limits,
        notes,
        table_tool=np.asarray(ctx.table_tool, float),
    )


def tool_offset_not_carried(others: list[tuple[float, np.ndarray]]) -> list[str]:
    """The NOT CARRIED line of 1-D tables for the tool offsets other than the tables' one
    (``others`` from :func:`table_residuals`): the worst RMS um they leave; none without
    other tool offsets."""
    if not others:
        return []
    worst, wt = max(others, key=lambda x: x[0])
    return [
        "the tool-length-dependent part of the angular errors (the tables know no tool "
        f"offset): up to {worst:.3g} um RMS at tool offset ("
        + ", ".join(f"{v:g}" for v in wt)
        + ") mm"
    ]


def check_axis_names(fld: ErrorField, names: Mapping[str, Any]) -> None:
    """Raise :class:`InputError` (source ``--axis``) if ``names`` (controller axis names by
    model axis) names an axis the model does not have."""
    inputs = [a.name for a in fld.axes]
    unknown = sorted(set(names) - set(inputs))
    if unknown:
        raise InputError(f"unknown axis name(s) {unknown}; the model has {inputs}", source="--axis")


def _builder(fmt: str):
    from importlib import import_module

    return import_module(f"volcal.outputs.compensation.{fmt}").build


def compensate(
    result: Any,
    format: str,
    out_dir: str | Path | None,
    *,
    tolerance_um: float | None = None,
    tools=None,
    table_tool=(0.0, 0.0, 0.0),
    sign: str = "correction",
    axis_names: dict[str, str] | None = None,
    max_points: int | None = None,
    max_tables: int | None = None,
    target: str | None = None,
    tool_direction: str = "-z",
    machine_datum: dict[str, float] | None = None,
    general_axis_names: bool = False,
    control_dir: str | None = None,
    force: bool | None = None,
) -> Compensation:
    """Write the compensation files of ``format`` for an identification ``result`` to
    ``out_dir`` (None: compute and report only) and return what was written with its
    residual figures (:class:`Compensation`).

    result: an :class:`~volcal.analysis.identify.IdentificationResult`, a
        :class:`~volcal.outputs.results.LoadedResult`, a result folder, or any object with
        ``machine``, ``error_model`` and ``theta``; never modified.
    format: one of :data:`FORMATS`.
    tolerance_um: the largest interpolation error at the tool point the node spacing must
        meet (default 0.1 um; for the generic grid with no tolerance given, the smallest
        of 0.1, 0.2, 0.5, 1, 2, 5, 10 um whose grid fits ``max_points``, reported).
    tools: tool offsets (K, 3) mm of the residual report and of the generic volumetric
        grids (default: the tool offsets of the measurement, else (0, 0, 0)).
    table_tool: the tool offset the 1-D tables (siemens, heidenhain) are built for.
    sign: ``"correction"`` (default, -error) or ``"error"``: what the generic grid holds.
        ISG files and the generic ISO tables hold errors (the controller computes the
        correction); SINUMERIK and HEIDENHAIN tables hold the compensation values with
        the sign their manuals document (``"error"`` is refused there).
    axis_names: controller axis identifiers by model axis name (ISG logical axis
        numbers, SINUMERIK machine axis names, HEIDENHAIN axis keys).
    max_points, max_tables, target: controller limits (see each format; ``target``
        ``"840d"`` or ``"828d"`` for siemens); exceeding them raises :class:`LimitError`
        naming the limit.
    tool_direction: ISG's tool zero orientation N0 (``-z`` default).
    machine_datum: {axis: position (mm / deg) of the model's zero of that axis in the
        control's machine coordinates}; table positions (SINUMERIK MIN / MAX, HEIDENHAIN
        AXISPOS, which the manuals give from the machine datum) are model positions plus
        this offset (default 0 for every axis, stated in the files).
    general_axis_names: SINUMERIK: name the machine axes AX1, AX2, ... (model order;
        for multi-channel controls) instead of X1, Y1, ...; ``axis_names`` still wins.
    control_dir: the folder of the files on the control (ISG ``.lis`` file names,
        HEIDENHAIN ``.CMA`` entries); default: bare file names, stated in the files.
    """
    fmt = str(format).lower()
    if fmt not in FORMATS:
        raise InputError(
            f"unknown format {format!r}; expected one of {list(FORMATS)}", source="--format"
        )
    if sign not in ("correction", "error"):
        raise InputError(f"expected 'correction' or 'error', got {sign!r}", source="--sign")
    auto_tolerance = tolerance_um is None
    try:
        tolerance_um = 0.1 if tolerance_um is None else float(tolerance_um)
    except (TypeError, ValueError):
        raise InputError(f"expected a number, got {tolerance_um!r}", source="--tolerance") from None
    if not (math.isfinite(tolerance_um) and tolerance_um > 0):
        raise InputError(f"expected a tolerance > 0 um, got {tolerance_um!r}", source="--tolerance")
    for name, v in (("--max-points", max_points), ("--max-tables", max_tables)):
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1):
            raise InputError(f"expected a positive integer, got {v!r}", source=name)
    machine, em, theta, src, plan = as_field_input(result)
    fld = ErrorField(machine, em, theta)
    if tools is None:
        tools = plan if plan is not None else np.zeros((1, 3))
    tools = np.atleast_2d(np.asarray(tools, float))
    if tools.ndim != 2 or tools.shape[1] != 3 or not np.all(np.isfinite(tools)) or len(tools) == 0:
        raise InputError(
            "expected tool offsets as rows of three finite numbers (mm)", source="--tool"
        )
    tools = np.unique(tools, axis=0)
    table_tool = _parse_tool(table_tool, "--table-tool")
    if sign == "error" and fmt in ("siemens", "heidenhain"):
        raise InputError(
            f"the {fmt} tables hold compensation values with the sign the control's manual "
            "documents (docs/compensation.md); --sign applies to the generic grid only",
            source="--sign",
        )
    # options a format does not read are refused, not silently dropped
    for given, option, formats in (
        (machine_datum, "--machine-datum", ("siemens", "heidenhain")),
        (general_axis_names, "--general-axis-names", ("siemens",)),
        (control_dir, "--control-dir", ("isg", "heidenhain")),
    ):
        if given and fmt not in formats:
            raise InputError(
                f"{option} applies to the {' and '.join(formats)} format(s), not to {fmt}",
                source=option,
            )
    datum = _parse_datum(machine_datum, [a.name for a in fld.axes])
    created = datetime.now(UTC).isoformat(timespec="seconds")
    options = dict(
        axis_names=dict(axis_names or {}),
        max_points=max_points,
        max_tables=max_tables,
        target=target,
        tool_direction=tool_direction,
        auto_tolerance=auto_tolerance,
        machine_datum=datum,
        general_axis_names=bool(general_axis_names),
        control_dir=control_dir,
    )
    ctx = Context(
        fld,
        tolerance_um,
        tools,
        table_tool,
        sign,
        options,
        created,
        source_name(result, src, theta),
    )
    built = _builder(fmt)(ctx)
    # the residual over the workspace at every tool offset
    report_tools = tools
    if (
        built.table_tool is not None
        and not (np.abs(tools - built.table_tool).max(axis=1) < 1e-9).any()
    ):
        report_tools = np.vstack([built.table_tool, tools])
    q = check_poses(fld)
    rows = []
    res_all, pts_all = [], []
    for t in report_tools:
        res_all.append(built.residual(q, t))
        pts_all.append(fld.nominal(q, t))
    # one rigid motion of the workpiece frame for the whole setup (every tool offset)
    mod_all, rig_t, rig_w, centre = rigid_split(np.vstack(res_all), np.vstack(pts_all))
    for k, t in enumerate(report_tools):
        dp = fld.volumetric(q, t) * 1e3
        r = res_all[k] * 1e3
        rm = mod_all[k * len(q) : (k + 1) * len(q)] * 1e3
        nd, nr = np.linalg.norm(dp, axis=1), np.linalg.norm(r, axis=1)
        rows.append(
            {
                "tool_x_mm": float(t[0]),
                "tool_y_mm": float(t[1]),
                "tool_z_mm": float(t[2]),
                "uncorrected_rms_um": float(np.sqrt(np.mean(nd**2))),
                "uncorrected_max_um": float(nd.max()),
                "residual_rms_um": float(np.sqrt(np.mean(nr**2))),
                "residual_max_um": float(nr.max()),
                "residual_mod_rigid_rms_um": float(np.sqrt(np.mean(np.sum(rm**2, axis=1)))),
                "ratio": float(np.sqrt(np.mean(nr**2)) / np.sqrt(np.mean(nd**2))),
            }
        )
    per_tool = pd.DataFrame(rows)
    spacing = {}
    for ax, h in built.spacing.items():
        a = fld.axis(ax)
        spacing[ax] = f"{a.to_file(h):.4g} {a.unit}"
    comp = Compensation(
        format=fmt,
        title=_TITLES[fmt],
        path=None,
        files=[],
        values=built.values,
        tolerance_um=built.tolerance_um if built.tolerance_um is not None else tolerance_um,
        spacing=spacing,
        interpolation_bound_um=built.bound_um,
        interpolation_max_um=built.measured_um,
        per_tool=per_tool,
        not_carried=built.not_carried,
        tables=built.tables,
        limits=built.limits,
        n_poses=len(q),
        model=fld.spec.name,
        fingerprint=fld.spec.fingerprint(),
        source=ctx.source,
        created=created,
        table_tool=built.table_tool,
        notes=built.notes,
        rigid_translation_um=rig_t * 1e3,
        rigid_rotation_urad=rig_w * 1e6,
        rigid_centre_mm=centre,
    )
    ident = getattr(result, "identifiable", None)
    if ident is not None and not np.all(ident):
        comp.notes.append(
            f"{int(np.sum(~np.asarray(ident, bool)))} parameter(s) were not "
            "identifiable: the files carry the values the datum chose for them"
        )
    if out_dir is None and built.file_names is not None:
        # a report only: large grids are not formatted for nothing
        comp.files = sorted(built.file_names)
        return comp
    files = built.render(comp)
    comp.files = sorted(files)
    if out_dir is None:
        return comp
    files = dict(files)
    files["compensation.json"] = json.dumps(_json_safe(comp.to_dict()), indent=1) + "\n"
    files["compensation.md"] = report_markdown(comp)

    def writer(tmp: Path) -> None:
        for name, content in files.items():
            p = tmp / name
            if isinstance(content, bytes):
                p.write_bytes(content)
            else:
                p.write_text(content, encoding="utf-8", newline="")

    from volcal.base.folders import write_folder

    comp.path = write_folder(
        out_dir,
        tuple(files),
        WHAT,
        writer,
        marker="compensation.json",
        inputs=[src] if src is not None else (),
        force=force,
    )
    return comp


def _parse_datum(datum, axes: list[str]) -> dict[str, float]:
    out = {a: 0.0 for a in axes}
    for k, v in dict(datum or {}).items():
        if k not in out:
            raise InputError(
                f"unknown axis {k!r} in the machine datum; the model has {axes}",
                source="--machine-datum",
            )
        try:
            out[k] = float(v)
        except (TypeError, ValueError):
            raise InputError(
                f"expected a number (mm / deg) for axis {k}, got {v!r}", source="--machine-datum"
            ) from None
        if not math.isfinite(out[k]):
            raise InputError(f"expected a finite number for axis {k}", source="--machine-datum")
    return out


def control_path(folder: str | None, name: str) -> str:
    """``name`` in the control's ``folder`` (its own separator: backslash when the folder
    has one or a drive colon, else slash); the bare name without a folder."""
    if not folder:
        return name
    sep = "\\" if ("\\" in folder or ":" in folder) else "/"
    return folder.rstrip("\\/") + sep + name


def source_name(result: Any, src: Path | None, theta: np.ndarray) -> str:
    """How the files name the identification result: the name of its folder (never an
    absolute path of the user's machine) and a fingerprint of its parameters."""
    import hashlib

    fp = hashlib.sha256(np.ascontiguousarray(theta, dtype="<f8").tobytes()).hexdigest()[:12]
    name = Path(src).resolve().name if src is not None else "(in memory)"
    return f"{name} (parameters sha256 {fp})"


def _json_safe(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _json_safe(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def report_markdown(comp: Compensation) -> str:
    """compensation.md: what was written, spacing, limits, residual per tool offset."""
    from tabulate import tabulate

    def table(df: pd.DataFrame) -> str:
        return tabulate(df, headers="keys", tablefmt="github", showindex=False, floatfmt=".4g")

    lines = [
        f"# Compensation: {comp.format}",
        "",
        comp.title,
        "",
        f"Model `{comp.model}` (fingerprint `{comp.fingerprint}`), identification "
        f"result `{comp.source}`, created {comp.created}.",
        "",
        f"**Values.** {comp.values}",
        "",
        f"**Grid.** {comp.spacing_line()}.",
        "",
        f"**Residual.** {comp.residual_line()} (first-order model, the files applied as "
        "the controller applies them: linear interpolation between nodes, modulo 360 "
        "deg on full-turn rotary axes).",
        "",
        table(comp.per_tool),
        "",
        "**Setup part.** " + ". ".join(comp.setup_lines()) + ".",
        "",
    ]
    if comp.table_tool is not None:
        lines += [
            "The 1-D tables are built for the tool offset ("
            + ", ".join(f"{v:g}" for v in comp.table_tool)
            + ") mm; at other tool offsets the "
            "tool-length-dependent part of the error remains.",
            "",
        ]
    lines += ["**What this format cannot carry.**", ""]
    lines += [f"- {n}" for n in comp.not_carried] or ["- nothing beyond the interpolation error"]
    lines += ["", "**Files.**", ""] + [f"- `{f}`" for f in comp.files]
    if comp.tables:
        lines += ["", "**Tables.**", "", table(pd.DataFrame(comp.tables))]
    if comp.limits:
        lines += ["", "**Controller limits checked.**", ""]
        lines += [f"- {k}: {v}" for k, v in comp.limits.items()]
    if comp.notes:
        lines += ["", "**Notes.**", ""] + [f"- {n}" for n in comp.notes]
    return "\n".join(lines) + "\n"
