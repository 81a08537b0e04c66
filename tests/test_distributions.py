"""volcal.base.distributions against scipy.special, the functions it replaces on
``volcal identify``'s path (scipy is the independent reference here: the module exists
only so that a short identification does not import it), over the ranges the adequacy
test and the residual plot use, and against mpmath (arbitrary precision) where scipy's
double-precision value underflows.

Tolerances (relative unless said):

* chi2_ppf, poisson_sf: 1e-10 (both sides reach ~1e-13; the quantile is well-conditioned);
* norm_cdf, norm_ppf: 1e-12 (both are erfc / AS 241 to a few ulp; ``erfc(-x / sqrt 2)``
  carries a relative error ~x^2 eps from the rounding of its argument, 3e-13 at x = -37);
* log_f_sf: the logs agree to 1e-10 absolute, or relative where |log p| > 1 (the far tail);
  near the continued fraction's branch point at d2 ~ 10^6 the log is good to ~1e-11.
"""

from __future__ import annotations

import math
import subprocess
import sys

import mpmath
import numpy as np
import pytest
import scipy.special as sc
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from volcal.base import distributions as D

DRAWN = settings(
    max_examples=300,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow],
)


def _rel(a: float, b: float) -> float:
    return abs(a - b) / abs(b) if b != 0 else abs(a)


def _log_uniform(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(math.log10(lo), math.log10(hi)).map(lambda e: 10.0**e)


# dof 1 to 10^6: mostly spread on a log scale, plus the two ends
_DOF = st.one_of(
    st.sampled_from([1, 2, 10**6]),
    _log_uniform(1.0, 1e6).map(lambda v: max(1, round(v))),
)
# p over (0, 1): both tails on a log scale down to 1e-300 and the middle
_P = st.one_of(
    _log_uniform(1e-300, 0.5),
    _log_uniform(1e-12, 0.5).map(lambda q: 1.0 - q),
    st.floats(0.01, 0.99),
    st.sampled_from([5e-4, 0.9995]),
)


@DRAWN
@given(_DOF, _P)
def test_chi2_ppf_matches_scipy(dof: int, p: float) -> None:
    ours = D.chi2_ppf(p, dof)
    ref = 2.0 * float(sc.gammaincinv(dof / 2.0, p))
    assert _rel(ours, ref) <= 1e-10, (dof, p, ours, ref)


@DRAWN
@given(
    st.one_of(st.sampled_from([0, 1, 10**5]), _log_uniform(1.0, 1e5).map(round)),
    st.one_of(st.sampled_from([1e-300, 1e-10, 0.5]), _log_uniform(1e-300, 2e5)),
)
def test_poisson_sf_matches_scipy(k: int, mu: float) -> None:
    ours = D.poisson_sf(k, mu)
    ref = float(sc.pdtrc(k, mu))
    if ref < 1e-290:  # scipy's value underflows (or is subnormal): ours must be as small
        assert ours < 1e-280, (k, mu, ours, ref)
    else:
        assert _rel(ours, ref) <= 1e-10, (k, mu, ours, ref)


@DRAWN
@given(
    st.one_of(st.sampled_from([1, 3000]), st.integers(1, 3000)),
    st.one_of(st.sampled_from([1, 10**6]), _log_uniform(1.0, 1e6).map(lambda v: max(1, round(v)))),
    st.one_of(_log_uniform(1e-8, 1e8), st.floats(0.3, 3.0), st.sampled_from([1.0])),
)
def test_log_f_sf_matches_scipy(d1: int, d2: int, f: float) -> None:
    ours = D.log_f_sf(d1, d2, f)
    ref_p = float(sc.fdtrc(d1, d2, f))
    if ref_p < 1e-300:  # scipy underflows: ours keeps going (checked against mpmath below)
        assert ours < math.log(1e-295), (d1, d2, f, ours, ref_p)
        return
    ref = math.log(ref_p)
    assert abs(ours - ref) <= 1e-10 * max(1.0, abs(ref)), (d1, d2, f, ours, ref)


def _mp_log_f_sf(d1: float, d2: float, f: float) -> float:
    """log P(F > f) in 50-digit arithmetic: I_x(d2 / 2, d1 / 2), x = d2 / (d2 + d1 f)."""
    with mpmath.workdps(50):
        x = mpmath.mpf(d2) / (mpmath.mpf(d2) + mpmath.mpf(d1) * mpmath.mpf(f))
        return float(
            mpmath.log(
                mpmath.betainc(mpmath.mpf(d2) / 2, mpmath.mpf(d1) / 2, 0, x, regularized=True)
            )
        )


@pytest.mark.parametrize(
    ("d1", "d2", "f"),
    [
        (30, 10**6, 80.0),  # p ~ 1e-488: the structure tests' far tail
        (3000, 10**4, 4.0),
        (1, 10**6, 2000.0),
        (20, 10**4, 1e3),
        (1, 1, 1e300),  # p ~ 1e-150: scipy gives 0 once d1 f overflows
        (2, 1, 1e308),
        (30, 10**6, 1.0),  # near the continued fraction's branch point
        (1, 10**6, 3.0),
    ],
)
def test_log_f_sf_far_tail_matches_mpmath(d1: int, d2: int, f: float) -> None:
    ref = _mp_log_f_sf(d1, d2, f)
    ours = D.log_f_sf(d1, d2, f)
    assert abs(ours - ref) <= 1e-10 * max(1.0, abs(ref)), (d1, d2, f, ours, ref)


def test_log_f_sf_edges() -> None:
    """F = 0 and below: p = 1; F = inf: p = 0; a huge finite F: finite and decreasing."""
    assert D.log_f_sf(3, 100, 0.0) == 0.0
    assert D.log_f_sf(3, 100, -1.0) == 0.0
    assert D.log_f_sf(3, 100, math.inf) == -math.inf
    a, b = D.log_f_sf(3, 100, 1e200), D.log_f_sf(3, 100, 1e300)
    assert math.isfinite(a) and math.isfinite(b) and b < a < -745.0
    # the far tail falls like f^(-d2 / 2): the slope of log p against log f
    assert (b - a) / (math.log(1e300) - math.log(1e200)) == pytest.approx(-50.0, rel=1e-9)
    with pytest.raises(ValueError, match="d1, d2 > 0"):
        D.log_f_sf(0, 100, 1.0)


def test_chi2_ppf_edges() -> None:
    assert D.chi2_ppf(0.0, 5) == 0.0
    assert D.chi2_ppf(1.0, 5) == math.inf
    for dof in (1, 10**6):
        for p in (1e-300, 1e-15, 5e-4, 0.5, 0.9995, 1.0 - 2**-52):
            ref = 2.0 * float(sc.gammaincinv(dof / 2.0, p))
            assert _rel(D.chi2_ppf(p, dof), ref) <= 1e-10, (dof, p)
    with pytest.raises(ValueError, match="0 <= p <= 1"):
        D.chi2_ppf(1.5, 3)


def test_poisson_sf_edges() -> None:
    # P(N > 0) = 1 - exp(-mu) ~ mu for the smallest mean the adequacy test passes
    assert _rel(D.poisson_sf(0, 1e-300), 1e-300) <= 1e-12
    assert D.poisson_sf(10**5, 1e-300) == 0.0
    assert _rel(D.poisson_sf(0, 50.0), -math.expm1(-50.0)) <= 1e-15
    with pytest.raises(ValueError, match="k >= 0"):
        D.poisson_sf(-1, 1.0)


@DRAWN
@given(st.one_of(st.floats(-37.0, 8.0), st.sampled_from([-37.0, -5.0, 0.0, 8.0])))
def test_norm_cdf_matches_scipy(x: float) -> None:
    assert _rel(D.norm_cdf(x), float(sc.ndtr(x))) <= 1e-12
    assert _rel(float(D.norm_cdf(np.array([x]))[0]), float(sc.ndtr(x))) <= 1e-12


def test_norm_ppf_matches_scipy() -> None:
    """The residual plot's quantiles ((i + 1/2) / n of up to 4,000 points) and the tails."""
    p = np.concatenate([(np.arange(4000) + 0.5) / 4000, [1e-300, 1e-20, 0.5, 1 - 1e-16]])
    ours, ref = D.norm_ppf(p), sc.ndtri(p)
    assert np.all(np.abs(ours - ref) <= 1e-12 * np.maximum(np.abs(ref), 1e-3))
    assert D.norm_ppf(0.0) == -math.inf and D.norm_ppf(1.0) == math.inf
    assert math.isnan(D.norm_ppf(1.5))


def test_non_convergence_raises(monkeypatch: pytest.MonkeyPatch) -> None:
    """A series cut short raises rather than returning a partial sum."""
    monkeypatch.setattr(D, "_MAX_SERIES_TERMS", 100)
    with pytest.raises(D.ConvergenceError, match="did not converge"):
        D.gamma_p(5e5, 5e5)


def test_identify_path_does_not_import_scipy() -> None:
    """The adequacy module and every function here, called: scipy stays out."""
    code = (
        "import sys, numpy as np, volcal.analysis.adequacy as A\n"
        "from volcal.base import distributions as D\n"
        "A.chi2_interval(10**6); D.log_f_sf(30, 10**6, 1.5); D.poisson_sf(3, 1e-3)\n"
        "D.norm_cdf(-5.0); D.norm_ppf(np.linspace(0.01, 0.99, 5))\n"
        "z = np.random.default_rng(0).standard_normal(500)\n"
        "A.assess_residuals(z, stations=np.arange(500) % 3)\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'scipy'))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout
