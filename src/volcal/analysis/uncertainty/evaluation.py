"""Comparing two results with their expanded uncertainties: the evaluation factor.

Paper 002, eq. (25) (the E_n number of proficiency testing, ISO 13528)::

    E_n = |y1 - y2| / sqrt(U(y1)^2 + U(y2)^2)

with U the expanded uncertainties (k = 2) of the two results.  E_n <= 1: the results agree
within their uncertainties ("satisfactory" in the paper).  With a reference value of
negligible uncertainty, U(y2) = 0.

:func:`compare_with_reference` joins a result table with a reference table (one row per
quantity: ``name, value, unit, U``) and adds E_n per quantity.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from volcal.base.exceptions import InputError

__all__ = ["evaluation_factor", "compare_with_reference", "UNIT_FACTORS"]

#: factors to the report units (um for lengths, urad for angles)
UNIT_FACTORS = {
    "um": ("um", 1.0),
    "µm": ("um", 1.0),
    "mm": ("um", 1e3),
    "nm": ("um", 1e-3),
    "urad": ("urad", 1.0),
    "µrad": ("urad", 1.0),
    "mrad": ("urad", 1e3),
    "rad": ("urad", 1e6),
    "arcsec": ("urad", np.pi / 648000.0 * 1e6),
    "deg": ("urad", np.pi / 180.0 * 1e6),
}


def evaluation_factor(y1, U1, y2, U2=0.0):
    """E_n = |y1 - y2| / sqrt(U1^2 + U2^2) (paper 002 eq. 25), elementwise; U1, U2 are
    expanded uncertainties (k = 2) in the unit of y.  Both U zero: inf for different
    values, NaN for equal ones."""
    y1, U1, y2, U2 = (np.asarray(v, float) for v in (y1, U1, y2, U2))
    if np.any(U1 < 0) or np.any(U2 < 0):
        raise ValueError("expanded uncertainties must be >= 0")
    den = np.sqrt(U1**2 + U2**2)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.abs(y1 - y2) / den
    return out if out.ndim else float(out)


def _to_report_units(
    values: pd.Series, units: pd.Series, what: str
) -> tuple[np.ndarray, list[str]]:
    out, kinds = [], []
    for v, u in zip(values, units):
        if u not in UNIT_FACTORS:
            raise InputError(
                f"unknown unit {u!r} in {what}; expected one of {sorted(UNIT_FACTORS)}",
                column="unit",
            )
        kind, f = UNIT_FACTORS[u]
        out.append(float(v) * f)
        kinds.append(kind)
    return np.array(out), kinds


def compare_with_reference(
    result: pd.DataFrame,
    reference: pd.DataFrame | str,
    *,
    name: str = "name",
    value: str = "value",
    U: str = "U",
    unit: str = "unit",
) -> pd.DataFrame:
    """E_n of every quantity present in both tables.

    result, reference: tables with columns ``name, value, unit, U`` (U the expanded
    uncertainty, k = 2, in ``unit``; a reference without a U column has U = 0); the
    reference may be a CSV path.  Units may differ (um / mm / nm, urad / mrad / rad /
    arcsec / deg); values are compared in um and urad.  Returns ``name, unit, value,
    U, reference, U_reference, difference, E_n, agrees`` (E_n <= 1), in the
    reference's row order; reference names missing from the result raise InputError."""
    if isinstance(reference, (str,)) or hasattr(reference, "__fspath__"):
        reference = pd.read_csv(reference)
    for tab, what in ((result, "result"), (reference, "reference")):
        for c in (name, value, unit):
            if c not in tab:
                raise InputError(f"the {what} table has no column {c!r}", column=c)
    if U not in result:
        raise InputError(f"the result table has no column {U!r} (expanded uncertainty)", column=U)
    ref = reference.copy()
    if U not in ref:
        ref[U] = 0.0
    res = result.set_index(result[name].astype(str))
    missing = [n for n in ref[name].astype(str) if n not in res.index]
    if missing:
        raise InputError(f"reference quantities not in the result: {missing[:8]}", column=name)
    sub = res.loc[ref[name].astype(str)]
    y1, k1 = _to_report_units(sub[value], sub[unit], "the result")
    U1, _ = _to_report_units(sub[U], sub[unit], "the result")
    y2, k2 = _to_report_units(ref[value], ref[unit], "the reference")
    U2, _ = _to_report_units(ref[U], ref[unit], "the reference")
    bad = [n for n, a, b in zip(ref[name], k1, k2) if a != b]
    if bad:
        raise InputError(f"length compared with angle for {bad[:5]}", column=unit)
    en = evaluation_factor(y1, U1, y2, U2)
    return pd.DataFrame(
        {
            "name": ref[name].astype(str).to_numpy(),
            "unit": k2,
            "value": y1,
            "U": U1,
            "reference": y2,
            "U_reference": U2,
            "difference": y1 - y2,
            "E_n": en,
            "agrees": en <= 1.0,
        }
    )
