"""``evaluate``: readings -> ISO 230-2 parameters and paper 003's model, per axis."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from volcal.base.exceptions import InputError
from volcal.measurement.iso230_2_files import LINEAR, AxisReadings, load_readings

from .model import TYPE_A_METHODS, PolynomialModel, fit_axis_model
from .parameters import IsoParameters, iso230_2_parameters

__all__ = ["AxisResult", "Iso230Result", "evaluate", "mpe_to_standard_uncertainty"]


def mpe_to_standard_uncertainty(mpe: float) -> float:
    """Standard uncertainty of an error known only to lie within ±MPE: rectangular
    distribution, u = MPE / sqrt(3)."""
    return float(mpe) / math.sqrt(3.0)


@dataclass(frozen=True)
class AxisResult:
    readings: AxisReadings
    iso: IsoParameters
    model: PolynomialModel

    @property
    def axis(self) -> str:
        return self.readings.axis

    @property
    def units(self):
        return self.readings.units


@dataclass(frozen=True)
class Iso230Result:
    """Result of :func:`evaluate`: one :class:`AxisResult` per axis, in file order.

    ``settings`` records the options (report units: um / arcsec / ppm); ``warnings`` lists
    deviations from the standard's test conditions and poor fits.
    """

    source: str
    axes: tuple[AxisResult, ...]
    settings: dict = field(default_factory=dict)
    warnings: tuple[str, ...] = ()

    def __getitem__(self, axis: str) -> AxisResult:
        for a in self.axes:
            if a.axis == axis:
                return a
        raise KeyError(axis)

    # tables (see tables.py)
    def parameters_table(self):
        from .tables import parameters_table

        return parameters_table(self)

    def targets_table(self):
        from .tables import targets_table

        return targets_table(self)

    def polynomial_table(self):
        from .tables import polynomial_table

        return polynomial_table(self)

    def correction_table(self, spacing_mm: float | None = None, spacing_deg: float | None = None):
        from .tables import correction_table

        return correction_table(self, spacing_mm=spacing_mm, spacing_deg=spacing_deg)


def check_option(name: str, value, *, minimum: float = 0.0, strict: bool = False) -> None:
    """Raise :class:`InputError` (source ``option <name>``) unless ``value`` is a finite
    number >= ``minimum`` (> with ``strict``)."""
    ok = (
        value is not None
        and math.isfinite(value)
        and (value > minimum if strict else value >= minimum)
    )
    if not ok:
        rel = ">" if strict else ">="
        raise InputError(
            f"{value!r} is not allowed; expected a number {rel} {minimum:g}",
            source=f"option {name}",
        )


def check_degree(name: str, degree) -> None:
    """Raise :class:`InputError` (source ``option <name>``) unless ``degree`` is an integer
    >= 0."""
    if int(degree) != degree or degree < 0:
        raise InputError(
            f"{degree!r} is not allowed; expected an integer >= 0", source=f"option {name}"
        )


def check_type_a(type_a: str) -> None:
    """Raise :class:`InputError` (source ``option --type-a``) unless ``type_a`` is one of
    :data:`~volcal.iso230_2.model.TYPE_A_METHODS`."""
    if type_a not in TYPE_A_METHODS:
        raise InputError(
            f"{type_a!r} is not allowed; expected one of {', '.join(TYPE_A_METHODS)}",
            source="option --type-a",
        )


def evaluate(
    data,
    *,
    degree: int = 3,
    mpe_um: float = 0.0,
    mpe_ppm: float = 0.0,
    mpe_arcsec: float = 0.0,
    k: float = 2.0,
    resolution_um: float = 0.0,
    resolution_arcsec: float = 0.0,
    type_a: str = "gum-s1",
    source: str | None = None,
) -> Iso230Result:
    """Evaluate ISO 230-2 positioning readings and fit paper 003's polynomial model.

    Parameters
    ----------
    data : path of a CSV file or a pandas DataFrame (format:
        :mod:`volcal.measurement.iso230_2_files`).
    degree : degree of the polynomial Δ(P) per approach direction (paper: 3).
    mpe_um, mpe_arcsec : maximum permissible error of the measuring instrument, a constant
        error common to all readings (linear axes in um, rotary axes in arcsec); its
        standard uncertainty is MPE / sqrt(3) (rectangular distribution).
    mpe_ppm : length-proportional MPE of the instrument (linear axes, in um per m of travel
        from the smallest target), also rectangular and fully correlated.  Not in the paper.
    k : coverage factor of the expanded uncertainty U = k u.
    resolution_um, resolution_arcsec : reading resolution r; u(x̄_i) is floored at
        r / sqrt(12) so that a target with identical readings still has a weight.
    type_a : standard uncertainty of each mean deviation: "gum-s1" (default,
        sqrt((n-1)/(n-3)) s_i / sqrt(n), JCGM 101 6.4.9; needs n >= 4) or "paper"
        (s_i / sqrt(n), paper 003 eq. 10, which understates the band for small n).
    """
    check_degree("--degree", degree)
    for name, v in (
        ("--mpe-um", mpe_um),
        ("--mpe-ppm", mpe_ppm),
        ("--mpe-arcsec", mpe_arcsec),
        ("--resolution-um", resolution_um),
        ("--resolution-arcsec", resolution_arcsec),
    ):
        check_option(name, v)
    check_option("--k", k, strict=True)
    check_type_a(type_a)
    axes_readings = load_readings(data, source=source)
    src = axes_readings[0].source
    results, warnings = [], []
    for rd in axes_readings:
        units = rd.units
        linear = units is LINEAR
        # instrument and resolution terms, converted to internal units (mm or rad)
        u_instr = (
            mpe_to_standard_uncertainty(mpe_um if linear else mpe_arcsec) / units.deviation_scale
        )
        u_scale = mpe_to_standard_uncertainty(mpe_ppm) * 1e-6 if linear else 0.0
        res = (resolution_um if linear else resolution_arcsec) / units.deviation_scale
        u_floor = res / math.sqrt(12.0)
        iso = iso230_2_parameters(rd.up, rd.down)
        ignored = [
            o
            for o, v in (
                (("--mpe-um", mpe_um), ("--mpe-ppm", mpe_ppm), ("--resolution-um", resolution_um))
                if not linear
                else (("--mpe-arcsec", mpe_arcsec), ("--resolution-arcsec", resolution_arcsec))
            )
            if v
        ]
        if ignored:
            warnings.append(
                f"axis {rd.axis} is {units.kind}: {', '.join(ignored)} do not "
                "apply to it and were ignored"
            )
        if type_a == "gum-s1" and rd.n < 4:
            raise InputError(
                f"axis {rd.axis}: {rd.n} cycles; the GUM-S1 type A uncertainty "
                "of the means needs at least 4 (ISO 230-2 asks for 5); use "
                "--type-a paper (s/sqrt(n)) for fewer",
                source=src,
            )
        if rd.m < degree + 1:
            raise InputError(
                f"axis {rd.axis}: {rd.m} target positions; a polynomial of degree "
                f"{degree} needs at least {degree + 1}; choose --degree "
                f"{rd.m - 1} or lower",
                source=src,
            )
        if rd.n < 5:
            warnings.append(f"axis {rd.axis}: {rd.n} cycles; ISO 230-2 asks for 5")
        if rd.m < 5:
            warnings.append(
                f"axis {rd.axis}: {rd.m} target positions; ISO 230-2 asks for at least 5"
            )
        try:
            model = fit_axis_model(
                rd.targets,
                rd.up,
                rd.down,
                degree=degree,
                u_instrument=u_instr,
                u_scale=u_scale,
                u_floor=u_floor,
                type_a=type_a,
            )
        except ValueError as exc:
            zero = np.flatnonzero((iso.s_up == 0) | (iso.s_down == 0))
            if zero.size and u_floor == 0.0:
                t = rd.targets[zero[0]] * units.position_scale
                opt = "--resolution-um" if linear else "--resolution-arcsec"
                raise InputError(
                    f"axis {rd.axis}: all readings at target {t:.6g} "
                    f"{units.position} are equal in one direction (s_i = 0), so "
                    f"the polynomial fit has no weight for it; give the reading "
                    f"resolution ({opt}) as a floor of the standard uncertainty",
                    source=src,
                ) from None
            raise InputError(f"axis {rd.axis}: {exc}", source=src) from None
        if model.dof > 0:
            from scipy.stats import chi2 as chi2_dist

            for lab, c2 in zip(model.labels, model.chi2):
                p = float(chi2_dist.sf(c2, model.dof))
                if p < 0.01:
                    warnings.append(
                        f"axis {rd.axis}, direction {'+' if lab == 'up' else '-'}: the degree "
                        f"{degree} polynomial does not explain the means within their "
                        f"uncertainty (chi2 = {c2:.3g} with {model.dof} dof, p = {p:.2g}); "
                        "the band understates the uncertainty between targets; try another "
                        "degree"
                    )
        results.append(AxisResult(readings=rd, iso=iso, model=model))
    settings = dict(
        degree=int(degree),
        k=float(k),
        mpe_um=float(mpe_um),
        mpe_ppm=float(mpe_ppm),
        mpe_arcsec=float(mpe_arcsec),
        resolution_um=float(resolution_um),
        resolution_arcsec=float(resolution_arcsec),
        type_a=type_a,
        mpe_to_u="rectangular: u = MPE / sqrt(3)",
    )
    return Iso230Result(
        source=src, axes=tuple(results), settings=settings, warnings=tuple(warnings)
    )
