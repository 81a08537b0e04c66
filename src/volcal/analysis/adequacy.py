"""Model adequacy: does the identified model explain the readings within their uncertainty?

After a weighted least-squares fit the whitened (normalised) residuals ``z = r / sigma``
of a model that is right, with a right uncertainty budget, are independent standard normal
numbers, so ``chi2 = sum z^2`` follows a chi-square distribution with the fit's degrees of
freedom ``dof``.  :func:`assess_residuals` tests ``chi2 / dof`` against its two-sided
99.9 % interval ``[chi2.ppf(0.0005, dof), chi2.ppf(0.9995, dof)] / dof`` and looks for
**residual structure** with nested F-tests, each significant below
:data:`STRUCTURE_P` (``p < 1e-6``):

* against one **axis' position**: the residuals are grouped into cells (station x position
  bin: a misfit of the tool point enters each station's readings through its own beam
  direction, so its sign differs between stations) and the cell means are compared with
  the station means alone;
* against the **tool offset** (cells station x tool offset, data with several offsets;
  an offset is a category, so every offset is its own group however many there are), and
  each offset alone against the others, its p multiplied by the number of offsets
  (Bonferroni): a significant one is named (``AxisStructure.group``);
* against the **station** (station means against the overall mean);
* against the **time** of the reading (cells station x time bin; data with a ``time``
  column).

The verdict has three outcomes (:data:`VERDICTS`, machine-readable in ``Adequacy.verdict``):

``fits``
    chi2/dof inside its interval and no significant structure;
``budget_pessimistic``
    the model fits, but chi2/dof lies *below* its interval with no significant
    structure: the readings scatter less than their budget says, so the reported
    uncertainties are conservative by the factor ``1 / budget_factor``;
``does_not_fit``
    chi2/dof above its interval, or significant structure (whatever chi2/dof is).

The likely causes (``Adequacy.causes``, most likely first; kinds in :data:`CAUSE_KINDS`)
are named in a metrologist's words.  Significant structure always outranks the budget:
then the budget is not named and the scale of the uncertainties is not offered as a
remedy.

* ``strategy``: a strategy with a biased step (``classic``: stations calibrated on nominal
  points and points multilaterated before the fit; ``two-phase``: the stations of the
  first phase held; ``points-only``: stations held where given or at the analytical
  solution from nominal points) leaves structure behind; the joint fit estimates
  everything together;
* ``basis``: structure against an axis: its basis is too poor for its error motions
  (raise the degree, ``--degree auto``, or give the axis another basis; a Fourier series
  on a full-turn axis cannot follow an error that does not return after a turn);
* ``tool_offset``: structure against the tool offset (wrong tool offsets in the data, or
  an angular error the model lacks);
* ``station``: a station's readings are offset (its dead path, a station moved);
* ``drift``: structure against time (thermal drift, a station moved during the run);
* ``outliers`` (blunders, heavy tails): the largest ``|z|``, the number of readings
  beyond 5 robust standard deviations of the bulk (``1.4826 MAD``) and beyond 5 budget
  sigmas, the excess kurtosis and the share of ``chi2`` the outliers carry;
* ``budget`` (only without significant structure): the readings' standard uncertainties
  are too small (or too large) by a factor, reported as the factor the budget's sigmas
  should be multiplied by (``sqrt`` of the variance factor that remains once outliers are
  accounted for).

Data from a single station always draw a warning: lengths from one station cannot
separate the station's position from the machine's errors, so even a passing ``chi2``
says little.

:func:`assess` applies this to an identification result (``IdentificationResult`` or a
result with the same ``residuals`` / ``conditions`` / ``machine`` / ``strategy`` /
``error_model``); :func:`volcal.plots.residuals_vs_axes` draws the normalised residuals
against each axis position with the binned means of :func:`position_bins`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
import pandas as pd

from volcal.base.distributions import chi2_ppf, log_f_sf, norm_cdf, poisson_sf

__all__ = [
    "Adequacy",
    "AxisStructure",
    "Cause",
    "assess",
    "assess_residuals",
    "position_bins",
    "format_p",
    "BIASED_STRATEGIES",
    "CAUSE_KINDS",
    "CONFIDENCE",
    "MAX_BINS",
    "OUTLIER_K",
    "STRUCTURE_P",
    "CAUSE_MIN_SHARE",
    "VERDICTS",
]

#: two-sided probability content of the chi2/dof acceptance interval
CONFIDENCE = 0.999
#: at most this many position bins per axis (axes with more distinct positions are binned
#: at quantiles)
MAX_BINS = 12
#: a reading is an outlier beyond this many robust standard deviations of the bulk
OUTLIER_K = 5.0
#: residual structure (against an axis, a tool offset, a station or time) is significant
#: below this p-value of its F-test
STRUCTURE_P = 1e-6
#: outliers (and a budget beside them) are named when they explain at least this share
#: of the excess chi2
CAUSE_MIN_SHARE = 0.2
#: excess kurtosis above this marks heavy tails (a normal sample of 1000 readings has a
#: standard error of about 0.15)
HEAVY_TAIL_KURTOSIS = 1.0
#: the three outcomes of the test, in ``Adequacy.verdict``
VERDICTS = ("fits", "budget_pessimistic", "does_not_fit")
#: the kinds of a :class:`Cause`
CAUSE_KINDS = ("strategy", "basis", "tool_offset", "station", "drift", "outliers", "budget")
#: strategies with a step that can bias the errors, and why (a metrologist's sentence)
BIASED_STRATEGIES = {
    "classic": (
        "classic calibrates the stations on nominal points and multilaterates every point "
        "before the error model is fitted, so the machine's errors at the calibration "
        "points end up in the station positions and come back as residual structure"
    ),
    "two-phase": (
        "two-phase holds the stations its first phase found on nominal points (the "
        "machine's errors set to zero), so the errors they absorbed are not recovered"
    ),
    "points-only": (
        "points-only holds the stations where the stations table puts them or, without "
        "one, at the analytical solution from nominal points (which absorbs part of the "
        "machine's errors); held stations that are off leave structure behind"
    ),
}
#: the structure kinds of :class:`AxisStructure` and the cause each points to
_CAUSE_OF = {"axis": "basis", "tool_offset": "tool_offset", "station": "station", "time": "drift"}


@dataclass(frozen=True)
class AxisStructure:
    """Residual structure against one grouping of the readings (nested F-test, see the
    module): an axis' position, the tool offset, the station or the time of the reading.

    axis: the axis name, or ``tool offset`` / ``station`` / ``time``; unit (mm / deg / s
    or empty); n_bins: groups (position bins, tool offsets, stations, time bins); f: the F
    statistic with degrees of freedom (df1, df2); p_value: its upper tail probability (0
    when below the smallest float; ``log10_p`` keeps the size); explained_share: share of
    the residual sum of squares explained by the group means beyond what chance explains
    (0..1); kind: ``axis``, ``tool_offset``, ``station`` or ``time``; group: the one
    group whose readings differ from the others' (tool offsets: each offset tested alone
    against the rest, its p multiplied by the number of offsets, Bonferroni), with that
    p, when it is significant; empty otherwise.
    """

    axis: str
    unit: str
    n_bins: int
    f: float
    df1: int
    df2: int
    p_value: float
    log10_p: float
    explained_share: float
    kind: str = "axis"
    group: str = ""

    @property
    def significant(self) -> bool:
        """p below :data:`STRUCTURE_P`."""
        return self.p_value < STRUCTURE_P

    @property
    def label(self) -> str:
        """``axis X``, ``tool offset``, ``station`` or ``time``."""
        return f"axis {self.axis}" if self.kind == "axis" else self.axis


@dataclass(frozen=True)
class Cause:
    """One likely cause of a fit that does not fit (or of a pessimistic budget): kind (one
    of :data:`CAUSE_KINDS`), share of the excess chi2 it explains (0..1; for structure the
    share of the residual sum of squares its group means explain; 1 for a budget that is
    too large), a sentence and its numbers."""

    kind: str
    share: float
    text: str
    numbers: dict[str, Any] = field(default_factory=dict)

    @property
    def short(self) -> str:
        """A few words for a summary line (``basis of axis X``, ``biased strategy
        (classic)``, ...)."""
        nb = self.numbers
        if self.kind == "strategy":
            return f"biased strategy ({nb.get('strategy', '?')})"
        if self.kind == "basis":
            return f"basis too poor for axis {nb.get('axis', '?')}"
        if self.kind == "tool_offset":
            group = str(nb.get("group", ""))
            return "structure against the tool offset" + (
                f" (at {group.split(' (', 1)[0]})" if group else ""
            )
        if self.kind == "station":
            a = str(nb.get("axis", ""))
            return (
                f"a station's scatter ({a[16:-1]})"
                if a.startswith("station spread")
                else ("offset between stations")
            )
        if self.kind == "drift":
            return "drift in time"
        if self.kind == "budget":
            f = nb.get("factor", float("nan"))
            return "budget too small" if f > 1 else "budget pessimistic"
        return self.kind


@dataclass(frozen=True)
class Adequacy:
    """Verdict of the adequacy test (see the module docstring).

    verdict: one of :data:`VERDICTS` (``fits``, ``budget_pessimistic``, ``does_not_fit``);
    chi2_per_dof, dof and interval (the 99.9 % interval of chi2/dof); n_readings (used),
    n_stations; causes (most likely first, empty when the model fits); structure: per
    axis, tool offset, station and time, strongest first; outliers: numbers of the tail
    (``max_abs``, ``n_beyond_5_robust``, ``n_beyond_5_sigma``, ``excess_kurtosis``,
    ``robust_sigma``, ``chi2_share``); budget_factor: the factor by which the budget's
    sigmas would have to be multiplied for the part of chi2 that outliers do not explain
    (below 1: the uncertainties are conservative by ``1 / budget_factor``); warnings;
    message: the human paragraph.
    """

    verdict: str
    chi2_per_dof: float
    dof: int
    interval: tuple[float, float]
    n_readings: int
    n_stations: int
    causes: tuple[Cause, ...]
    structure: tuple[AxisStructure, ...]
    outliers: dict[str, Any]
    budget_factor: float
    warnings: tuple[str, ...]
    message: str

    @property
    def adequate(self) -> bool:
        """The model fits (``fits`` or ``budget_pessimistic``)."""
        return self.verdict != "does_not_fit"

    @property
    def cause(self) -> str | None:
        """The kind of the most likely cause (None when there is none)."""
        return self.causes[0].kind if self.causes else None

    @property
    def cause_kinds(self) -> list[str]:
        """The kinds of the causes, most likely first (for tables such as compare's)."""
        return [c.kind for c in self.causes]

    @property
    def strongest_axis(self) -> str | None:
        """The axis with the most significant residual structure (None without axes)."""
        axes = [s for s in self.structure if s.kind == "axis"]
        return axes[0].axis if axes else None

    @property
    def significant_structure(self) -> tuple[AxisStructure, ...]:
        """The structure tests below :data:`STRUCTURE_P`, strongest first."""
        return tuple(s for s in self.structure if s.significant)

    @property
    def summary(self) -> str:
        """One line for a terminal summary or a banner (the message is the paragraph)."""
        lo, hi = self.interval
        c2 = f"chi2/dof {self.chi2_per_dof:.3g}"
        if self.verdict == "fits":
            return f"fits ({c2} inside [{lo:.3g}, {hi:.3g}], no significant structure)"
        if self.verdict == "budget_pessimistic":
            return (
                f"fits; the budget is pessimistic ({c2} below [{lo:.3g}, {hi:.3g}], no "
                f"significant structure): uncertainties conservative by a factor of about "
                f"{1.0 / self.budget_factor:.3g}"
            )
        c = self.chi2_per_dof
        where = "above" if c > hi else "below" if c < lo else "inside"
        return (
            f"does NOT fit ({c2} {where} [{lo:.3g}, {hi:.3g}]"
            + (f"; likely cause: {', '.join(_shorts(self.causes))}" if self.causes else "")
            + ")"
        )

    def to_dict(self) -> dict[str, Any]:
        """Plain data for result.json (floats, lists, dicts); ``verdict`` and
        ``cause_kinds`` are the machine-readable verdict."""
        d = asdict(self)
        d["interval"] = list(self.interval)
        d["adequate"] = self.adequate
        d["cause_kinds"] = self.cause_kinds
        d["summary"] = self.summary
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Adequacy:
        """The inverse of :meth:`to_dict` (a saved result's ``adequacy``; results saved
        before the three outcomes read ``adequate`` as ``fits`` and ``inadequate`` as
        ``does_not_fit``)."""
        verdict = {"adequate": "fits", "inadequate": "does_not_fit"}.get(
            str(d["verdict"]), str(d["verdict"])
        )
        return cls(
            verdict=verdict,
            chi2_per_dof=float(d["chi2_per_dof"]),
            dof=int(d["dof"]),
            interval=(float(d["interval"][0]), float(d["interval"][1])),
            n_readings=int(d["n_readings"]),
            n_stations=int(d["n_stations"]),
            causes=tuple(Cause(**c) for c in d.get("causes", ())),
            structure=tuple(AxisStructure(**s) for s in d.get("structure", ())),
            outliers=dict(d.get("outliers", {})),
            budget_factor=float(d["budget_factor"]),
            warnings=tuple(d.get("warnings", ())),
            message=str(d["message"]),
        )

    def lines(self) -> list[str]:
        """The message and the warnings, one per line."""
        return [self.message, *self.warnings]


def _shorts(causes: Sequence[Cause]) -> list[str]:
    """The causes' few words, the axes of several basis causes in one.  After a biased
    strategy the structure causes are its likely consequences: only where the structure
    is is said (the report gives them as causes in their own right)."""
    if causes and causes[0].kind == "strategy":
        rest = [c for c in causes[1:] if c.kind not in ("outliers", "budget")]
        return (
            [causes[0].short]
            + [c.short for c in causes[1:] if c.kind == "outliers"]
            + (
                [f"structure against {', '.join(str(c.numbers.get('axis')) for c in rest)}"]
                if rest
                else []
            )
        )
    out: list[str] = []
    axes = [str(c.numbers.get("axis", "?")) for c in causes if c.kind == "basis"]
    for c in causes:
        if c.kind != "basis":
            out.append(c.short)
        elif len(axes) == 1:
            out.append(c.short)
        elif str(c.numbers.get("axis")) == axes[0]:
            out.append(f"basis too poor for axes {', '.join(axes)}")
    return out


# --------------------------------------------------------------------------------------
# statistics


def chi2_interval(dof: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """The two-sided ``confidence`` interval of chi2/dof for ``dof`` degrees of freedom."""
    # volcal.base.distributions, not scipy: its import would cost 0.1-0.15 s of every
    # short `volcal identify`
    a = (1.0 - confidence) / 2.0
    dof = max(int(dof), 1)
    return chi2_ppf(a, dof) / dof, chi2_ppf(1.0 - a, dof) / dof


# The tests group 10^6 readings a dozen times over: every grouping here is a hash or a
# count, O(readings), not a sort (np.unique sorts: its n log n made the adequacy test the
# one stage of `volcal identify` growing faster than the readings, exponent 1.06-1.19
# from 10^5 to 10^6).  Each gives what the np.unique call it replaces gave.


def _factorize(values: Any) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(np.asarray(values).astype(str), return_inverse=True)`` by hashing: the
    distinct texts in sorted order and each value's index among them."""
    codes, uniques = pd.factorize(np.asarray(values).ravel(), use_na_sentinel=False)
    names, inv = np.unique(np.asarray(uniques).astype(str), return_inverse=True)
    return names, inv.ravel()[codes]


def _dense(codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(codes, return_inverse=True)``'s inverse for non-negative integer codes of
    moderate size (cells: station x bin): (codes numbered 0.. in order, readings per
    code), by counting; other codes through np.unique."""
    c = np.asarray(codes)
    if c.dtype.kind in "iub" and len(c) and c.min() >= 0 and c.max() < 4 * len(c) + 4096:
        counts = np.bincount(c)
        present = counts > 0
        return (np.cumsum(present) - 1)[c], counts[present]
    inv = np.unique(c, return_inverse=True)[1].ravel()
    return inv, np.bincount(inv)


def _n_distinct(codes: np.ndarray) -> int:
    """The number of distinct non-negative integer codes (``len(np.unique(codes))``)."""
    return len(_dense(codes)[1])


def position_bins(values: np.ndarray, max_bins: int = MAX_BINS) -> tuple[np.ndarray, np.ndarray]:
    """Bin index per reading and the bin centres: the distinct positions when there are at
    most ``max_bins`` of them, else quantile bins (ties kept together)."""
    v = np.asarray(values, float)
    r = np.round(v, 9) + 0.0  # -0.0 as 0.0: one position (np.unique took them as equal)
    uniq = np.sort(pd.unique(r))  # hashing the readings, sorting the few distinct values
    if len(uniq) <= max_bins:
        code = np.searchsorted(uniq, r)
        return code, uniq
    edges = np.unique(np.quantile(v, np.linspace(0.0, 1.0, max_bins + 1)[1:-1]))
    code, counts = _dense(np.searchsorted(edges, v, side="right"))
    centres = np.bincount(code, weights=v) / counts
    return code, centres


def _within_ss(z: np.ndarray, group: np.ndarray) -> tuple[float, int]:
    """Sum of squares of z about its group means, and the number of groups."""
    g, n = _dense(group)
    s = np.bincount(g, weights=z)
    ss = float(np.sum(z * z) - np.sum(s * s / n))
    return max(ss, 0.0), len(n)


def _nested_f(
    z: np.ndarray, base: np.ndarray, cell: np.ndarray, label: str, unit: str, kind: str, n_bins: int
) -> AxisStructure | None:
    """Nested F-test: do the means of ``cell`` explain z beyond the means of ``base``?"""
    n = len(z)
    ss_base, k_base = _within_ss(z, base)
    ss_cell, k_cell = _within_ss(z, cell)
    df1, df2 = k_cell - k_base, n - k_cell
    if df1 < 1 or df2 < 1 or ss_cell <= 0:
        return None
    between = max(ss_base - ss_cell, 0.0)
    fstat = (between / df1) / (ss_cell / df2)
    # the log of the F survival function, accurate also where p itself underflows; kept
    # at -745 (the log of the smallest float) below, as when it came from p: the ranking
    # of the structure tests (log10_p, then the explained share) stays as it was
    logp = max(log_f_sf(df1, df2, fstat), -745.0)
    total = float(np.sum(z * z))
    explained = max(between - df1 * ss_cell / df2, 0.0) / total if total > 0 else 0.0
    return AxisStructure(
        axis=label,
        unit=unit,
        n_bins=int(n_bins),
        f=float(fstat),
        df1=int(df1),
        df2=int(df2),
        p_value=float(math.exp(logp)),
        log10_p=logp / math.log(10),
        explained_share=float(explained),
        kind=kind,
    )


def _binned(station: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, int]:
    """Cells station x bin of ``values`` and the number of bins."""
    code, centres = position_bins(values)
    return station.astype(np.int64) * (len(centres) + 1) + code, len(centres)


def _offset_name(key: str) -> str:
    """``(x, y, z) mm`` of a tool offset key ``"x,y,z"`` (the key itself otherwise)."""
    try:
        return "(" + ", ".join(f"{float(v):g}" for v in str(key).split(",")) + ") mm"
    except ValueError:
        return str(key)


def _tool_structure(
    z: np.ndarray, station: np.ndarray, codes: np.ndarray, names: Sequence[str] | None
) -> AxisStructure | None:
    """Structure against the tool offset.  An offset is a category, not a position: the
    cells are station x offset, every offset its own group however many there are (no
    binning).  Then each offset alone against the others (within each station): the
    smallest p, multiplied by the number of offsets (Bonferroni: the chance that any of
    them is that far off by chance), names the offset when it is significant."""
    codes = _dense(codes)[0]
    n_t = int(codes.max()) + 1
    st = station.astype(np.int64)
    overall = _nested_f(z, st, st * n_t + codes, "tool offset", "", "tool_offset", n_t)
    if overall is None or n_t < 3:
        return overall
    best: AxisStructure | None = None
    best_k = 0
    for k in range(n_t):
        one = _nested_f(z, st, st * 2 + (codes == k), "", "", "tool_offset", 2)
        if one is not None and (best is None or one.log10_p < best.log10_p):
            best, best_k = one, k
    if best is None:
        return overall
    log10_p = min(best.log10_p + math.log10(n_t), 0.0)
    if log10_p >= math.log10(STRUCTURE_P):
        return overall
    name = _offset_name(names[best_k]) if names is not None else str(best_k)
    return replace(
        overall,
        group=f"{name} (that offset alone against the others: F = {best.f:.3g}, p = "
        f"{10**log10_p:.2g} after multiplying by the {n_t} offsets)",
    )


def _structure(
    z: np.ndarray,
    station: np.ndarray,
    positions: pd.DataFrame | None,
    units: Sequence[str],
    tools: np.ndarray | None,
    time: np.ndarray | None,
    station_names: Sequence[str] | None = None,
    tool_names: Sequence[str] | None = None,
) -> list[AxisStructure]:
    """Every structure test the data allow (see the module), strongest first; ``tools``:
    a code per reading, ``tool_names`` the offset of each code."""
    out: list[AxisStructure | None] = []
    if positions is not None:
        for name, unit in zip(positions.columns, units):
            cell, nb = _binned(station, positions[name].to_numpy(float))
            if nb >= 2:
                out.append(_nested_f(z, station, cell, str(name), unit, "axis", nb))
    if tools is not None and _n_distinct(np.asarray(tools)) > 1:
        out.append(_tool_structure(z, station, np.asarray(tools), tool_names))
    n_st = _n_distinct(station)
    if n_st > 1:
        zero = np.zeros_like(station)
        out.append(_nested_f(z, zero, station, "station", "", "station", n_st))
        # a fitted dead length takes up a station's mean: what is left to see is one
        # station scattering more than the others (Brown-Forsythe: the means of the
        # absolute deviations from each station's median)
        med = np.zeros(len(z))
        present = [int(k) for k in np.flatnonzero(np.bincount(station))]
        for k in present:
            med[station == k] = np.median(z[station == k])
        spread = _nested_f(np.abs(z - med), zero, station, "station spread", "", "station", n_st)
        if spread is not None:
            rms = {k: float(np.sqrt(np.mean(z[station == k] ** 2))) for k in present}
            worst = max(rms, key=lambda k: rms[k])
            name = station_names[worst] if station_names is not None else str(worst)
            spread = replace(spread, axis=f"station spread (widest {name})")
            out.append(spread)
    if time is not None:
        t = np.asarray(time, float)
        fin = np.isfinite(t)
        if fin.sum() > 2 * MAX_BINS and t[fin].min() != t[fin].max():
            cell, nb = _binned(station[fin], t[fin])
            out.append(_nested_f(z[fin], station[fin], cell, "time", "s", "time", nb))
    res = [s for s in out if s is not None]
    res.sort(key=lambda s: (s.log10_p, -s.explained_share))
    return res


def _excess_kurtosis(z: np.ndarray) -> float:
    if len(z) < 4:
        return float("nan")
    c = z - z.mean()
    m2 = float(np.mean(c**2))
    return float(np.mean(c**4) / m2**2 - 3.0) if m2 > 0 else float("nan")


def _basis_advice(axis: str, forms: Sequence[Any], full_turn: bool) -> str:
    """What to do about an axis whose basis cannot follow its error motions."""
    described = sorted({f.describe() for f in forms}) if forms else []
    has = f" ({'; '.join(described)})" if described else ""
    kinds = {getattr(f, "kind", "") for f in forms}
    degree = max((int(getattr(f, "degree", 0) or 0) for f in forms), default=0)
    if "fourier" in kinds and full_turn:
        return (
            f"the basis of axis {axis}{has} is too poor for its error motions: a Fourier "
            "series assumes an error motion that returns to its value after a full turn; "
            f"if the error is periodic, raise the harmonics (--basis {axis}=fourier:"
            f"{degree + 2} or --degree auto), if it is not (it drifts over the turn), give "
            f"{axis} a basis that is not periodic (--basis {axis}=bspline:8)"
        )
    if "poly" in kinds:
        return (
            f"the basis of axis {axis}{has} is too poor for its error motions: let the data "
            f"choose the degree (--degree auto) or give {axis} more freedom (--basis "
            f"{axis}=poly:{degree + 2} or {axis}=bspline:8), or look for an error the model "
            "does not have"
        )
    return (
        f"the basis of axis {axis}{has} is too poor for its error motions: raise its degree "
        f"(--degree auto) or give {axis} a basis that fits (--basis {axis}=KIND:N, e.g. "
        "bspline:8 or, for a full-turn rotary axis with a periodic error, fourier:N), or look "
        "for an error the model does not have"
    )


def _structure_cause(
    s: AxisStructure, bases: Mapping[str, Sequence[Any]], full_turn: set[str]
) -> Cause:
    """The cause a significant structure points to, in a metrologist's words."""
    numbers = {
        "against": s.kind,
        "axis": s.axis,
        "f": s.f,
        "p_value": s.p_value,
        "log10_p": s.log10_p,
        "explained_share": s.explained_share,
        "n_bins": s.n_bins,
    }
    if s.group:
        numbers["group"] = s.group
    stat = (
        f"the residuals' group means against {s.label} explain "
        f"{100 * s.explained_share:.0f} % of the residual sum of squares (F = {s.f:.3g}, "
        f"{format_p(s)} < {STRUCTURE_P:g}, {s.n_bins} groups)"
    )
    kind = _CAUSE_OF[s.kind]
    if kind == "basis":
        text = f"{_basis_advice(s.axis, bases.get(s.axis, ()), s.axis in full_turn)}: {stat}"
    elif kind == "tool_offset":
        text = (
            f"the readings differ between tool offsets: {stat}"
            + (f"; most of all at tool offset {s.group}" if s.group else "")
            + "; check the tool offsets "
            "in the data (measure the reflectors' offsets, e.g. on a tool presetter) or "
            "look for an angular error the model does not have (when the offsets were "
            "measured one after the other, a drift in time shows here too)"
        )
    elif kind == "station" and s.axis.startswith("station spread"):
        text = (
            f"one station's readings scatter more than the others' ({s.axis[16:-1]}): "
            f"{stat}; that station moved or its beam path was disturbed during the run "
            "(reflector seating, air turbulence, a beam break re-initialised): check it and "
            "measure it again"
        )
    elif kind == "station":
        text = (
            f"the stations' readings are offset from each other: {stat}; check each "
            "station's dead path (reflector seating, the interferometer re-initialised "
            "during the run) and whether a station moved"
        )
    else:
        text = (
            f"drift in time: {stat}; the machine or the instrument drifted during the "
            "measurement (thermal growth, warm-up, a station moved): measure in a stable "
            "temperature or repeat a reference pose through the run to correct the drift "
            "(structure against an axis measured in order shows here too)"
        )
    return Cause(kind, s.explained_share, text, numbers)


def assess_residuals(
    normalised: Sequence[float] | np.ndarray,
    dof: int | None = None,
    *,
    stations: Sequence[Any] | np.ndarray | None = None,
    positions: pd.DataFrame | None = None,
    units: Sequence[str] | None = None,
    rejected: Sequence[bool] | np.ndarray | None = None,
    chi2_per_dof: float | None = None,
    tools: Sequence[Any] | np.ndarray | None = None,
    time: Sequence[float] | np.ndarray | None = None,
    strategy: str | None = None,
    bases: Mapping[str, Sequence[Any]] | None = None,
    full_turn: Sequence[str] = (),
) -> Adequacy:
    """Test whitened residuals for model adequacy (see the module docstring).

    normalised: whitened residuals ``r / sigma`` of every reading; dof: degrees of freedom
    of the fit (readings used minus free parameters plus constraints; default the number of
    readings used); stations: station id per reading (default one station); positions:
    one column per axis (mm / deg), a row per reading; units: the unit of each column
    (default ``""``); rejected: readings left out of the fit (ignored here);
    chi2_per_dof: the fit's own value (default ``sum z^2 / dof`` over the readings used);
    tools: a tool offset id per reading (several offsets: a structure test against them);
    time: time stamp per reading (s; NaN allowed: a structure test against time);
    strategy: the identification strategy (a biased one is named as a cause of
    structure); bases: per axis, the error forms of its error motions (``ErrorForm``, for
    the advice on a basis too poor); full_turn: the full-turn rotary axes.
    """
    z_all = np.asarray(normalised, float)
    keep = np.isfinite(z_all)
    if rejected is not None:
        keep &= ~np.asarray(rejected, bool)
    z = z_all[keep]
    n = len(z)
    if stations is None:
        st_names, st = np.array(["1"]), np.zeros(len(z_all), np.int64)[keep]
    else:
        st_names, st = _factorize(stations)
        st = st[keep]
    n_st = _n_distinct(st) if n else 0
    dof = n if dof is None else max(int(dof), 1)
    chi2_sum = float(np.sum(z * z))
    c2 = chi2_sum / dof if chi2_per_dof is None else float(chi2_per_dof)
    lo, hi = chi2_interval(dof)

    # the tail: outliers relative to the bulk's robust spread
    med = float(np.median(z)) if n else 0.0
    s_rob = float(1.4826 * np.median(np.abs(z - med))) if n else float("nan")
    s_ref = s_rob if s_rob > 0 else 1.0
    out_mask = np.abs(z - med) > OUTLIER_K * s_ref
    n_out = int(out_mask.sum())
    kurt = _excess_kurtosis(z)
    # under a normal law with the bulk's spread, OUTLIER_K sigmas are exceeded with this
    # probability: outliers count when they are clearly more than chance gives
    p_tail = 2.0 * norm_cdf(-OUTLIER_K)
    p_count = poisson_sf(n_out - 1, max(n * p_tail, 1e-300)) if n_out else 1.0
    ss_out = float(np.sum(z[out_mask] ** 2))
    outliers = {
        "max_abs": float(np.max(np.abs(z))) if n else float("nan"),
        "n_beyond_5_robust": n_out,
        "n_beyond_5_sigma": int(np.sum(np.abs(z) > 5.0)),
        "robust_sigma": s_rob,
        "excess_kurtosis": kurt,
        "chi2_share": ss_out / chi2_sum if chi2_sum > 0 else 0.0,
    }

    # structure on the readings that are not outliers
    structure: list[AxisStructure] = []
    if n:
        inl = ~out_mask
        pos = None
        u: list[str] = []
        if positions is not None and len(positions.columns):
            pos = positions.loc[keep].reset_index(drop=True).loc[inl].reset_index(drop=True)
            u = list(units) if units is not None else [""] * len(pos.columns)
        tl, t_names = None, None
        if tools is not None:
            uniq, codes = _factorize(tools)
            tl, t_names = codes[keep][inl], [str(v) for v in uniq]
        tm = np.asarray(time, float)[keep][inl] if time is not None else None
        structure = _structure(z[inl], st[inl], pos, u, tl, tm, list(st_names), t_names)
    significant = [s for s in structure if s.significant]

    warnings: list[str] = []
    if n_st == 1:
        warnings.append(
            "all readings come from a single station: lengths from one station "
            "cannot separate the station's position from the machine's errors, "
            "so a passing chi2 says little about the identified errors; measure "
            "from at least four stations that are not coplanar"
        )

    # the expected chi2 with the right model and budget is dof; the outliers carry their
    # sum of squares beyond what the bulk's spread gives them, the rest is a budget factor
    expected = float(dof)
    excess = c2 * dof - expected
    out_excess = max(ss_out - n_out * s_ref**2, 0.0) if n_out and p_count < 1e-3 else 0.0
    dof_in = max(dof - n_out, 1)
    rest = max(chi2_sum - ss_out, 0.0) / dof_in
    budget_factor = float(math.sqrt(rest)) if rest > 0 else float("nan")
    rest_lo, rest_hi = chi2_interval(dof_in)

    if significant:
        verdict = "does_not_fit"
    elif c2 > hi:
        verdict = "does_not_fit"
    elif c2 < lo:
        verdict = "budget_pessimistic"
    else:
        verdict = "fits"

    causes: list[Cause] = []
    if verdict != "fits":
        heavy = (
            n_out > 0
            and p_count < 1e-3
            and (kurt > HEAVY_TAIL_KURTOSIS or outliers["chi2_share"] > 0.05)
        )
        out_share = out_excess / excess if excess > 0 else 0.0
        if heavy and (out_share >= CAUSE_MIN_SHARE or significant):
            causes.append(
                Cause(
                    "outliers",
                    out_share,
                    f"outliers: {n_out} reading(s) beyond {OUTLIER_K:g} robust standard "
                    f"deviations of the bulk (largest |normalised residual| "
                    f"{outliers['max_abs']:.3g}, excess kurtosis {kurt:.3g}) carry "
                    f"{100 * outliers['chi2_share']:.0f} % of chi2; look for blunders "
                    "(wrong reflector, beam breaks, a mistyped pose) or run with --robust",
                    {
                        k: outliers[k]
                        for k in (
                            "max_abs",
                            "n_beyond_5_robust",
                            "n_beyond_5_sigma",
                            "excess_kurtosis",
                            "chi2_share",
                        )
                    },
                )
            )
        found = [_structure_cause(s, dict(bases or {}), set(full_turn)) for s in significant]
        if found and strategy in BIASED_STRATEGIES:
            strongest = significant[0]
            found.insert(
                0,
                Cause(
                    "strategy",
                    strongest.explained_share,
                    f"the strategy is biased: {BIASED_STRATEGIES[str(strategy)]} (strongest "
                    f"against {strongest.label}: F = {strongest.f:.3g}, {format_p(strongest)}); "
                    "run --strategy joint (stations and errors estimated together) on the "
                    "same data; if the structure stays, the causes below remain",
                    {"strategy": str(strategy), "against": strongest.label},
                ),
            )
        # blunders first only when they carry most of the excess: they also pull the fit
        # and so leave structure of their own behind
        if causes and found and out_share < 0.5:
            causes = found + causes
        else:
            causes = causes + found
        budget_off = not (rest_lo <= rest <= rest_hi)
        # the budget is judged only on residuals without significant structure: a misfit
        # is not noise, and scaling the uncertainties would hide it
        if not significant and (
            excess <= 0
            or not causes
            or (budget_off and abs(budget_factor - 1.0) >= 0.1 and 1 - out_share >= CAUSE_MIN_SHARE)
        ):
            if budget_factor > 1:
                text = (
                    "the uncertainty budget is too small: the residuals show no "
                    f"significant structure (every F-test p >= {STRUCTURE_P:g})"
                    + (
                        f" and look Gaussian (excess kurtosis {kurt:.2g})"
                        if not causes and math.isfinite(kurt)
                        else ""
                    )
                    + (
                        ""
                        if not causes
                        else ", and they scatter more than the budget allows beyond "
                        "what the outliers explain"
                    )
                    + f": the readings' standard uncertainties would have to be multiplied "
                    f"by {budget_factor:.3g} (or the budget is not the instrument's; "
                    "--scale-covariance scales the uncertainties by chi2/dof)"
                )
            else:
                text = (
                    "the uncertainty budget is pessimistic: the residuals show no "
                    f"significant structure (every F-test p >= {STRUCTURE_P:g}) and "
                    "scatter less than the readings' standard uncertainties say, so the "
                    "reported uncertainties are conservative by a factor of about "
                    f"{1.0 / budget_factor:.3g} (the budget's sigmas could be multiplied by "
                    f"{budget_factor:.3g}, or --scale-covariance scales the uncertainties by "
                    "chi2/dof)"
                )
            share = max(excess - out_excess, 0.0) / excess if excess > 0 else 1.0
            numbers = {"factor": budget_factor, "variance_factor": rest}
            causes.append(Cause("budget", share, text, numbers))

    interval = f"its 99.9 % interval [{lo:.4g}, {hi:.4g}] for {dof} degrees of freedom"
    tested = ", ".join(
        dict.fromkeys(s.label if s.kind != "axis" else "the axes" for s in structure)
    )
    if verdict == "fits":
        msg = f"the model fits: chi2/dof = {c2:.4g} lies inside {interval}" + (
            f", and no residual structure (against {tested}) reaches p < {STRUCTURE_P:g}"
            if structure
            else ""
        )
    elif verdict == "budget_pessimistic":
        msg = (
            f"the model fits, and the budget is pessimistic: chi2/dof = {c2:.4g} lies below "
            f"{interval} with no significant residual structure (against {tested or 'nothing'};"
            f" threshold p < {STRUCTURE_P:g}): the readings scatter less than the budget says, "
            "so the reported uncertainties are conservative by a factor of about "
            f"{1.0 / budget_factor:.3g}"
        )
    else:
        where = "above" if c2 > hi else "below" if c2 < lo else "inside"
        msg = (
            f"the model does NOT fit the data within their uncertainty: chi2/dof = {c2:.4g} "
            f"lies {where} {interval}"
            + (
                f"; the residuals are structured (F-test p < {STRUCTURE_P:g} against "
                + ", ".join(s.label for s in significant)
                + ")"
                if significant
                else ""
            )
            + "; likely cause: "
            + "; also ".join(c.text for c in causes)
        )
    return Adequacy(
        verdict=verdict,
        chi2_per_dof=float(c2),
        dof=int(dof),
        interval=(lo, hi),
        n_readings=int(n),
        n_stations=n_st,
        causes=tuple(causes),
        structure=tuple(structure),
        outliers=outliers,
        budget_factor=budget_factor,
        warnings=tuple(warnings),
        message=msg,
    )


def format_p(s: AxisStructure) -> str:
    return f"p = {s.p_value:.2g}" if s.log10_p > -300 else "p < 1e-300"


# --------------------------------------------------------------------------------------
# results


def _axes(result: Any) -> tuple[list[str], list[str]]:
    spec = result.machine.spec
    names = [a.name for a in spec.axes]
    units = ["deg" if a.is_rotary else "mm" for a in spec.axes]
    return names, units


def _bases(result: Any) -> dict[str, list[Any]]:
    """Per axis, the error forms of its error motions (empty without an error model)."""
    em = getattr(result, "error_model", None)
    out: dict[str, list[Any]] = {}
    for s, f in zip(getattr(em, "errors", ()), getattr(em, "forms", ())):
        if s.kind == "component" and f not in out.setdefault(s.axis, []):
            out[s.axis].append(f)
    return out


def _dof(result: Any, z: np.ndarray, keep: np.ndarray) -> tuple[int, float | None]:
    """The fit's degrees of freedom: from chi2/dof and the weighted residuals the fit
    reports (``dof = sum z^2 / (chi2/dof)``), else the number of readings used."""
    c2 = (getattr(result, "conditions", None) or {}).get("chi2_per_dof")
    n = int(keep.sum())
    if c2 is None or not np.isfinite(c2) or c2 <= 0:
        return n, None
    dof = int(round(float(np.sum(z[keep] ** 2)) / float(c2)))
    return max(min(dof, n), 1), float(c2)


def assess(result: Any) -> Adequacy:
    """The adequacy of an identification result (see the module docstring).

    Uses ``result.residuals`` (``normalised_residual``, ``rejected``, ``station``, the
    axis columns, the tool offsets and ``time`` when present),
    ``result.conditions['chi2_per_dof']``, ``result.machine.spec``, ``result.strategy`` and
    ``result.error_model``.
    The result is computed once per result object and kept on it
    (``result.__dict__['_adequacy']``)."""
    cached = getattr(result, "__dict__", {}).get("_adequacy")
    if cached is not None and cached[0] is result.residuals:
        return cached[1]
    res = result.residuals
    z = res["normalised_residual"].to_numpy(float)
    rejected = np.asarray(res["rejected"], bool) if "rejected" in res else np.zeros(len(res), bool)
    keep = np.isfinite(z) & ~rejected
    dof, c2 = _dof(result, z, keep)
    names, units = _axes(result)
    cols = [n for n in names if n in res.columns]
    tcols = [c for c in ("tool_x", "tool_y", "tool_z") if c in res.columns]
    tools = None
    if tcols:
        # One "x,y,z" key per reading, joined column-wise: a row-wise agg(",".join) took
        # seconds at 10^5 readings for the same strings.  "+ 0.0" turns -0.0 (a tiny
        # negative offset rounded) into 0.0, so one offset gets one key.
        rounded = res[tcols].round(6) + 0.0
        vals = rounded.to_numpy(float)
        if np.isfinite(vals).all():
            # the text of each distinct offset once (str(float) is the text astype(str)
            # gives), handed to its readings: 10^4 readings share a handful of offsets.
            # The offsets told apart by hashing each column, not by sorting the rows
            row = np.zeros(len(vals), np.int64)
            for j in range(vals.shape[1]):
                cj, uj = pd.factorize(vals[:, j])
                row = pd.factorize(row * len(uj) + cj)[0]  # renumbered: stays below n
            first = np.empty(int(row.max()) + 1 if len(row) else 0, np.int64)
            first[row[::-1]] = np.arange(len(row))[::-1]  # each offset's first reading
            keys = np.array([",".join(map(str, r)) for r in vals[first].tolist()], dtype=object)
            tools = keys[row]
        else:
            txt = rounded.astype(str)
            key = txt[tcols[0]]
            for c in tcols[1:]:
                key = key + "," + txt[c]
            tools = key.to_numpy(dtype=object)
    time = res["time"].to_numpy(float) if "time" in res.columns else None
    if time is not None and not np.isfinite(time).any():
        time = None
    ad = assess_residuals(
        z,
        dof,
        stations=res["station"].to_numpy() if "station" in res else None,
        positions=res[cols] if cols else None,
        units=[u for n, u in zip(names, units) if n in cols],
        rejected=rejected,
        chi2_per_dof=c2,
        tools=tools,
        time=time,
        strategy=getattr(result, "strategy", None),
        bases=_bases(result),
        full_turn=[a.name for a in result.machine.spec.axes if a.full_turn],
    )
    try:
        result.__dict__["_adequacy"] = (result.residuals, ad)
    except (AttributeError, TypeError):  # pragma: no cover - slotted or frozen results
        pass
    return ad
