"""Units: one place for the factors between internal and reported units.

Inside the code lengths are in mm and angles in rad (DESIGN.md). Reports, tables and the
solver's scaled variables use um and urad: a unit step of a scaled variable is a typical
uncertainty of the quantity, and a reported value reads in the units metrologists use.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

#: internal unit -> (factor to the reported unit, reported unit)
REPORT: dict[str, tuple[float, str]] = {"mm": (1e3, "um"), "rad": (1e6, "urad")}


def report_factor(unit: str) -> float:
    """Factor from an internal unit (``mm`` or ``rad``) to its reported unit (um, urad)."""
    try:
        return REPORT[unit][0]
    except KeyError:
        raise ValueError(
            f"unknown internal unit {unit!r}; expected one of {list(REPORT)}"
        ) from None


def report_unit(unit: str) -> str:
    """The reported unit (``um`` or ``urad``) of an internal unit (``mm`` or ``rad``)."""
    return REPORT[unit][1]


def report_factors(units: Iterable[str]) -> np.ndarray:
    """Factors to the reported units, one per internal unit."""
    return np.array([report_factor(u) for u in units], float)


def solver_scale(units: Iterable[str]) -> np.ndarray:
    """Physical size (mm, rad) of one scaled solver unit per variable: 1 um or 1 urad."""
    return 1.0 / report_factors(units)
