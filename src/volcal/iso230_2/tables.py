"""Result tables (pandas DataFrames) in report units: positions in mm or deg, deviations in
um or arcsec, every column name ending in its unit."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from .parameters import SCALAR_PARAMETERS

__all__ = [
    "parameters_table",
    "targets_table",
    "polynomial_table",
    "correction_table",
    "correction_positions",
    "nice_spacing",
]

_DIR_NAMES = (("up", "+"), ("down", "-"), ("bidir", "bidir"))


def parameters_table(result) -> pd.DataFrame:
    """One row per axis parameter: axis, name (with unit suffix), value, unit, description."""
    rows = []
    k = result.settings.get("k", 2.0)
    for ax in result.axes:
        u = ax.units
        du, ds = u.deviation, u.deviation_scale
        iso, mdl = ax.iso, ax.model

        def add(name, value, unit, desc, ax=ax):
            rows.append(dict(axis=ax.axis, name=name, value=value, unit=unit, description=desc))

        add("targets", ax.readings.m, "-", "number of target positions m")
        add("cycles", ax.readings.n, "-", "number of bidirectional cycles n")
        add(
            f"first_target_{u.position}",
            ax.readings.targets[0] * u.position_scale,
            u.position,
            "smallest target position",
        )
        add(
            f"last_target_{u.position}",
            ax.readings.targets[-1] * u.position_scale,
            u.position,
            "largest target position",
        )
        for attr, stem, desc in SCALAR_PARAMETERS:
            add(f"{stem}_{du}", getattr(iso, attr) * ds, du, desc + " (ISO 230-2:2014)")
        add("poly_degree", mdl.degree, "-", "degree of the polynomial model (paper 003)")
        add(
            f"u_instrument_{du}",
            mdl.u_instrument * ds,
            du,
            "standard uncertainty of the constant instrument error, MPE / sqrt(3)",
        )
        if mdl.u_scale:
            add(
                "u_instrument_scale_ppm",
                mdl.u_scale * 1e6,
                "ppm",
                "relative standard uncertainty of the length-proportional instrument error",
            )
        add("k", k, "-", "coverage factor of the expanded uncertainties U")
        grid = np.linspace(mdl.lower, mdl.upper, 201)
        for lab, sym in _DIR_NAMES:
            add(
                f"U_max_{lab}_{du}",
                float(mdl.expanded(grid, lab, k).max() * ds),
                du,
                f"largest expanded uncertainty of the fitted deviation ({sym}) over the "
                "measured travel",
            )
        for lab, c2 in zip(mdl.labels, mdl.chi2):
            add(
                f"chi2_{lab}",
                c2,
                "-",
                f"chi-square of the fit ({lab}), {mdl.dof} degrees of freedom",
            )
    return pd.DataFrame(rows, columns=["axis", "name", "value", "unit", "description"])


def targets_table(result) -> pd.DataFrame:
    """Per axis and target: ISO values per direction and the fitted model at the target."""
    frames = []
    k = result.settings.get("k", 2.0)
    for ax in result.axes:
        u = ax.units
        du, ds = u.deviation, u.deviation_scale
        iso, mdl, P = ax.iso, ax.model, ax.readings.targets
        d = {
            "axis": ax.axis,
            f"target_{u.position}": P * u.position_scale,
            f"mean_up_{du}": iso.mean_up * ds,
            f"mean_down_{du}": iso.mean_down * ds,
            f"mean_bidir_{du}": iso.mean_bidir * ds,
            f"s_up_{du}": iso.s_up * ds,
            f"s_down_{du}": iso.s_down * ds,
            f"R_up_{du}": iso.R_up_i * ds,
            f"R_down_{du}": iso.R_down_i * ds,
            f"R_bidir_{du}": iso.R_i * ds,
            f"B_{du}": iso.B_i * ds,
            f"u_mean_up_{du}": mdl.u_means[0] * ds,
            f"u_mean_down_{du}": mdl.u_means[1] * ds,
        }
        for lab in ("up", "down"):
            d[f"fit_{lab}_{du}"] = mdl.value(P, lab) * ds
            d[f"U_fit_{lab}_{du}"] = mdl.expanded(P, lab, k) * ds
        frames.append(pd.DataFrame(d))
    return pd.concat(frames, ignore_index=True)


def polynomial_table(result) -> pd.DataFrame:
    """Coefficients a_k of Δ(P) = Σ a_k P^k per axis and direction (+, -, bidir), in
    deviation unit / position unit^k, with its standard uncertainty u and covariance.

    Column ``cov_a<l>`` of the row of a_k holds cov(a_k, a_l) in
    (deviation unit)^2 / (position unit)^(k+l); ``cov_unit`` spells it out per row.
    """
    rows = []
    for ax in result.axes:
        u = ax.units
        du, pu = u.deviation, u.position
        mdl = ax.model
        p = mdl.p
        scale = np.array([u.deviation_scale / u.position_scale**j for j in range(p)])
        for lab, sym in _DIR_NAMES:
            a, C = mdl.raw(lab)
            a = a * scale
            C = C * np.outer(scale, scale)
            for j in range(p):
                unit = du if j == 0 else (f"{du}/{pu}" if j == 1 else f"{du}/{pu}^{j}")
                row = dict(
                    axis=ax.axis,
                    direction=sym,
                    coefficient=f"a{j}",
                    power=j,
                    value=a[j],
                    u=math.sqrt(max(C[j, j], 0.0)),
                    unit=unit,
                )
                for l in range(p):
                    row[f"cov_a{l}"] = C[j, l]
                row["cov_unit"] = f"{du}^2/{pu}^({j}+l) for column cov_a<l>"
                rows.append(row)
    return pd.DataFrame(rows)


def nice_spacing(span: float, intervals: int = 50) -> float:
    """A 1-2-5 step giving about ``intervals`` intervals over ``span``."""
    if span <= 0:
        return 1.0
    raw = span / intervals
    e = 10.0 ** math.floor(math.log10(raw))
    for f in (1.0, 2.0, 5.0, 10.0):
        if raw <= f * e * (1 + 1e-12):
            return f * e
    return 10.0 * e


def correction_positions(lower: float, upper: float, spacing: float) -> np.ndarray:
    """Multiples of ``spacing`` inside [lower, upper] plus both ends (report units)."""
    if not (spacing > 0 and math.isfinite(spacing)):
        raise ValueError(f"spacing must be > 0, got {spacing}")
    n0 = math.ceil(lower / spacing - 1e-9)
    n1 = math.floor(upper / spacing + 1e-9)
    if n1 - n0 > 1_000_000:
        raise ValueError(f"spacing {spacing:g} gives more than a million positions")
    grid = np.arange(n0, n1 + 1) * spacing
    pts = np.concatenate([[lower], grid, [upper]])
    pts = np.unique(np.round(pts, 9))
    return pts[(pts >= lower - 1e-9) & (pts <= upper + 1e-9)]


def correction_table(
    result, spacing_mm: float | None = None, spacing_deg: float | None = None
) -> pd.DataFrame:
    """Fitted deviation, correction (= -deviation) and expanded uncertainty U (coverage
    factor k of the result) per direction and for the bidirectional mean, at the multiples
    of the spacing inside the measured range plus the first and last target (the model
    is not valid outside the measured range).  Default spacing: a 1-2-5 step giving about
    50 intervals."""
    frames = []
    k = result.settings.get("k", 2.0)
    for ax in result.axes:
        u = ax.units
        du, pu, ds = u.deviation, u.position, u.deviation_scale
        mdl = ax.model
        lo, hi = mdl.lower * u.position_scale, mdl.upper * u.position_scale
        spacing = spacing_mm if pu == "mm" else spacing_deg
        if spacing is None:
            spacing = nice_spacing(hi - lo)
        pos = correction_positions(lo, hi, spacing)
        x = pos / u.position_scale
        d = {"axis": ax.axis, f"position_{pu}": pos}
        for lab, _ in _DIR_NAMES:
            dev = mdl.value(x, lab) * ds
            d[f"deviation_{lab}_{du}"] = dev
            d[f"correction_{lab}_{du}"] = -dev + 0.0  # no "-0.0"
            d[f"U_{lab}_{du}"] = mdl.expanded(x, lab, k) * ds
        frames.append(pd.DataFrame(d))
    return pd.concat(frames, ignore_index=True)
