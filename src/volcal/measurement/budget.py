"""Uncertainty budgets as data: sources, their distributions, sampling, TOML files.

A :class:`Budget` is a named list of :class:`Source` objects and an optional
:class:`DriftModel`.  Each source has a magnitude in a stated unit, a distribution and a
target:

* ``distribution = "normal"``: the magnitude is an *expanded* uncertainty ``U`` with
  coverage factor ``k`` (required); standard uncertainty ``u = U / k``.
* ``distribution = "rectangular"``: the magnitude is the *half-width* ``a`` of a uniform
  distribution on ``[-a, a]``; standard uncertainty ``u = a / sqrt(3)``.
* ``applies_to = "length"``: an error of every length reading, sampled independently per
  reading.  A length source may grow with the measured length: the magnitude is
  ``magnitude + per_metre * |L| / 1000`` (``L`` in mm, ``per_metre`` in the source's unit
  per metre of length).  Units: ``mm``, ``um`` (or ``µm``), ``nm``.
* ``applies_to = "axis:<NAME>"``: positioning repeatability of one machine axis, one draw
  per positioning of the machine (one visit of a commanded pose).  Units: ``mm, um, nm``
  for a linear axis, ``rad, mrad, urad, deg, arcsec`` for a rotary axis.  At most one
  source per axis; axes without a source have no positioning scatter, and ``volcal
  simulate``, ``identify`` and ``mc`` warn once naming them
  (:meth:`Budget.warn_uncovered`: the bundled ``paper002`` covers X, Y and Z only).
* ``applies_to = "drift"``: a linear drift of the length readings over time, the magnitude
  being a drift *rate* (units ``mm/s, um/s, nm/s, um/min, um/h``); each realisation draws
  one rate and applies ``rate * (t - t_first)``.

Inside the code every value is in mm, rad, s and mm/s (rotary axis repeatabilities are
returned and sampled in rad, never deg).

Combined standard uncertainty of a length reading (paper 002, eq. (22)): the length-type
sources are combined in quadrature, ``u_L = sqrt(sum_i u_i(L)^2)``.

The bundled default ``paper002`` is Table 1 of paper 002 (Liu, Xia, Rui, Metrol. Meas.
Syst. 30 (2023) 49-63).  The text extraction of that table garbles the units ("HM",
"NM", "FM", "pm"); they are read here as micrometres (the same extraction writes um as "pm"
elsewhere: a machine tool's maximum volumetric error of "84.1 pm" and an expanded
uncertainty of "5.8 pm (k = 2)" can only be micrometres):

* laser tracker length measurement error ``0.2 + 0.3 L/1000`` um, Gaussian, k = 2;
* resolution 0.5 um, stability of the fixed reference sphere 0.1 um, optical form
  deviation of the reflector 0.03 um, all rectangular (the tabulated value taken as the
  half-width a);
* positioning repeatability of the axes X 0.8 um, Y 0.6 um, Z 0.3 um, rectangular (the
  tabulated value taken as the half-width a).

Paper 001 (Aguado et al., IOP MSE 1193 (2021) 012061, eq. (2)) models drift and vibration
of its telescopic instrument as a sum of eight sinusoids ``f(t) = sum_i A_i sin(w_i t +
phi_i)`` with amplitudes 1.77e-6 ... 8.939e-6.  The paper states no unit for f(t); the
amplitudes are read here in **metres** (so 1.8 ... 8.9 um), consistent with its reported
multilateration errors of about 6 um on average and below 25 um at most; ``t`` is read
in seconds and ``w_i`` in rad/s (6.283 rad/s = 1 Hz).  It is available as
:data:`PAPER001_DRIFT` and in budget files as ``[drift] preset = "paper001"``; it is not
part of the ``paper002`` default.  By default each realisation draws new uniform phases
(a stationary process with the paper's spectrum, standard deviation
``sqrt(sum A_i^2 / 2)``); ``random_phase = false`` evaluates the paper's fixed phases.

Randomness always comes from a caller-supplied :class:`numpy.random.Generator` (or an
integer seed); the functions never use global random state.

The budget file format is described in docs/budget.md.
"""

from __future__ import annotations

import math
import re
import tomllib
import warnings
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Literal

import numpy as np

from volcal.base.exceptions import InputError

__all__ = [
    "BudgetWarning",
    "Source",
    "DriftModel",
    "Budget",
    "PAPER001_DRIFT",
    "LENGTH_UNITS",
    "ANGLE_UNITS",
    "RATE_UNITS",
    "load_budget",
    "budget_from_dict",
    "bundled_budgets",
    "default_budget",
]

#: factor from the unit to mm
LENGTH_UNITS = {"mm": 1.0, "um": 1e-3, "µm": 1e-3, "nm": 1e-6}
#: factor from the unit to rad
ANGLE_UNITS = {
    "rad": 1.0,
    "mrad": 1e-3,
    "urad": 1e-6,
    "µrad": 1e-6,
    "deg": math.pi / 180.0,
    "arcsec": math.pi / 648000.0,
}
#: factor from the unit to mm/s
RATE_UNITS = {
    "mm/s": 1.0,
    "um/s": 1e-3,
    "µm/s": 1e-3,
    "nm/s": 1e-6,
    "um/min": 1e-3 / 60.0,
    "um/h": 1e-3 / 3600.0,
}

_DISTRIBUTIONS = ("normal", "rectangular")


class BudgetWarning(UserWarning):
    """The budget does not cover the model: axes without a positioning repeatability."""


_AXIS_RE = re.compile(r"^axis:([A-Z][A-Z0-9]{0,3})$")
_SQRT3 = math.sqrt(3.0)


def _rng(rng: np.random.Generator | int) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, bool):
        return np.random.default_rng(int(rng))
    raise TypeError(
        f"expected a numpy.random.Generator or an integer seed, got {type(rng).__name__}"
    )


def _number(value: Any, where: str, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(
            f"expected a number, got {type(value).__name__} {value!r}", source=where, column=key
        )
    v = float(value)
    if not math.isfinite(v):
        raise InputError(f"expected a finite number, got {value!r}", source=where, column=key)
    return v


def _text(value: Any, where: str, key: str, *, empty_ok: bool = False) -> str:
    if not isinstance(value, str) or (not empty_ok and not value.strip()):
        raise InputError(f"expected a non-empty string, got {value!r}", source=where, column=key)
    return value


# --------------------------------------------------------------------------------------
# sources


@dataclass(frozen=True)
class Source:
    """One uncertainty source.

    name: unique name within its budget.
    magnitude: expanded uncertainty U (normal) or half-width a (rectangular), in ``unit``;
        for length sources the constant part of ``magnitude + per_metre * |L| / 1000``.
    unit: see the module docstring (length, angle or rate units by ``applies_to``).
    distribution: ``"normal"`` or ``"rectangular"``.
    applies_to: ``"length"``, ``"axis:<NAME>"`` or ``"drift"``.
    k: coverage factor of a normal source (required for it, not allowed otherwise).
    per_metre: length-proportional part, in ``unit`` per metre of measured length
        (length sources only).
    note: free text (where the value comes from).
    """

    name: str
    magnitude: float
    unit: str
    distribution: Literal["normal", "rectangular"]
    applies_to: str
    k: float | None = None
    per_metre: float = 0.0
    note: str = ""

    def __post_init__(self) -> None:
        _check_source(self, f"source '{self.name}'")

    @property
    def target(self) -> str:
        """``"length"``, ``"axis"`` or ``"drift"``."""
        return "axis" if self.applies_to.startswith("axis:") else self.applies_to

    @property
    def axis(self) -> str | None:
        """The axis name of an ``axis:<NAME>`` source, else None."""
        return self.applies_to[5:] if self.target == "axis" else None

    @property
    def internal_unit(self) -> str:
        """``mm``, ``rad`` or ``mm/s``."""
        if self.unit in LENGTH_UNITS:
            return "mm"
        return "rad" if self.unit in ANGLE_UNITS else "mm/s"

    @property
    def scale(self) -> float:
        """Factor from ``unit`` to the internal unit (mm, rad or mm/s)."""
        return {**LENGTH_UNITS, **ANGLE_UNITS, **RATE_UNITS}[self.unit]

    def _magnitude(self, L_mm: np.ndarray | float | None) -> np.ndarray | float:
        if L_mm is None or self.per_metre == 0.0:
            m = self.magnitude
            return m if L_mm is None else np.full(np.shape(L_mm), m, dtype=float)
        return self.magnitude + self.per_metre * np.abs(np.asarray(L_mm, dtype=float)) / 1000.0

    def half_width(self, L_mm: np.ndarray | float | None = None) -> np.ndarray | float:
        """Half-width a of a rectangular source, internal units."""
        if self.distribution != "rectangular":
            raise ValueError(f"source '{self.name}' is {self.distribution}, not rectangular")
        return self._magnitude(L_mm) * self.scale

    def standard_uncertainty(self, L_mm: np.ndarray | float | None = None) -> np.ndarray | float:
        """Standard uncertainty u in internal units (mm, rad or mm/s); U/k or a/sqrt(3).

        ``L_mm`` (measured length, mm) matters for length sources with ``per_metre``.
        """
        # a normal source always has its coverage factor (checked when it is built)
        div = float(self.k or 1.0) if self.distribution == "normal" else _SQRT3
        return self._magnitude(L_mm) * self.scale / div

    def sample(
        self,
        size: int | tuple[int, ...],
        rng: np.random.Generator | int,
        L_mm: np.ndarray | None = None,
    ) -> np.ndarray:
        """Independent draws, internal units; with ``L_mm`` its shape is the shape of L."""
        g = _rng(rng)
        if L_mm is not None:
            size = np.shape(L_mm)
        if self.distribution == "normal":
            return g.normal(0.0, 1.0, size) * self.standard_uncertainty(L_mm)
        return g.uniform(-1.0, 1.0, size) * (self._magnitude(L_mm) * self.scale)


def _check_source(s: Any, where: str) -> None:
    """Validate the fields of a Source (or of a namespace holding them)."""
    _text(s.name, where, "name")
    if s.distribution not in _DISTRIBUTIONS:
        raise InputError(
            f'expected "normal" or "rectangular", got {s.distribution!r}',
            source=where,
            column="distribution",
        )
    if not isinstance(s.applies_to, str) or not (
        s.applies_to in ("length", "drift") or _AXIS_RE.match(s.applies_to)
    ):
        raise InputError(
            'expected "length", "drift" or "axis:<NAME>" (an axis name of '
            f'1-4 upper-case letters/digits, e.g. "axis:X"), got {s.applies_to!r}',
            source=where,
            column="applies_to",
        )
    mag = _number(s.magnitude, where, "magnitude")
    if mag < 0:
        raise InputError(
            f"expected a magnitude >= 0, got {mag:g}", source=where, column="magnitude"
        )
    target = "axis" if s.applies_to.startswith("axis:") else s.applies_to
    if target == "length":
        units, what = LENGTH_UNITS, "a length unit"
    elif target == "drift":
        units, what = RATE_UNITS, "a drift-rate unit"
    else:
        units, what = (
            {**LENGTH_UNITS, **ANGLE_UNITS},
            "a length unit (linear axis) or an angle unit (rotary axis)",
        )
    if s.unit not in units:
        raise InputError(
            f"expected {what}, one of {list(units)}, got {s.unit!r}", source=where, column="unit"
        )
    if s.distribution == "normal":
        if s.k is None:
            raise InputError(
                "a normal source needs its coverage factor k (the magnitude is the "
                "expanded uncertainty U = k u)",
                source=where,
                column="k",
            )
        k = _number(s.k, where, "k")
        if k <= 0:
            raise InputError(f"expected k > 0, got {k:g}", source=where, column="k")
    elif s.k is not None:
        raise InputError(
            "k applies to normal sources only (a rectangular magnitude is the half-width a)",
            source=where,
            column="k",
        )
    pm = _number(s.per_metre, where, "per_metre")
    if pm < 0:
        raise InputError(f"expected per_metre >= 0, got {pm:g}", source=where, column="per_metre")
    if pm != 0 and target != "length":
        raise InputError(
            "per_metre applies to length sources only", source=where, column="per_metre"
        )
    if not isinstance(s.note, str):
        raise InputError(f"expected a string, got {s.note!r}", source=where, column="note")


# --------------------------------------------------------------------------------------
# drift


@dataclass(frozen=True)
class DriftModel:
    """Drift/vibration of the length readings as a sum of sinusoids (paper 001, eq. (2)).

    ``f(t) = sum_i amplitude_mm[i] * sin(omega_rad_s[i] * t + phase_rad[i])``, t in s,
    result in mm, added to the length reading.  With ``random_phase`` each realisation
    (:meth:`sample`) draws new phases uniformly in [0, 2 pi).
    """

    amplitude_mm: tuple[float, ...]
    omega_rad_s: tuple[float, ...]
    phase_rad: tuple[float, ...]
    random_phase: bool = True
    name: str = "drift"
    note: str = ""

    def __post_init__(self) -> None:
        n = len(self.amplitude_mm)
        if n == 0 or len(self.omega_rad_s) != n or len(self.phase_rad) != n:
            raise ValueError(
                "a drift model needs equally many amplitudes, frequencies and phases (at least one)"
            )

    @property
    def sigma_mm(self) -> float:
        """Standard deviation of f at a random time / random phases: sqrt(sum A^2 / 2)."""
        return float(math.sqrt(sum(a * a for a in self.amplitude_mm) / 2.0))

    def evaluate(self, t_s: np.ndarray, phase_rad: np.ndarray | None = None) -> np.ndarray:
        """f(t) in mm for times t in s (fixed phases unless ``phase_rad`` is given)."""
        t = np.asarray(t_s, dtype=float)
        ph = np.asarray(self.phase_rad if phase_rad is None else phase_rad, dtype=float)
        A = np.asarray(self.amplitude_mm, dtype=float)
        w = np.asarray(self.omega_rad_s, dtype=float)
        return np.sin(t[..., None] * w + ph) @ A

    def sample(self, t_s: np.ndarray, rng: np.random.Generator | int) -> np.ndarray:
        """One realisation over the times t (s), mm."""
        if not self.random_phase:
            return self.evaluate(t_s)
        ph = _rng(rng).uniform(0.0, 2.0 * math.pi, len(self.amplitude_mm))
        return self.evaluate(t_s, ph)


#: Paper 001, eq. (2), amplitudes read in metres (converted to mm), t in s, omega in rad/s.
PAPER001_DRIFT = DriftModel(
    amplitude_mm=tuple(
        a * 1e3
        for a in (6.058e-6, 1.833e-6, 8.939e-6, 2.593e-6, 1.833e-6, 2.133e-6, 1.870e-6, 1.77e-6)
    ),
    omega_rad_s=(6.283, 1263.0, 1257.0, 62.83, 1250.0, 75.4, 18.85, 31.42),
    phase_rad=(-1.362, 1.377, 0.3743, -2.088, 2.565, 2.734, 2.042, 3.104),
    random_phase=True,
    name="paper001",
    note="Aguado et al. 2021, eq. (2): drift and vibration of a telescopic laser instrument; "
    "amplitudes read in metres",
)

_DRIFT_PRESETS = {"paper001": PAPER001_DRIFT}


# --------------------------------------------------------------------------------------
# budget


@dataclass(frozen=True)
class Budget:
    """A named uncertainty budget: sources and an optional drift model.

    origin: the file it was read from ("" when built in Python).
    """

    name: str
    sources: tuple[Source, ...]
    drift: DriftModel | None = None
    description: str = ""
    reference: str = ""
    origin: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        where = self.origin or f"budget '{self.name}'"
        object.__setattr__(self, "sources", tuple(self.sources))
        names = [s.name for s in self.sources]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise InputError(f"duplicate source name(s) {dup}", source=where, column="source.name")
        axes = [s.axis for s in self.sources if s.axis is not None]
        dup = sorted({a for a in axes if axes.count(a) > 1})
        if dup:
            raise InputError(
                f"more than one source for axis {dup}; give one positioning repeatability per axis",
                source=where,
                column="source.applies_to",
            )

    # -- selections

    @property
    def length_sources(self) -> tuple[Source, ...]:
        return tuple(s for s in self.sources if s.target == "length")

    @property
    def axis_sources(self) -> dict[str, Source]:
        return {s.axis: s for s in self.sources if s.axis is not None}  # type: ignore[misc]

    @property
    def drift_sources(self) -> tuple[Source, ...]:
        return tuple(s for s in self.sources if s.target == "drift")

    def with_drift(self, drift: DriftModel | None) -> Budget:
        """A copy with another drift model (e.g. :data:`PAPER001_DRIFT`), or none."""
        return replace(self, drift=drift)

    # -- lengths

    def length_sigma(self, L_mm: np.ndarray) -> np.ndarray:
        """Standard uncertainty (mm) of each length reading L (mm): the length sources in
        quadrature (paper 002, eq. (22)).  Drift is not included (see :meth:`sample_drift`)."""
        L = np.asarray(L_mm, dtype=float)
        var = np.zeros(L.shape)
        for s in self.length_sources:
            var = var + np.asarray(s.standard_uncertainty(L)) ** 2
        return np.sqrt(var)

    def sample_length_errors(self, L_mm: np.ndarray, rng: np.random.Generator | int) -> np.ndarray:
        """One error draw (mm) per length reading L (mm): the sum of independent draws of
        every length source, each reading independent of the others."""
        g = _rng(rng)
        L = np.asarray(L_mm, dtype=float)
        out = np.zeros(L.shape)
        for s in self.length_sources:
            out += s.sample(L.shape, g, L)
        return out

    # -- axes

    def axis_repeatability(self, axis_name: str) -> tuple[str, float]:
        """``(distribution, value)`` of an axis' positioning repeatability: for
        ``"rectangular"`` the half-width a, for ``"normal"`` the standard uncertainty
        U/k; in mm (linear) or rad (rotary).  ``("none", 0.0)`` when the budget has no
        source for the axis."""
        s = self.axis_sources.get(axis_name)
        if s is None:
            return ("none", 0.0)
        if s.distribution == "rectangular":
            return ("rectangular", float(s.half_width()))
        return ("normal", float(s.standard_uncertainty()))

    def axis_sigma(self, axis_name: str) -> float:
        """Standard uncertainty of an axis' positioning, mm or rad (0 without a source)."""
        s = self.axis_sources.get(axis_name)
        return 0.0 if s is None else float(s.standard_uncertainty())

    def sample_axis_errors(
        self, axis_names: list[str] | tuple[str, ...], n: int, rng: np.random.Generator | int
    ) -> np.ndarray:
        """Positioning errors, shape (n, len(axis_names)): one row per positioning of the
        machine (one visit of a commanded pose), columns in ``axis_names`` order, mm for
        axes with a length unit, rad for axes with an angle unit, 0 for axes without a
        source."""
        g = _rng(rng)
        out = np.zeros((int(n), len(axis_names)))
        srcs = self.axis_sources
        for j, a in enumerate(axis_names):
            if a in srcs:
                out[:, j] = srcs[a].sample(int(n), g)
        return out

    def check_axes(self, spec: Any) -> None:
        """Check the axis sources against a :class:`volcal.model.spec.MachineSpec`: every axis
        source must name an axis of the model, with a length unit for a linear axis and an
        angle unit for a rotary one.  Raises :class:`InputError`."""
        where = self.origin or f"budget '{self.name}'"
        names = list(spec.axis_names)
        for a, s in self.axis_sources.items():
            if a not in names:
                raise InputError(
                    f"source '{s.name}' applies to axis {a}, which the model "
                    f"'{spec.name}' does not have (axes: {', '.join(names)})",
                    source=where,
                    column="applies_to",
                )
            rotary = spec.axis(a).is_rotary
            if rotary and s.unit not in ANGLE_UNITS:
                raise InputError(
                    f"source '{s.name}': axis {a} is rotary; expected an angle "
                    f"unit {list(ANGLE_UNITS)}, got {s.unit!r}",
                    source=where,
                    column="unit",
                )
            if not rotary and s.unit not in LENGTH_UNITS:
                raise InputError(
                    f"source '{s.name}': axis {a} is linear; expected a length "
                    f"unit {list(LENGTH_UNITS)}, got {s.unit!r}",
                    source=where,
                    column="unit",
                )

    def axes_without_term(self, spec: Any) -> list[str]:
        """The axes of a :class:`volcal.model.spec.MachineSpec` the budget gives no
        positioning repeatability (their positioning scatter is then taken as zero)."""
        srcs = self.axis_sources
        return [a for a in spec.axis_names if a not in srcs]

    def coverage_message(self, spec: Any) -> str | None:
        """A sentence naming the model's axes without a repeatability term, or None when
        the budget covers every axis."""
        missing = self.axes_without_term(spec)
        if not missing:
            return None
        rotary = [a for a in missing if spec.axis(a).is_rotary]
        kinds = (
            "rotary"
            if len(rotary) == len(missing)
            else "linear"
            if not rotary
            else f"rotary: {', '.join(rotary)}"
        )
        unit = (
            "an angle unit such as arcsec"
            if len(rotary) == len(missing)
            else "a length unit such as um"
            if not rotary
            else "um for a linear axis, arcsec for a rotary one"
        )
        return (
            f"the uncertainty budget '{self.name}' has no positioning repeatability for "
            f"{'axes' if len(missing) > 1 else 'axis'} {', '.join(missing)} ({kinds}) of "
            f"model '{spec.name}': their positioning "
            "scatter is taken as zero, so the readings' uncertainties leave it out; give a "
            f'source per axis in a budget file (applies_to = "axis:{missing[0]}", {unit}, '
            "and where the value comes from in its note; docs/budget.md) and pass it "
            "with --budget"
        )

    def warn_uncovered(self, spec: Any) -> str | None:
        """Warn (:class:`BudgetWarning`) when the budget leaves axes of the model without a
        repeatability term; returns the message (None when every axis is covered).

        The warning is issued from this one place, so Python's default filter shows it
        once per run however many steps (simulate, identify, each Monte Carlo trial) use
        the same budget on the same model."""
        msg = self.coverage_message(spec)
        if msg is not None:
            warnings.warn(msg, BudgetWarning, stacklevel=1)
        return msg

    # -- drift

    def sample_drift(self, t_s: np.ndarray, rng: np.random.Generator | int) -> np.ndarray:
        """One realisation of the time-dependent length error (mm) at times t (s): the
        drift model (if any) plus, for each drift source, one drawn rate times
        ``t - min(t)``.  Call it once per span over which the drift is continuous (e.g.
        once per station visit when the instrument is re-referenced at each station).
        Zeros when the budget has neither."""
        g = _rng(rng)
        t = np.asarray(t_s, dtype=float)
        if t.size and not np.all(np.isfinite(t)):
            raise ValueError("sample_drift needs finite time stamps (s) for every reading")
        out = np.zeros(t.shape)
        if self.drift is not None:
            out += self.drift.sample(t, g)
        if t.size:
            t0 = float(t.min())
            for s in self.drift_sources:
                out += float(s.sample(1, g)[0]) * (t - t0)
        return out

    # -- reporting

    def to_frame(self, L_mm: float = 1000.0):
        """The sources as a pandas DataFrame with their standard uncertainty in internal
        units (length sources evaluated at ``L_mm``)."""
        import pandas as pd

        rows = []
        for s in self.sources:
            u = s.standard_uncertainty(L_mm if s.target == "length" else None)
            rows.append(
                {
                    "name": s.name,
                    "applies_to": s.applies_to,
                    "distribution": s.distribution,
                    "magnitude": s.magnitude,
                    "per_metre": s.per_metre,
                    "unit": s.unit,
                    "k": s.k,
                    "standard_uncertainty": float(u),
                    "internal_unit": s.internal_unit,
                }
            )
        return pd.DataFrame(rows)


# --------------------------------------------------------------------------------------
# files

_TOP_KEYS = {"name", "description", "reference", "source", "drift"}
_SOURCE_KEYS = {"name", "applies_to", "distribution", "magnitude", "unit", "k", "per_metre", "note"}
_DRIFT_KEYS = {"preset", "unit", "terms", "random_phase", "note"}
_TERM_KEYS = {"amplitude", "omega_rad_s", "phase_rad"}


def _unknown(d: dict, allowed: set[str], where: str, what: str) -> None:
    bad = sorted(set(d) - allowed)
    if bad:
        import difflib

        hints = [
            f"'{b}' (did you mean '{m[0]}'?)"
            if (m := difflib.get_close_matches(b, sorted(allowed), n=1))
            else f"'{b}'"
            for b in bad
        ]
        raise InputError(
            f"unknown {what} key(s) {', '.join(hints)}; allowed: {sorted(allowed)}",
            source=where,
            column=bad[0],
        )


def _drift_from_dict(d: Any, where: str) -> DriftModel:
    if not isinstance(d, dict):
        raise InputError("expected a [drift] table", source=where, column="drift")
    _unknown(d, _DRIFT_KEYS, where, "[drift]")
    random_phase = d.get("random_phase", True)
    if not isinstance(random_phase, bool):
        raise InputError(
            f"expected true or false, got {random_phase!r}",
            source=where,
            column="drift.random_phase",
        )
    note = _text(d.get("note", ""), where, "drift.note", empty_ok=True)
    if "preset" in d:
        if "terms" in d or "unit" in d:
            raise InputError(
                "give either preset or unit + terms, not both", source=where, column="drift.preset"
            )
        p = d["preset"]
        if p not in _DRIFT_PRESETS:
            raise InputError(
                f"unknown drift preset {p!r}; presets: {sorted(_DRIFT_PRESETS)}",
                source=where,
                column="drift.preset",
            )
        return replace(
            _DRIFT_PRESETS[p], random_phase=random_phase, note=note or _DRIFT_PRESETS[p].note
        )
    if "terms" not in d:
        raise InputError(
            'expected preset = "paper001" or unit + terms', source=where, column="drift.terms"
        )
    unit = d.get("unit")
    if unit not in LENGTH_UNITS:
        raise InputError(
            f"expected the amplitude unit, one of {list(LENGTH_UNITS)}, got {unit!r}",
            source=where,
            column="drift.unit",
        )
    terms = d["terms"]
    if not isinstance(terms, list) or not terms:
        raise InputError(
            "expected a non-empty array of {amplitude, omega_rad_s, phase_rad} tables",
            source=where,
            column="drift.terms",
        )
    A, w, ph = [], [], []
    for i, t in enumerate(terms):
        key = f"drift.terms[{i + 1}]"
        if not isinstance(t, dict):
            raise InputError(
                "expected a table {amplitude = ..., omega_rad_s = ..., phase_rad = ...}",
                source=where,
                column=key,
            )
        _unknown(t, _TERM_KEYS, where, key)
        for k in ("amplitude", "omega_rad_s"):
            if k not in t:
                raise InputError("missing required key", source=where, column=f"{key}.{k}")
        a = _number(t["amplitude"], where, f"{key}.amplitude")
        if a < 0:
            raise InputError(
                f"expected an amplitude >= 0, got {a:g}", source=where, column=f"{key}.amplitude"
            )
        A.append(a * LENGTH_UNITS[unit])
        w.append(_number(t["omega_rad_s"], where, f"{key}.omega_rad_s"))
        ph.append(_number(t.get("phase_rad", 0.0), where, f"{key}.phase_rad"))
    return DriftModel(tuple(A), tuple(w), tuple(ph), random_phase, "drift", note)


def budget_from_dict(doc: dict[str, Any], where: str = "<budget>") -> Budget:
    """Validate a parsed budget document (see docs/budget.md) and build the Budget."""
    if not isinstance(doc, dict):
        raise InputError("expected a table", source=where)
    _unknown(doc, _TOP_KEYS, where, "top-level")
    if "name" not in doc:
        raise InputError("missing required key", source=where, column="name")
    name = _text(doc["name"], where, "name")
    desc = _text(doc.get("description", ""), where, "description", empty_ok=True)
    ref = _text(doc.get("reference", ""), where, "reference", empty_ok=True)
    raw = doc.get("source")
    if not isinstance(raw, list) or not raw:
        raise InputError("expected one or more [[source]] tables", source=where, column="source")
    sources = []
    for i, d in enumerate(raw):
        w = f"{where} [[source]] #{i + 1}"
        if not isinstance(d, dict):
            raise InputError("expected a table", source=w)
        if isinstance(d.get("name"), str):
            w += f" ({d['name']})"
        _unknown(d, _SOURCE_KEYS, w, "[[source]]")
        for key in ("name", "applies_to", "distribution", "magnitude", "unit"):
            if key not in d:
                raise InputError("missing required key", source=w, column=key)
        fields = {k: d[k] for k in _SOURCE_KEYS if k in d}
        # validate with the file location before constructing (same checks as Source)
        _check_source(SimpleNamespace(**{"k": None, "per_metre": 0.0, "note": "", **fields}), w)
        fields["magnitude"] = float(fields["magnitude"])
        if "k" in fields:
            fields["k"] = float(fields["k"])
        if "per_metre" in fields:
            fields["per_metre"] = float(fields["per_metre"])
        sources.append(Source(**fields))
    drift = _drift_from_dict(doc["drift"], where) if "drift" in doc else None
    return Budget(name, tuple(sources), drift, desc, ref, origin=where)


def bundled_budgets() -> dict[str, Path]:
    """Names and paths of the budgets shipped with volcal (``volcal/data/budget_*.toml``)."""
    root = resources.files("volcal").joinpath("data")
    out = {}
    for p in sorted(root.iterdir(), key=lambda p: p.name):
        if p.name.startswith("budget_") and p.name.endswith(".toml"):
            out[p.name[len("budget_") : -len(".toml")]] = Path(str(p))
    return out


def load_budget(path_or_name: str | Path | Budget = "paper002") -> Budget:
    """A bundled budget by name (see :func:`bundled_budgets`), a budget TOML file, or a
    Budget (returned as is).  The file is parsed with :mod:`tomllib`, never executed."""
    if isinstance(path_or_name, Budget):
        return path_or_name
    bundled = bundled_budgets()
    if isinstance(path_or_name, str) and path_or_name in bundled:
        path = bundled[path_or_name]
    else:
        path = Path(path_or_name)
        if not path.is_file():
            raise InputError(
                f"no bundled budget named {str(path_or_name)!r} and no such file; "
                f"bundled budgets: {sorted(bundled)}",
                source=str(path_or_name),
            )
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read budget file: {exc}", source=str(path)) from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML: {exc}", source=str(path)) from None
    return budget_from_dict(doc, str(path))


def default_budget() -> Budget:
    """The bundled ``paper002`` budget (paper 002, Table 1)."""
    return load_budget("paper002")
