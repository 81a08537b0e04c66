"""Model adequacy: does the identified model explain the readings within their uncertainty?

After a weighted least-squares fit the whitened (normalised) residuals ``z = r / sigma``
of a model that is right, with a right uncertainty budget, are independent standard normal
numbers, so ``chi2 = sum z^2`` follows a chi-square distribution with the fit's degrees of
freedom ``dof``.  :func:`assess_residuals` tests ``chi2 / dof`` against its two-sided
99.9 % interval ``[chi2.ppf(0.0005, dof), chi2.ppf(0.9995, dof)] / dof`` and, when it lies
outside, names the likely cause with its numbers:

* **structure** against one axis' position (the error model cannot follow an error motion
  of that axis: too low a degree, the wrong basis, a missing error): for every axis the
  residuals are grouped into cells (station x position bin: a misfit of the tool point
  enters each station's readings through its own beam direction, so its sign differs
  between stations) and a nested F-test compares the cell means with the station means
  alone.  The axis whose position explains the most is reported with its F statistic,
  p-value and the share of the residual sum of squares its binned means explain beyond
  chance;
* **outliers** (blunders, heavy tails): the largest ``|z|``, the number of readings beyond
  5 robust standard deviations of the bulk (``1.4826 MAD``) and beyond 5 budget sigmas,
  the excess kurtosis and the share of ``chi2`` the outliers carry;
* **the budget** (``chi2 / dof`` off, residuals unstructured and Gaussian-looking): the
  readings' standard uncertainties are too small (or too large) by a factor, reported as
  the factor the budget's sigmas should be multiplied by (``sqrt`` of the variance factor
  that remains once outliers and structure are accounted for).

The share of the excess ``chi2 - dof`` each candidate explains orders the causes; every
candidate that explains at least :data:`CAUSE_MIN_SHARE` of it is named.  Data from a
single station always draw a warning: lengths from one station cannot separate the
station's position from the machine's errors, so even a passing ``chi2`` says little.

:func:`assess` applies this to an identification result (``IdentificationResult`` or a
result with the same ``residuals`` / ``conditions`` / ``machine``);
:func:`volcal.plots.residuals_vs_axes` draws the normalised residuals against each axis
position with the binned means of :func:`position_bins`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import pandas as pd

__all__ = [
    "Adequacy",
    "AxisStructure",
    "Cause",
    "assess",
    "assess_residuals",
    "position_bins",
    "format_p",
    "CONFIDENCE",
    "MAX_BINS",
    "OUTLIER_K",
    "STRUCTURE_P",
    "CAUSE_MIN_SHARE",
]

#: two-sided probability content of the chi2/dof acceptance interval
CONFIDENCE = 0.999
#: at most this many position bins per axis (axes with more distinct positions are binned
#: at quantiles)
MAX_BINS = 12
#: a reading is an outlier beyond this many robust standard deviations of the bulk
OUTLIER_K = 5.0
#: structure against an axis counts only below this p-value of its F-test
STRUCTURE_P = 1e-6
#: a cause is named when it explains at least this share of the excess chi2
CAUSE_MIN_SHARE = 0.2
#: excess kurtosis above this marks heavy tails (a normal sample of 1000 readings has a
#: standard error of about 0.15)
HEAVY_TAIL_KURTOSIS = 1.0


@dataclass(frozen=True)
class AxisStructure:
    """Residual structure against one axis' position (nested F-test, see the module).

    axis, unit (mm / deg); n_bins: position bins used; f: the F statistic with degrees of
    freedom (df1, df2); p_value: its upper tail probability (0 when below the smallest
    float; ``log10_p`` keeps the size); explained_share: share of the residual sum of
    squares explained by the binned means beyond what chance explains (0..1).
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


@dataclass(frozen=True)
class Cause:
    """One likely cause of an inadequate fit: kind (``structure``, ``outliers`` or
    ``budget``), share of the excess chi2 it explains (0..1, negative excess for a budget
    that is too large: then 1), a sentence and its numbers."""

    kind: str
    share: float
    text: str
    numbers: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Adequacy:
    """Verdict of the adequacy test (see the module docstring).

    verdict: ``adequate`` or ``inadequate``; chi2_per_dof, dof and interval (the 99.9 %
    interval of chi2/dof); n_readings (used), n_stations; causes (most likely first,
    empty when adequate); structure: per axis, strongest first; outliers: numbers of the
    tail (``max_abs``, ``n_beyond_5_robust``, ``n_beyond_5_sigma``, ``excess_kurtosis``,
    ``robust_sigma``, ``chi2_share``); budget_factor: the factor by which the budget's
    sigmas would have to be multiplied for the part of chi2 that neither outliers nor
    structure explain; warnings; message: one human sentence.
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
        return self.verdict == "adequate"

    @property
    def cause(self) -> str | None:
        """The kind of the most likely cause (None when adequate)."""
        return self.causes[0].kind if self.causes else None

    @property
    def strongest_axis(self) -> str | None:
        """The axis with the most significant residual structure (None without axes)."""
        return self.structure[0].axis if self.structure else None

    def to_dict(self) -> dict[str, Any]:
        """Plain data for result.json (floats, lists, dicts)."""
        d = asdict(self)
        d["interval"] = list(self.interval)
        d["adequate"] = self.adequate
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Adequacy:
        """The inverse of :meth:`to_dict` (a saved result's ``adequacy``)."""
        return cls(
            verdict=str(d["verdict"]),
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


# --------------------------------------------------------------------------------------
# statistics


def chi2_interval(dof: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """The two-sided ``confidence`` interval of chi2/dof for ``dof`` degrees of freedom."""
    # scipy.special, not scipy.stats: the same functions (chi2.ppf(p, k) =
    # 2 gammaincinv(k / 2, p)) without a second of imports in every `volcal identify`
    from scipy.special import gammaincinv

    a = (1.0 - confidence) / 2.0
    dof = max(int(dof), 1)
    return (
        float(2.0 * gammaincinv(dof / 2.0, a) / dof),
        float(2.0 * gammaincinv(dof / 2.0, 1.0 - a) / dof),
    )


def position_bins(values: np.ndarray, max_bins: int = MAX_BINS) -> tuple[np.ndarray, np.ndarray]:
    """Bin index per reading and the bin centres: the distinct positions when there are at
    most ``max_bins`` of them, else quantile bins (ties kept together)."""
    v = np.asarray(values, float)
    uniq = np.unique(np.round(v, 9))
    if len(uniq) <= max_bins:
        code = np.searchsorted(uniq, np.round(v, 9))
        return code, uniq
    edges = np.unique(np.quantile(v, np.linspace(0.0, 1.0, max_bins + 1)[1:-1]))
    code = np.searchsorted(edges, v, side="right")
    code = np.unique(code, return_inverse=True)[1]
    centres = np.array([np.mean(v[code == k]) for k in range(code.max() + 1)])
    return code, centres


def _within_ss(z: np.ndarray, group: np.ndarray) -> tuple[float, int]:
    """Sum of squares of z about its group means, and the number of groups."""
    g = np.unique(group, return_inverse=True)[1]
    n = np.bincount(g)
    s = np.bincount(g, weights=z)
    ss = float(np.sum(z * z) - np.sum(s * s / n))
    return max(ss, 0.0), len(n)


def _axis_structure(
    z: np.ndarray, station: np.ndarray, positions: pd.DataFrame, units: Sequence[str]
) -> list[AxisStructure]:
    from scipy.special import fdtrc  # F survival function (scipy.stats.f.sf)

    n = len(z)
    ss_st, k_st = _within_ss(z, station)
    out = []
    for name, unit in zip(positions.columns, units):
        code, centres = position_bins(positions[name].to_numpy(float))
        if len(centres) < 2:
            continue
        cell = station.astype(np.int64) * (len(centres) + 1) + code
        ss_cell, k_cell = _within_ss(z, cell)
        df1, df2 = k_cell - k_st, n - k_cell
        if df1 < 1 or df2 < 1 or ss_cell <= 0:
            continue
        between = max(ss_st - ss_cell, 0.0)
        fstat = (between / df1) / (ss_cell / df2)
        with np.errstate(divide="ignore"):
            logp = float(np.log(fdtrc(df1, df2, fstat)))
        if not math.isfinite(logp):  # beyond the float range
            logp = -745.0
        total = float(np.sum(z * z))
        explained = max(between - df1 * ss_cell / df2, 0.0) / total if total > 0 else 0.0
        out.append(
            AxisStructure(
                axis=str(name),
                unit=unit,
                n_bins=len(centres),
                f=float(fstat),
                df1=int(df1),
                df2=int(df2),
                p_value=float(math.exp(logp)),
                log10_p=logp / math.log(10),
                explained_share=float(explained),
            )
        )
    out.sort(key=lambda s: (s.log10_p, -s.explained_share))
    return out


def _excess_kurtosis(z: np.ndarray) -> float:
    if len(z) < 4:
        return float("nan")
    c = z - z.mean()
    m2 = float(np.mean(c**2))
    return float(np.mean(c**4) / m2**2 - 3.0) if m2 > 0 else float("nan")


def assess_residuals(
    normalised: Sequence[float] | np.ndarray,
    dof: int | None = None,
    *,
    stations: Sequence[Any] | np.ndarray | None = None,
    positions: pd.DataFrame | None = None,
    units: Sequence[str] | None = None,
    rejected: Sequence[bool] | np.ndarray | None = None,
    chi2_per_dof: float | None = None,
) -> Adequacy:
    """Test whitened residuals for model adequacy (see the module docstring).

    normalised: whitened residuals ``r / sigma`` of every reading; dof: degrees of freedom
    of the fit (readings used minus free parameters plus constraints; default the number of
    readings used); stations: station id per reading (default one station); positions:
    one column per axis (mm / deg), a row per reading; units: the unit of each column
    (default ``""``); rejected: readings left out of the fit (ignored here);
    chi2_per_dof: the fit's own value (default ``sum z^2 / dof`` over the readings used).
    """
    z_all = np.asarray(normalised, float)
    keep = np.isfinite(z_all)
    if rejected is not None:
        keep &= ~np.asarray(rejected, bool)
    z = z_all[keep]
    n = len(z)
    st = (
        np.zeros(len(z_all), np.int64)
        if stations is None
        else np.unique(np.asarray(stations).astype(str), return_inverse=True)[1]
    )[keep]
    n_st = int(len(np.unique(st))) if n else 0
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
    from scipy.special import ndtr, pdtrc  # normal cdf, Poisson survival function

    p_tail = 2.0 * float(ndtr(-OUTLIER_K))
    p_count = float(pdtrc(n_out - 1, max(n * p_tail, 1e-300))) if n_out else 1.0
    ss_out = float(np.sum(z[out_mask] ** 2))
    outliers = {
        "max_abs": float(np.max(np.abs(z))) if n else float("nan"),
        "n_beyond_5_robust": n_out,
        "n_beyond_5_sigma": int(np.sum(np.abs(z) > 5.0)),
        "robust_sigma": s_rob,
        "excess_kurtosis": kurt,
        "chi2_share": ss_out / chi2_sum if chi2_sum > 0 else 0.0,
    }

    # structure against each axis, on the readings that are not outliers
    structure: list[AxisStructure] = []
    if positions is not None and len(positions.columns) and n:
        pos = positions.loc[keep].reset_index(drop=True)
        u = list(units) if units is not None else [""] * len(pos.columns)
        inl = ~out_mask
        structure = _axis_structure(z[inl], st[inl], pos.loc[inl].reset_index(drop=True), u)

    warnings: list[str] = []
    if n_st == 1:
        warnings.append(
            "all readings come from a single station: lengths from one station "
            "cannot separate the station's position from the machine's errors, "
            "so a passing chi2 says little about the identified errors; measure "
            "from at least four stations that are not coplanar"
        )

    inside = lo <= c2 <= hi
    causes: list[Cause] = []
    # the expected chi2 with the right model and budget is dof; split the excess between
    # the outliers (their sum of squares beyond what the bulk's spread gives them), the
    # strongest structure (the sum of squares its binned means explain beyond chance) and
    # the rest (a budget factor)
    expected = float(dof)
    excess = c2 * dof - expected
    n_in = n - n_out
    ss_in = chi2_sum - ss_out
    out_excess = max(ss_out - n_out * s_ref**2, 0.0) if n_out and p_count < 1e-3 else 0.0
    best = structure[0] if structure else None
    struct_ok = best is not None and best.p_value < STRUCTURE_P
    struct_excess = best.explained_share * ss_in if best is not None and struct_ok else 0.0
    dof_in = max(dof - (n - n_in), 1)
    rest = max(ss_in - struct_excess, 0.0) / dof_in
    budget_factor = float(math.sqrt(rest)) if rest > 0 else float("nan")
    rest_lo, rest_hi = chi2_interval(dof_in)

    if not inside:
        if excess > 0:
            shares = {
                "outliers": out_excess / excess,
                "structure": struct_excess / excess,
                "budget": max(excess - out_excess - struct_excess, 0.0) / excess,
            }
        else:
            shares = {"outliers": 0.0, "structure": 0.0, "budget": 1.0}
        heavy = (
            n_out > 0
            and p_count < 1e-3
            and (kurt > HEAVY_TAIL_KURTOSIS or outliers["chi2_share"] > 0.05)
        )
        if heavy and shares["outliers"] >= CAUSE_MIN_SHARE:
            causes.append(
                Cause(
                    "outliers",
                    shares["outliers"],
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
        if best is not None and struct_ok and shares["structure"] >= CAUSE_MIN_SHARE:
            causes.append(
                Cause(
                    "structure",
                    shares["structure"],
                    f"structure against axis {best.axis}: the residuals' binned means over its "
                    f"position explain {100 * best.explained_share:.0f} % of the residual sum "
                    f"of squares (F = {best.f:.3g}, {format_p(best)}, {best.n_bins} position "
                    f"bins); the error model cannot follow an error motion of {best.axis} "
                    "(raise its degree, use a basis that fits, e.g. a Fourier series for a "
                    "rotary axis, or look for an error the model does not have)",
                    {
                        "axis": best.axis,
                        "f": best.f,
                        "p_value": best.p_value,
                        "log10_p": best.log10_p,
                        "explained_share": best.explained_share,
                        "n_bins": best.n_bins,
                    },
                )
            )
        budget_off = not (rest_lo <= rest <= rest_hi)
        # a budget factor within 10 % of one is not worth naming beside another cause
        budget_also = (
            budget_off and shares["budget"] >= CAUSE_MIN_SHARE and abs(budget_factor - 1.0) >= 0.1
        )
        if excess <= 0 or budget_also or not causes:
            word = "too small" if budget_factor > 1 else "too large"
            gauss = f"excess kurtosis {kurt:.2g}" if math.isfinite(kurt) else ""
            causes.append(
                Cause(
                    "budget",
                    shares["budget"],
                    "the uncertainty budget: the residuals are "
                    + (
                        "unstructured and Gaussian-looking"
                        if not causes
                        else "larger than the budget allows beyond what the causes above explain"
                    )
                    + (f" ({gauss})" if gauss and not causes else "")
                    + f", but {word}: the readings' standard uncertainties would have to be "
                    f"multiplied by {budget_factor:.3g} (or the budget is not the instrument's; "
                    "--scale-covariance scales the uncertainties by chi2/dof)",
                    {"factor": budget_factor, "variance_factor": rest},
                )
            )
        causes.sort(key=lambda c: -c.share)

    verdict = "adequate" if inside else "inadequate"
    if inside:
        msg = (
            f"the model fits: chi2/dof = {c2:.4g} lies inside its 99.9 % interval "
            f"[{lo:.4g}, {hi:.4g}] for {dof} degrees of freedom"
        )
    else:
        msg = (
            f"the model does NOT fit the data within their uncertainty: chi2/dof = "
            f"{c2:.4g} lies outside its 99.9 % interval [{lo:.4g}, {hi:.4g}] for {dof} "
            "degrees of freedom; likely cause: " + "; also ".join(c.text for c in causes)
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

    Uses ``result.residuals`` (``normalised_residual``, ``rejected``, ``station`` and the
    axis columns), ``result.conditions['chi2_per_dof']`` and ``result.machine.spec``.
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
    ad = assess_residuals(
        z,
        dof,
        stations=res["station"].to_numpy() if "station" in res else None,
        positions=res[cols] if cols else None,
        units=[u for n, u in zip(names, units) if n in cols],
        rejected=rejected,
        chi2_per_dof=c2,
    )
    try:
        result.__dict__["_adequacy"] = (result.residuals, ad)
    except (AttributeError, TypeError):  # pragma: no cover - slotted or frozen results
        pass
    return ad
