"""One self-contained HTML document from an identification result, to hand to a customer.

:func:`html_report` reads a result folder written by ``volcal identify`` (through
:func:`volcal.outputs.results.load_result` and the folder's tables; nothing is identified
again) and, optionally, a compensation export written by ``volcal compensate``, and
renders ``templates/report/report.html.j2`` into one HTML document:

* header: model, dates, volcal versions, the data file and the folders read;
* model: axes, travel, the error model (bases of the component error motions);
* data: readings, stations, poses, tool offsets, where the reading uncertainties came from;
* the datum in force; the identification (strategy, solver status, chi2/dof, residual RMS
  and the model adequacy verdict: a fit that does not fit says so in a red banner);
* what the data could not determine; the uncertainties (largest parameter uncertainties,
  volumetric uncertainty); every parameter with six significant digits; the plots;
* with a compensation export: its summary (format, grid spacing, residual after
  compensation, what the format cannot carry).

The document needs nothing else: CSS is inline, every plot is a ``data:image/png``
URI, there is no script and no external address.  All text goes through Jinja2's
autoescape.  :func:`write_report` writes it atomically (temporary file in the same folder,
then ``os.replace``) and can print it to PDF through a headless Chromium.
"""

from __future__ import annotations

import base64
import json
import logging
import os
import shutil
import subprocess
import tempfile
from collections.abc import Callable, Iterable, Mapping
from datetime import UTC, datetime
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from volcal import __version__
from volcal.analysis.adequacy import STRUCTURE_P, Adequacy
from volcal.base.exceptions import InputError
from volcal.outputs.report_env import TEMPLATE_DIR as TEMPLATE_DIR
from volcal.outputs.report_env import code_spans as code_spans
from volcal.outputs.report_env import environment as _environment
from volcal.outputs.report_env import number as _g
from volcal.outputs.results import (
    OPTIONAL_FILES,
    PLOT_FILES,
    RESULT_FILES,
    LoadedResult,
    load_result,
)

if TYPE_CHECKING:
    from volcal.outputs.plot_process import PlotProcess

log = logging.getLogger(__name__)

__all__ = [
    "html_report",
    "write_report",
    "find_browser",
    "missing_plots",
    "find_comparison",
    "TEMPLATE",
]

TEMPLATE = "report.html.j2"
#: how many of the largest parameter uncertainties the uncertainty section lists per unit
LARGEST_UNCERTAINTIES = 5
#: seconds a headless browser may take to print the PDF
BROWSER_TIMEOUT = 180.0

_MANIFEST = "manifest.json"
_COMPENSATION_FORMAT = "volcal-compensation"
_UNITS = {"um": "µm", "urad": "µrad"}
_PLOT_CAPTIONS = {
    "component_errors.png": "Component error motions of each axis (error = actual − "
    "nominal), band = ±2u (k = 2)",
    "volumetric_map.png": "Volumetric error over the workspace",
    "residuals.png": "Residuals of the length readings (model - measured)",
    "residuals_vs_axes.png": "Normalised residuals against each axis position, binned means",
    "correlations.png": "Correlations of the identifiable parameters (basis coefficients) "
    "and the strongest pairs",
}


# --------------------------------------------------------------------------------------
# formatting


def _unit(u: Any) -> str:
    """Report unit as a reader writes it (um -> µm)."""
    return _UNITS.get(str(u), str(u))


def _option(v: Any) -> str:
    """An identification option as a reader writes it, not as Python does (``None`` ->
    "not given", ``True`` -> "yes", lists joined)."""
    if v is None:
        return "not given"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (list, tuple)):
        return ", ".join(_option(x) for x in v) or "none"
    if isinstance(v, dict):
        return "; ".join(f"{k} {_option(x)}" for k, x in v.items()) or "none"
    return str(v)


def _axis_unit(axis: Any) -> str:
    return "deg" if axis.is_rotary else "mm"


# --------------------------------------------------------------------------------------
# inputs


def _read_json(path: Path, what: str) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"cannot read {what} ({exc})", source=str(path)) from None
    if not isinstance(doc, dict):
        raise InputError(f"not {what}", source=str(path))
    return doc


def _load(result_dir: Path) -> LoadedResult:
    """The result, with messages that name the folder for the usual mistakes."""
    if not result_dir.exists():
        raise InputError("no such result folder", source=str(result_dir))
    if not result_dir.is_dir():
        raise InputError(
            "expected a result folder written by `volcal identify`, got a file",
            source=str(result_dir),
        )
    return load_result(result_dir)


def _read_table(folder: Path, name: str) -> pd.DataFrame | None:
    """A CSV table of the folder, or None when the folder has none (older or partial
    results: the report leaves the section out instead of failing)."""
    path = folder / name
    if not path.is_file():
        return None
    try:
        return pd.read_csv(path)
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read the table ({exc})", source=str(path)) from None


def _load_compensation(comp_dir: Path, fingerprint: str | None) -> dict[str, Any]:
    """compensation.json of an export of ``volcal compensate``, checked against its
    manifest and against the model of the result it is reported with."""
    from volcal.base.folders import verify_manifest

    if not comp_dir.is_dir():
        raise InputError(
            "no such compensation folder (expected a folder written by `volcal compensate`)",
            source=str(comp_dir),
        )
    file = comp_dir / "compensation.json"
    if not file.is_file():
        raise InputError(
            "no compensation.json here; expected a folder written by `volcal compensate`",
            source=str(comp_dir),
        )
    verify_manifest(comp_dir)
    doc = _read_json(file, "a compensation summary")
    if doc.get("format") != _COMPENSATION_FORMAT:
        raise InputError(
            f'not a volcal compensation export (expected "format": "{_COMPENSATION_FORMAT}")',
            source=str(file),
        )
    if fingerprint and doc.get("model_fingerprint") not in (None, fingerprint):
        # a report that pairs an identification with another machine's tables would be
        # worse than none
        raise InputError(
            f"the compensation was made for another model ({doc.get('model')!r}, fingerprint "
            f"{doc.get('model_fingerprint')}) than the identification result "
            f"(fingerprint {fingerprint})",
            source=str(comp_dir),
        )
    return doc


def _png_data_uri(path: Path) -> str:
    """The PNG as a ``data:`` URI (the document must not refer to any file)."""
    data = path.read_bytes()
    if not data.startswith(b"\x89PNG\r\n\x1a\n"):
        raise InputError("not a PNG image", source=str(path))
    return _png_bytes_uri(data)


def _caption(name: str) -> str:
    """Caption of a plot file; a plot this module does not know gets its file name in words."""
    if name in _PLOT_CAPTIONS:
        return _PLOT_CAPTIONS[name]
    words = Path(name).stem.replace("_", " ").strip()
    return words[:1].upper() + words[1:]


def _png_bytes_uri(data: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(data).decode("ascii")


def missing_plots(result_dir: Path) -> list[str]:
    """The result plots (:data:`PLOT_FILES`) the folder lacks, e.g. written with
    ``volcal identify --no-plots``: the report draws them."""
    return [n for n in PLOT_FILES if not (Path(result_dir) / n).is_file()]


def _drawn_plots(
    res: LoadedResult, names: list[str], plotter: PlotProcess | None = None
) -> dict[str, bytes]:
    """The result plots ``names`` (of :data:`PLOT_FILES`) drawn from the saved result, as
    PNG bytes: the figures ``volcal identify`` draws, from the same data.  With a
    ``plotter`` its children draw them, two at a time, into a temporary folder."""
    import io

    from volcal.base import progress
    from volcal.outputs.plots import saved_plot_requests

    out: dict[str, bytes] = {}
    with progress.stage("drawing the plots the result folder lacks"):
        requests = [r for r in saved_plot_requests(res) if r[0] in names]
        if plotter is None:
            for name, draw, data, _cost in requests:
                buf = io.BytesIO()
                draw(data, buf)
                out[name] = buf.getvalue()
            return out
        with tempfile.TemporaryDirectory(prefix="volcal-report-") as tmp:
            for name, draw, data, cost in requests:
                plotter.draw(draw, data, Path(tmp) / name, cost=cost)
            plotter.wait()
            for name, *_ in requests:
                out[name] = (Path(tmp) / name).read_bytes()
    return out


def _plots(
    res: LoadedResult, draw_missing: bool, plotter: PlotProcess | None = None
) -> list[dict[str, str]]:
    """The plots section: every plot of the result folder (:func:`_plot_names`) and, with
    ``draw_missing``, the result plots it lacks, drawn from the saved result."""
    folder = res.path
    names = _plot_names(folder)
    missing = missing_plots(folder) if draw_missing else []
    drawn = _drawn_plots(res, missing, plotter) if missing else {}
    order = [n for n in PLOT_FILES if n in names or n in drawn]
    order += [n for n in names if n not in PLOT_FILES]
    return [
        {
            "name": n,
            "caption": _caption(n),
            "src": _png_bytes_uri(drawn[n]) if n in drawn else _png_data_uri(folder / n),
        }
        for n in order
    ]


def _plot_names(folder: Path) -> list[str]:
    """The plots of the folder: the known ones in their order, then any other PNG the
    manifest lists (a file volcal did not write is never embedded)."""
    names = [n for n in PLOT_FILES if (folder / n).is_file()]
    manifest = folder / _MANIFEST
    if manifest.is_file():
        try:
            listed = json.loads(manifest.read_text(encoding="utf-8")).get("files", {})
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError):
            listed = {}
        names += sorted(
            n for n in listed if n.endswith(".png") and n not in names and (folder / n).is_file()
        )
    return names


# --------------------------------------------------------------------------------------
# sections


def _header(res: LoadedResult, title: str | None, comp_dir: Path | None) -> dict[str, Any]:
    meta = res.meta
    versions = meta.get("versions") or {}
    spec = res.spec
    return {
        "title": title or f"Geometric error identification: {spec.name}",
        "model": spec.name,
        "description": spec.description,
        "created": str(meta.get("created", "")),
        "generated": datetime.now(UTC).isoformat(timespec="seconds"),
        "volcal_result": str(versions.get("volcal", "?")),
        "volcal_report": __version__,
        "other_versions": ", ".join(
            f"{k} {v}" for k, v in versions.items() if k != "volcal" and v is not None
        ),
        "data": str(meta.get("data") or "(data given in memory)"),
        "result_dir": str(res.path),
        "compensation_dir": str(comp_dir) if comp_dir is not None else "",
    }


def _model(res: LoadedResult) -> dict[str, Any]:
    spec, em = res.spec, res.error_model
    axes = [
        {
            "name": a.name,
            "kind": a.kind,
            "direction": a.direction,
            "branch": a.branch,
            "travel": f"{a.travel[0]:g} … {a.travel[1]:g} {_axis_unit(a)}",
            "reference": f"{a.reference:g} {_axis_unit(a)}",
        }
        for a in spec.axes
    ]
    bases: dict[str, list[str]] = {}
    for s, f in zip(em.errors, em.forms):
        label = "constant (location error)" if s.kind == "location" else f.describe()
        bases.setdefault(label, []).append(s.name)
    return {
        "axes": axes,
        "n_errors": em.n_errors,
        "n_params": em.n_params,
        "datum": em.datum,
        "bases": [{"label": k, "errors": ", ".join(v)} for k, v in bases.items()],
    }


def _data(res: LoadedResult, residuals: pd.DataFrame | None) -> dict[str, Any]:
    meta = res.meta
    out: dict[str, Any] = {
        "file": str(meta.get("data") or "(data given in memory)"),
        "n_readings": int(meta.get("n_readings") or 0),
        "n_rejected": int(meta.get("n_rejected") or 0),
        "sigma_source": str(meta.get("sigma_source") or "not recorded"),
        "n_stations": len(meta.get("stations") or []),
        "n_poses": None,
        "n_points": None,
        "tools": [],
        "stations": [],
    }
    if residuals is not None and len(residuals):
        axes = [a for a in res.spec.axis_names if a in residuals]
        if axes:
            out["n_poses"] = int(len(residuals[axes].drop_duplicates()))
        if "point" in residuals:
            out["n_points"] = int(residuals["point"].nunique())
        if "station" in residuals:
            out["n_stations"] = int(residuals["station"].nunique())
        tcols = [c for c in ("tool_x", "tool_y", "tool_z") if c in residuals]
        if len(tcols) == 3:
            tools = residuals[tcols].drop_duplicates().to_numpy(float)
            out["tools"] = [f"({x:g}, {y:g}, {z:g})" for x, y, z in tools]
    for st in meta.get("stations") or []:
        out["stations"].append(
            {
                "name": str(st.get("station", "")),
                "xyz": ", ".join(_g(st.get(k), 7) for k in ("x_mm", "y_mm", "z_mm")),
                "dead": _g(st.get("dead_length_mm"), 4),
                "u": ", ".join(_g(st.get(k), 3) for k in ("u_x_um", "u_y_um", "u_z_um")),
                "fixed": "yes" if st.get("fixed") else "no",
            }
        )
    return out


def _datum(res: LoadedResult) -> dict[str, Any]:
    tab = res.datum
    if tab is None or not len(tab):
        return {"name": res.error_model.datum, "conditions": [], "n_imposed": 0, "n": 0}
    conds = [
        {
            "condition": str(r["condition"]),
            "class": str(r.get("class", "")),
            "imposed": bool(r["imposed"]),
            "value": _g(r.get("value"), 4),
            "unit": _unit(r.get("unit", "")),
        }
        for r in tab.to_dict(orient="records")
    ]
    return {
        "name": res.error_model.datum,
        "conditions": conds,
        "n_imposed": sum(c["imposed"] for c in conds),
        "n": len(conds),
    }


def _identification(res: LoadedResult) -> dict[str, Any]:
    meta = res.meta
    ad = res.adequacy
    verdict = None
    if ad:
        lo, hi = (ad.get("interval") or [None, None])[:2]
        # the three outcomes (results saved before them read adequate / inadequate)
        adq = Adequacy.from_dict(ad)
        verdict = {
            "adequate": adq.adequate,
            "verdict": adq.verdict,
            "summary": adq.summary,
            "threshold": f"{STRUCTURE_P:g}",
            "where": (
                "above"
                if adq.chi2_per_dof > adq.interval[1]
                else "below"
                if adq.chi2_per_dof < adq.interval[0]
                else "inside"
            ),
            "message": str(ad.get("message", "")),
            "chi2_per_dof": _g(ad.get("chi2_per_dof")),
            "interval": f"[{_g(lo)}, {_g(hi)}]",
            "dof": ad.get("dof"),
            "causes": [
                {
                    "kind": str(c.get("kind", "")),
                    "share": _g(100.0 * float(c.get("share", 0.0)), 3),
                    "text": str(c.get("text", "")),
                }
                for c in ad.get("causes") or []
            ],
            "warnings": [str(w) for w in ad.get("warnings") or []],
            "budget_factor": _g(ad.get("budget_factor")),
            "max_abs": _g((ad.get("outliers") or {}).get("max_abs")),
            "structure": [
                {
                    "axis": (
                        f"axis {s.get('axis', '')}"
                        if s.get("kind", "axis") == "axis"
                        else str(s.get("axis", ""))
                    ),
                    "significant": float(s.get("p_value", 1.0)) < STRUCTURE_P,
                    "bins": s.get("n_bins"),
                    "f": _g(s.get("f"), 3),
                    "p": (
                        _g(s.get("p_value"), 2) if (s.get("log10_p") or 0) > -300 else "< 1e-300"
                    ),
                    "share": _g(100.0 * float(s.get("explained_share") or 0.0), 3),
                }
                for s in ad.get("structure") or []
            ],
        }
    phases = [
        {
            "n": k + 1,
            "status": str(p.get("status", "")),
            "success": "yes" if p.get("success") else "no",
            "iterations": p.get("iterations"),
            "polish": p.get("gauss_newton_polish_steps"),
            "seconds": _g(p.get("seconds"), 3),
        }
        for k, p in enumerate(meta.get("phases") or [])
    ]
    conditions = [
        {"name": str(k), "value": _g(v)}
        for k, v in (meta.get("conditions") or {}).items()
        if k != "chi2_per_dof"
    ]
    options = meta.get("options") or {}
    return {
        "strategy": str(meta.get("strategy", "")),
        "status": str(meta.get("status", "")),
        "success": bool(meta.get("success", False)),
        "chi2_per_dof": _g(meta.get("chi2_per_dof")),
        "residual_rms_um": _g(meta.get("residual_rms_um")),
        "seconds": _g(meta.get("seconds"), 3),
        "phases": phases,
        "conditions": conditions,
        "options": [
            {"name": str(k).replace("_", " "), "value": _option(v)} for k, v in options.items()
        ],
        "timings": [
            {"stage": str(k), "seconds": _g(v, 3)} for k, v in (meta.get("timings_s") or {}).items()
        ],
        "adequacy": verdict,
        "notes": [str(n) for n in meta.get("notes") or []],
        # several instruments' tables: each one's check (volcal.analysis.fusion)
        "instruments": [
            {
                "data": str(r.get("data", "")),
                "instrument": str(r.get("instrument", "")),
                "n_readings": r.get("n_readings"),
                "dof": _g(r.get("dof"), 4),
                "chi2_per_dof": _g(r.get("chi2_per_dof"), 4),
                "interval": f"[{_g(r.get('chi2_low'), 4)}, {_g(r.get('chi2_high'), 4)}]",
                "verdict": str(r.get("verdict", "")),
                "scale": (
                    f"{_g(r['scale_factor'], 3)} ± {_g(r.get('u_scale_factor'), 2)} "
                    f"(95 %: {_g(r.get('scale_low_95'), 3)} .. {_g(r.get('scale_high_95'), 3)})"
                    if r.get("scale_factor") is not None
                    else ""
                ),
                "determined_alone": r.get("determined_alone"),
                "field_u": _g(r.get("field_u_cumulative_um"), 3),
            }
            for r in meta.get("instruments") or []
        ],
    }


def _unidentifiable(res: LoadedResult) -> dict[str, Any]:
    meta = res.meta
    names = meta.get("unidentifiable")
    if names is None:
        names = list(np.asarray(res.error_model.param_names)[~res.identifiable])
    return {
        "parameters": [str(n) for n in names],
        "combinations": [str(c) for c in meta.get("null_space") or []],
        "gauge": [str(c) for c in meta.get("gauge") or []],
        "why": str((meta.get("unidentifiable_explanation") or {}).get("text") or ""),
    }


def _parameters(res: LoadedResult) -> list[dict[str, Any]]:
    """Every parameter, six significant digits (the table a customer checks values in)."""
    table = res.parameters()
    return [
        {
            "name": str(r.name),
            "value": _g(r.value, 6),
            "unit": _unit(r.unit),
            "std": (
                "imposed by the datum"
                if getattr(r, "imposed", False)
                else _g(r.u, 6)
                if r.identifiable
                else "not identifiable"
            ),
            "identifiable": bool(r.identifiable),
        }
        for r in table.itertuples(index=False)
    ]


def _uncertainty(res: LoadedResult, grid: pd.DataFrame | None) -> dict[str, Any]:
    table = res.parameters()
    largest = []
    for unit in dict.fromkeys(table["unit"]):
        sub = table[
            (table["unit"] == unit)
            & table["identifiable"]
            & ~table["imposed"]
            & np.isfinite(table["u"])
        ]
        for r in sub.sort_values("u", ascending=False).head(LARGEST_UNCERTAINTIES).itertuples():
            largest.append(
                {
                    "name": str(r.name),
                    "value": _g(r.value, 6),
                    "std": _g(r.u, 4),
                    "unit": _unit(unit),
                }
            )
    meta = res.meta
    vol: dict[str, Any] = {
        "max_error": _g(meta.get("max_volumetric_um")),
        "max_pose": ", ".join(
            f"{a} = {_g(v, 6)} {_axis_unit(res.spec.axis(a))}"
            for a, v in (meta.get("max_volumetric_pose") or {}).items()
        ),
        "axes": ", ".join(meta.get("max_volumetric_axes") or []) or "no axis",
        "available": False,
    }
    ucols = ["u_dx_um", "u_dy_um", "u_dz_um"]
    if grid is not None and len(grid) and all(c in grid for c in ucols):
        u = grid[ucols].to_numpy(float)
        u_norm = np.sqrt(np.sum(u**2, axis=1))
        ok = np.isfinite(u_norm)
        vol.update(
            available=bool(ok.any()),
            n_poses=int(len(grid)),
            n_undetermined=int((~ok).sum()),
            u_max=_g(np.max(u_norm[ok])) if ok.any() else "",
            u_rms=_g(np.sqrt(np.mean(u_norm[ok] ** 2))) if ok.any() else "",
            u_components=", ".join(
                f"{c[2:4]} {_g(np.nanmax(grid[c].to_numpy(float)))}" for c in ucols
            ),
        )
        if "norm_um" in grid:
            n = grid["norm_um"].to_numpy(float)
            vol["rms_error"] = _g(np.sqrt(np.mean(n[np.isfinite(n)] ** 2)))
    return {"largest": largest, "volumetric": vol}


def _error_motions(
    res: LoadedResult, comp: pd.DataFrame | None, motions: pd.DataFrame | None
) -> dict[str, Any]:
    """The error-motion section: peak-to-peak per motion (error_motions.csv, or computed
    from the saved result for a folder written before it existed) and the motions at
    positions along each axis (rows of component_errors.csv)."""
    from volcal.outputs.results import (
        error_motion_table,
        error_motions_at_positions,
        positions_text,
    )

    if motions is None:
        motions = error_motion_table(res.error_model, res.theta, res.cov_theta, res.identifiable)
    peak = [
        {
            "axis": str(r.axis),
            "name": str(r.error_motion),
            "description": str(r.description),
            "pp": _g(r.peak_to_peak_in_unit, 4),
            "u": _g(r.u_peak_to_peak_in_unit, 2) or "not identifiable",
            "unit": _unit(r.unit),
            "min": _g(r.min_in_unit, 4),
            "max": _g(r.max_in_unit, 4),
            "at_min": f"{_g(r.position_of_min_in_axis_unit, 6)} {r.axis_unit}",
            "at_max": f"{_g(r.position_of_max_in_axis_unit, 6)} {r.axis_unit}",
        }
        for r in motions.itertuples(index=False)
    ]
    tables = []
    for axis, t in error_motions_at_positions(comp) if comp is not None else []:
        pos, cols = t.columns[0], list(t.columns[1:])

        def head(c: str) -> str:
            name, _, unit = c.rpartition("_")
            return f"{name} ({_unit(unit)})"

        tables.append(
            {
                "axis": axis,
                "where": positions_text(t),
                "head": [head(pos).replace("position", f"{axis} position")]
                + [head(c) for c in cols],
                "rows": [
                    [_g(r[pos], 6)] + [_g(0.0 if abs(r[c]) < 1e-9 else r[c], 3) for c in cols]
                    for _, r in t.iterrows()
                ],
            }
        )
    return {"peak": peak, "tables": tables}


def _compensation(doc: Mapping[str, Any], comp_dir: Path) -> dict[str, Any]:
    spacing = doc.get("spacing") or {}
    per_tool = [
        {
            "tool": f"({_g(t.get('tool_x_mm'))}, {_g(t.get('tool_y_mm'))}, "
            f"{_g(t.get('tool_z_mm'))})",
            "uncorrected_rms": _g(t.get("uncorrected_rms_um")),
            "uncorrected_max": _g(t.get("uncorrected_max_um")),
            "residual_rms": _g(t.get("residual_rms_um")),
            "residual_max": _g(t.get("residual_max_um")),
            "ratio": _g(100.0 * float(t.get("ratio") or 0.0), 3),
        }
        for t in doc.get("per_tool") or []
    ]
    ratio = doc.get("ratio")
    return {
        "folder": str(comp_dir),
        "format": str(doc.get("compensation_format", "")),
        "title": str(doc.get("title", "")),
        "values_text": str(doc.get("values", "")),
        "created": str(doc.get("created", "")),
        "source": str(doc.get("source", "")),
        "tolerance": _g(doc.get("tolerance_um")),
        "spacing": ", ".join(f"{k} {v}" for k, v in spacing.items()),
        "interpolation_bound": _g(doc.get("interpolation_bound_um")),
        "interpolation_max": _g(doc.get("interpolation_max_um")),
        "uncorrected_rms": _g(doc.get("uncorrected_rms_um")),
        "residual_rms": _g(doc.get("residual_rms_um")),
        "residual_max": _g(doc.get("residual_max_um")),
        "ratio": _g(100.0 * float(ratio), 3) if ratio is not None else "",
        # the rigid motion multilateration does not determine (exports written before the
        # export stated it have none of these keys: the rows are left out)
        "setup_part": str(doc.get("setup_part") or ""),
        "residual_mod_rigid": _g(doc.get("residual_mod_rigid_rms_um")),
        "rigid_translation": ", ".join(_g(v) for v in doc.get("rigid_translation_um") or []),
        "rigid_rotation": ", ".join(_g(v) for v in doc.get("rigid_rotation_urad") or []),
        "n_poses": doc.get("n_poses"),
        "per_tool": per_tool,
        "not_carried": [str(n) for n in doc.get("not_carried") or []],
        "files": [str(f) for f in doc.get("files") or []],
        "limits": [f"{k}: {v}" for k, v in (doc.get("limits") or {}).items()],
        "notes": [str(n) for n in doc.get("notes") or []],
        "has_md": (comp_dir / "compensation.md").is_file(),
    }


# --------------------------------------------------------------------------------------
# the document


@lru_cache(maxsize=1)
def find_comparison(result_dir: Path, compare_dir: Path | None) -> tuple[Path, Path | None]:
    """(the result folder to report, the ``volcal compare`` folder to embed or None): a
    compare folder given as the result reports its reference result with the comparison;
    the reference result inside a compare folder finds its comparison by itself."""
    from volcal.outputs.compare_report import REFERENCE_DIR, is_comparison

    if result_dir.is_dir() and is_comparison(result_dir):
        ref = result_dir / REFERENCE_DIR
        if not ref.is_dir():
            raise InputError(
                "this `volcal compare` folder holds no reference result (its reference "
                "strategy did not solve); give a result folder with --result and this "
                "folder with --compare",
                source=str(result_dir),
            )
        return ref, compare_dir or result_dir
    if compare_dir is None and result_dir.name == REFERENCE_DIR:
        if is_comparison(result_dir.parent):
            return result_dir, result_dir.parent
    return result_dir, compare_dir


def _comparison(compare_dir: Path, model: str) -> dict[str, Any]:
    from volcal.outputs.compare_report import load_comparison, section_context

    doc, table, png = load_comparison(compare_dir)
    if doc.get("model") != model:
        raise InputError(
            f"the comparison was made for another model ({doc.get('model')!r}, the result "
            f"is of {model!r})",
            source=str(compare_dir),
        )
    return section_context(doc, table, png)


def html_report(
    result_dir: Path,
    *,
    compensation_dir: Path | None = None,
    compare_dir: Path | None = None,
    title: str | None = None,
    plots: bool = True,
    plotter: PlotProcess | None = None,
) -> str:
    """The report of the result folder ``result_dir`` as one self-contained HTML document.

    compensation_dir: a folder written by ``volcal compensate`` from this result (its
    summary is added); title: the document title (default: the model's name); plots: embed
    the folder's plots, and draw from the saved result those it lacks (a result written
    with ``--no-plots``; about a second); False: no plots section; plotter: plotting
    processes (:class:`volcal.outputs.plot_process.PlotProcess`) that draw them.  Raises
    :class:`InputError` naming the folder when it is missing or not a result (or the
    compensation folder is not an export for the same model).

    compare_dir: a folder written by ``volcal compare`` (its table, explanation and plot
    are added as a section); a compare folder given as ``result_dir`` reports its
    reference result with the comparison, and that reference result finds it by itself.
    """
    result_dir, compare_dir = find_comparison(
        Path(result_dir), None if compare_dir is None else Path(compare_dir)
    )
    res = _load(result_dir)
    cmp = _comparison(compare_dir, res.spec.name) if compare_dir is not None else None
    comp = None
    if compensation_dir is not None:
        compensation_dir = Path(compensation_dir)
        doc = _load_compensation(compensation_dir, res.meta.get("model_fingerprint"))
        comp = _compensation(doc, compensation_dir)
    folder = res.path
    residuals = _read_table(folder, "residuals.csv")
    grid = _read_table(folder, "volumetric_grid.csv")
    comp_table = _read_table(folder, "component_errors.csv")
    motions = _read_table(folder, "error_motions.csv")
    context = {
        "header": _header(res, title, compensation_dir),
        "model": _model(res),
        "data": _data(res, residuals),
        "datum": _datum(res),
        "ident": _identification(res),
        "unid": _unidentifiable(res),
        "uncertainty": _uncertainty(res, grid),
        "motions": _error_motions(res, comp_table, motions),
        "parameters": _parameters(res),
        "plots": _plots(res, draw_missing=True, plotter=plotter) if plots else [],
        "compensation": comp,
        "compare": cmp,
    }
    return _environment().get_template(TEMPLATE).render(context)


# --------------------------------------------------------------------------------------
# writing


def find_browser() -> str | None:
    """A headless-capable Chromium on the PATH (None when there is none)."""
    return (
        shutil.which("chromium")
        or shutil.which("chromium-browser")
        or shutil.which("google-chrome")
    )


def _protected(folders: Iterable[Path | None]) -> set[Path]:
    """The files of the input folders that the report must never replace: what the
    folder's manifest lists plus the names volcal writes there."""
    from volcal.outputs.compare_report import COMPARE_FILES
    from volcal.outputs.compensation import COMPENSATION_FILES

    known = (
        set(RESULT_FILES)
        | set(OPTIONAL_FILES)
        | set(COMPENSATION_FILES)
        | set(COMPARE_FILES)
        | {_MANIFEST}
    )
    out: set[Path] = set()
    for folder in folders:
        if folder is None or not Path(folder).is_dir():
            continue
        folder = Path(folder).resolve()
        names = set(known)
        try:
            doc = json.loads((folder / _MANIFEST).read_text(encoding="utf-8"))
            names |= set(doc.get("files", {}))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError):
            pass
        out |= {folder / n for n in names}
    return out


def _atomic_write(out: Path, write: Callable[[Path], Any]) -> None:
    """``write(tmp_path)`` fills a temporary file beside ``out``, renamed over ``out`` once
    complete: a reader never sees a half-written report, a failure leaves ``out`` as it
    was."""
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.tmp-", dir=out.parent)
    os.close(fd)
    try:
        write(Path(tmp))
        mask = os.umask(0o022)
        os.umask(mask)
        os.chmod(tmp, 0o666 & ~mask)  # mkstemp makes it private; follow the umask
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _print_pdf(browser: str, html: str, pdf: Path) -> None:
    """Print ``html`` to ``pdf`` with a headless Chromium (fresh profile, no sandbox:
    it runs as root in containers and CI)."""
    with tempfile.TemporaryDirectory(prefix="volcal-report-") as tmp:
        page = Path(tmp) / "report.html"
        page.write_text(html, encoding="utf-8")
        cmd = [
            browser,
            "--headless",
            "--disable-gpu",
            "--no-sandbox",
            "--disable-dev-shm-usage",
            f"--user-data-dir={Path(tmp) / 'profile'}",
            "--no-pdf-header-footer",
            f"--print-to-pdf={pdf}",
            page.as_uri(),
        ]
        log.info("printing to PDF with %s", browser)
        try:
            run = subprocess.run(
                cmd, capture_output=True, text=True, timeout=BROWSER_TIMEOUT, check=False
            )
        except (OSError, subprocess.TimeoutExpired) as exc:
            raise InputError(f"the browser engine could not print the PDF ({exc})") from None
        if run.returncode != 0 or not pdf.is_file() or pdf.stat().st_size == 0:
            tail = (run.stderr or "").strip().splitlines()[-1:] or ["no message"]
            raise InputError(
                f"the browser engine {browser} could not print the PDF (exit code "
                f"{run.returncode}: {tail[0]})"
            )


def write_report(
    result_dir: Path,
    out_file: Path,
    *,
    compensation_dir: Path | None = None,
    compare_dir: Path | None = None,
    pdf: bool = False,
    title: str | None = None,
    plots: bool = True,
    plotter: PlotProcess | None = None,
) -> Path:
    """Write the report of ``result_dir`` (see :func:`html_report`) to ``out_file`` and
    return the path written (``title``, ``plots``, ``plotter``: see :func:`html_report`).

    With ``pdf`` the document is printed to PDF by a headless Chromium and written to
    ``out_file`` with the suffix ``.pdf``; without one installed :class:`InputError` says
    so.  Atomic (temporary file in the same folder, then ``os.replace``); a file of the
    result or compensation folder is never replaced, any other existing ``out_file`` is.
    """
    out = Path(out_file)
    if pdf:
        out = out.with_suffix(".pdf")
    if out.is_dir():
        raise InputError("expected a file name, got a folder", source=str(out))
    # the folders the report reads, as find_comparison resolves them (a compare folder
    # given as the result reports its reference/ result; a reference/ result reads the
    # compare folder around it) as well as the ones given
    found = find_comparison(Path(result_dir), None if compare_dir is None else Path(compare_dir))
    if out.resolve() in _protected([Path(result_dir), compensation_dir, compare_dir, *found]):
        raise InputError(
            "the report would overwrite a file of the result, comparison or compensation "
            "folder; choose another name",
            source=str(out),
        )
    browser = None
    if pdf:
        # before any work: a missing browser is known at once
        browser = find_browser()
        if browser is None:
            raise InputError(
                "no browser engine is installed to print the PDF (looked for chromium, "
                "chromium-browser and google-chrome on the PATH); install Chromium or "
                "write the HTML report and print it from a browser"
            )
    html = html_report(
        Path(result_dir),
        compensation_dir=compensation_dir,
        compare_dir=compare_dir,
        title=title,
        plots=plots,
        plotter=plotter,
    )
    if browser is not None:
        _atomic_write(out, lambda tmp: _print_pdf(browser, html, tmp))
    else:
        _atomic_write(out, lambda tmp: tmp.write_text(html, encoding="utf-8"))
    log.info("wrote %s", out)
    return out
