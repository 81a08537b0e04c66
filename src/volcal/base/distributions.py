"""Distribution functions of the adequacy test and the residual plot (numpy and math only).

Why hand-written rather than scipy.special: importing scipy.special (its array-API layer
touches every lazy numpy submodule, and it parses its docstrings at import) costs 0.1-0.15 s
of every short ``volcal identify``, which needs only a handful of numbers from it: the
chi-square interval of chi2/dof, the F-test tails of the structure tests, a normal and a
Poisson tail for the outlier count, and the normal quantiles of the residual plot.
tests/test_distributions.py checks every function here against scipy.special (the
independent truth) over the ranges the callers use.

The methods are the standard ones (Numerical Recipes 3rd ed. 6.2 and 6.4; DiDonato & Morris
1986 for the split between series and continued fraction):

* the regularised incomplete gamma ``P(a, x)``: its power series up to
  ``x = a + sqrt(a) + 1`` (summed in numpy blocks: a bounded number of terms, about
  ``10 sqrt(a)`` near ``x = a``, each a ratio ``x / (a + j)``), else the continued fraction
  of ``Q(a, x)`` (modified Lentz), in O(sqrt(a)) iterations there;
* the regularised incomplete beta ``I_x(a, b)`` in log form: its continued fraction
  (modified Lentz) for ``x < (a + 1) / (a + b + 2)``, else ``1 - I_{1-x}(b, a)``; the far
  tail therefore always comes from the fast side and keeps its log far below the float range;
* the prefactors ``x^a e^-x / Gamma(a + 1)`` and ``x^a (1 - x)^b / B(a, b)`` written with
  ``log1p(t) - t`` and Stirling's series, so that 10^6 degrees of freedom lose no digits to
  the cancellation of terms of size ``a log a``;
* the inverse of ``P`` by Newton steps on ``log P`` (or ``log Q`` above the median) from a
  Wilson-Hilferty start, kept inside a bracket by bisection.

A series or continued fraction that does not converge within its bound raises
:class:`ConvergenceError` instead of returning a wrong number.
"""

from __future__ import annotations

import math
from typing import overload

import numpy as np

__all__ = [
    "ConvergenceError",
    "chi2_ppf",
    "gamma_p",
    "gamma_p_inv",
    "gamma_q",
    "log_beta_inc",
    "log_f_sf",
    "norm_cdf",
    "norm_ppf",
    "poisson_sf",
]

_EPS = 2.0**-53
_TINY = 1e-300  # the modified Lentz method's stand-in for a zero denominator
_LOG_2PI_HALF = 0.5 * math.log(2.0 * math.pi)
_MAX_SERIES_TERMS = 50_000_000  # P's series needs ~9 sqrt(a) + 4 sqrt(a): a up to ~10^12


class ConvergenceError(ArithmeticError):
    """A series or continued fraction did not converge within its iteration bound."""


# --------------------------------------------------------------------------------------
# normal distribution


@overload
def norm_cdf(x: float) -> float: ...
@overload
def norm_cdf(x: np.ndarray) -> np.ndarray: ...
def norm_cdf(x: float | np.ndarray) -> float | np.ndarray:
    """The standard normal distribution function ``Phi(x)`` (x in standard deviations),
    elementwise; ``0.5 erfc(-x / sqrt 2)``, accurate in the lower tail."""
    if np.ndim(x) == 0:
        return 0.5 * math.erfc(-float(x) / math.sqrt(2.0))
    arr = np.asarray(x, float)
    out = np.frompyfunc(lambda v: 0.5 * math.erfc(-v / math.sqrt(2.0)), 1, 1)(arr)
    return np.asarray(out, float)


@overload
def norm_ppf(p: float) -> float: ...
@overload
def norm_ppf(p: np.ndarray) -> np.ndarray: ...
def norm_ppf(p: float | np.ndarray) -> float | np.ndarray:
    """The standard normal quantile ``Phi^-1(p)`` (in standard deviations) of probabilities
    ``p``, elementwise: -inf at 0, +inf at 1, nan outside [0, 1].

    ``statistics.NormalDist().inv_cdf`` (Wichura's AS 241, accurate to about 1e-16) does
    the work; imported here, not at the top, as only the residual plot needs it."""
    from statistics import NormalDist

    inv = NormalDist().inv_cdf

    def one(v: float) -> float:
        if 0.0 < v < 1.0:
            return inv(v)
        if v == 0.0:
            return -math.inf
        if v == 1.0:
            return math.inf
        return math.nan

    if np.ndim(p) == 0:
        return one(float(p))
    arr = np.asarray(p, float)
    return np.asarray(np.frompyfunc(one, 1, 1)(arr), float)


def _norm_ppf_rough(p: float) -> float:
    """A normal quantile to about 5e-4 (Abramowitz & Stegun 26.2.23): a start value only,
    without importing statistics on the adequacy path."""
    q = min(p, 1.0 - p)
    t = math.sqrt(-2.0 * math.log(q))
    z = t - (2.515517 + 0.802853 * t + 0.010328 * t * t) / (
        1.0 + 1.432788 * t + 0.189269 * t * t + 0.001308 * t**3
    )
    return -z if p < 0.5 else z


# --------------------------------------------------------------------------------------
# accurate pieces of the prefactors


def _log1pmx(t: float) -> float:
    """``log(1 + t) - t`` without the cancellation near t = 0 (t > -1)."""
    if abs(t) > 0.5:
        return math.log1p(t) - t
    # log(1 + t) = 2 atanh(y), y = t / (2 + t), |y| <= 1/3: 2y - t = -t^2 / (2 + t)
    y = t / (2.0 + t)
    y2 = y * y
    s, term, k = 0.0, y * y2, 3
    while abs(term) > 1e-18 * abs(s) or s == 0.0:
        s += term / k
        term *= y2
        k += 2
        if term == 0.0:
            break
    return -t * t / (2.0 + t) + 2.0 * s


def _stirling_error(a: float) -> float:
    """``lgamma(a) - ((a - 1/2) log a - a + log(2 pi) / 2)``: Stirling's series for
    a >= 10 (its terms then fall below 1e-16 by the seventh), the definition below."""
    if a < 10.0:
        return math.lgamma(a) - ((a - 0.5) * math.log(a) - a + _LOG_2PI_HALF)
    r = 1.0 / (a * a)
    return (
        1.0
        / a
        * (
            1.0 / 12.0
            - r
            * (
                1.0 / 360.0
                - r
                * (
                    1.0 / 1260.0
                    - r * (1.0 / 1680.0 - r * (1.0 / 1188.0 - r * (691.0 / 360360.0 - r / 156.0)))
                )
            )
        )
    )


def _log_gamma_factor(a: float, x: float) -> float:
    """``log(x^a e^-x / Gamma(a + 1))`` for a > 0, x > 0, written as
    ``a (log1p(t) - t) - log(2 pi a) / 2 - stirling_error(a)`` with t = (x - a) / a so that
    large a loses no digits to the cancellation of ``a log x`` against ``lgamma(a + 1)``."""
    t = (x - a) / a
    if t < -0.5:  # x well below a: log(x / a) from the logs (x may be near the underflow)
        lmx = (math.log(x) - math.log(a)) - t
    else:
        lmx = _log1pmx(t)
    return a * lmx - 0.5 * math.log(2.0 * math.pi * a) - _stirling_error(a)


def _log_beta(a: float, b: float) -> float:
    """``log B(a, b)`` for a, b > 0, from Stirling's form with the large terms combined
    analytically (``(a - 1/2) log a - (a + b - 1/2) log(a + b)`` =
    ``-(a - 1/2) log1p(b / a) - b log(a + b)``), accurate when a or b is ~10^6."""
    if a < b:
        a, b = b, a
    if a < 10.0:
        return math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b)
    return (
        _LOG_2PI_HALF
        - 0.5 * math.log(b)
        + b * (math.log(b) - math.log(a + b))
        - (a - 0.5) * math.log1p(b / a)
        + _stirling_error(a)
        + _stirling_error(b)
        - _stirling_error(a + b)
    )


# --------------------------------------------------------------------------------------
# regularised incomplete gamma


def _gamma_series(a: float, x: float) -> float:
    """``sum_{n>=0} x^n / ((a + 1) ... (a + n))`` (so that P(a, x) = that times
    x^a e^-x / Gamma(a + 1)), in numpy blocks of cumulative products.  Called for
    x <= a + sqrt(a) + 1: the terms peak at n ~ x - a and then fall like
    exp(-n^2 / 2x), so about sqrt(a) + 9 sqrt(x) terms reach double precision."""
    total, last, n = 1.0, 1.0, 0
    block = 64
    while n < _MAX_SERIES_TERMS:
        j = np.arange(n + 1, n + block + 1, dtype=float)
        terms = last * np.cumprod(x / (a + j))
        total += float(terms.sum())
        last = float(terms[-1])
        n += block
        r = x / (a + n + 1.0)  # the ratio of every later term to the one before: a bound
        if r < 1.0 and last * r / (1.0 - r) <= _EPS * 0.25 * total:
            return total
        block = min(2 * block, 1 << 16)
    raise ConvergenceError(f"the series of P(a, x) did not converge (a = {a:g}, x = {x:g})")


def _lentz(d: float, c: float, an: float, bn: float) -> tuple[float, float, float]:
    """One term a_n / (b_n + ...) of a continued fraction by the modified Lentz method:
    the new (D, C) and the factor the convergent is multiplied by (a zero denominator
    replaced by a tiny number, as the method does)."""
    d = an * d + bn
    if abs(d) < _TINY:
        d = _TINY
    c = bn + an / c
    if abs(c) < _TINY:
        c = _TINY
    d = 1.0 / d
    return d, c, d * c


def _gamma_cf(a: float, x: float) -> float:
    """The continued fraction of Q(a, x) (Numerical Recipes 6.2.7, modified Lentz):
    Q = x^a e^-x / Gamma(a) times the returned value.  Called for x > a + sqrt(a) + 1,
    where it converges in O(sqrt(a)) iterations (its bound: 1000 + 20 sqrt(a))."""
    max_iter = 1000 + int(20.0 * math.sqrt(a))
    b = x + 1.0 - a
    c = 1.0 / _TINY
    d = 1.0 / b
    h = d
    for i in range(1, max_iter + 1):
        b += 2.0
        d, c, delta = _lentz(d, c, -i * (i - a), b)
        h *= delta
        if abs(delta - 1.0) <= _EPS:
            return h
    raise ConvergenceError(
        f"the continued fraction of Q(a, x) did not converge (a = {a:g}, x = {x:g})"
    )


def _log_gamma_pq(a: float, x: float) -> tuple[float, float]:
    """``(log P(a, x), log Q(a, x))``, each accurate where it is the small one."""
    if not a > 0.0 or math.isnan(x):
        raise ValueError(f"the incomplete gamma function needs a > 0 and a number x (a = {a})")
    if x <= 0.0:
        return -math.inf, 0.0
    if math.isinf(x):
        return 0.0, -math.inf
    log_fac = _log_gamma_factor(a, x)
    if x <= a + math.sqrt(a) + 1.0:
        log_p = log_fac + math.log(_gamma_series(a, x))
        return log_p, math.log1p(-math.exp(log_p))
    log_q = log_fac + math.log(a) + math.log(_gamma_cf(a, x))
    return math.log1p(-math.exp(log_q)), log_q


def gamma_p(a: float, x: float) -> float:
    """The regularised lower incomplete gamma function ``P(a, x)`` (a > 0, x >= 0)."""
    return math.exp(_log_gamma_pq(float(a), float(x))[0])


def gamma_q(a: float, x: float) -> float:
    """The regularised upper incomplete gamma function ``Q(a, x) = 1 - P(a, x)``."""
    return math.exp(_log_gamma_pq(float(a), float(x))[1])


def poisson_sf(k: int, mu: float) -> float:
    """``P(N > k)`` for a Poisson count N of mean ``mu`` > 0 (k >= 0 an integer): the
    regularised lower incomplete gamma ``P(k + 1, mu)`` (scipy.special.pdtrc)."""
    if k < 0:
        raise ValueError(f"poisson_sf needs a count k >= 0 (got {k})")
    if not mu > 0.0:
        raise ValueError(f"poisson_sf needs a mean mu > 0 (got {mu})")
    return gamma_p(int(k) + 1.0, float(mu))


def gamma_p_inv(a: float, p: float) -> float:
    """The x with ``P(a, x) = p`` (a > 0, 0 <= p <= 1; scipy.special.gammaincinv).

    Newton steps on ``log P`` (``log Q`` above the median, where 1 - p carries the
    information) from a Wilson-Hilferty start, each kept inside the current bracket of the
    root (bisection otherwise); converged when a step moves x by less than 4 ulp."""
    a, p = float(a), float(p)
    if not a > 0.0 or not 0.0 <= p <= 1.0:
        raise ValueError(f"gamma_p_inv needs a > 0 and 0 <= p <= 1 (a = {a}, p = {p})")
    if p == 0.0:
        return 0.0
    if p == 1.0:
        return math.inf
    upper = p > 0.5
    target = math.log1p(-p) if upper else math.log(p)
    # start: Wilson-Hilferty (the cube root of a gamma variable is nearly normal); in the
    # lower tail of small a, P ~ x^a / Gamma(a + 1) instead
    z = _norm_ppf_rough(p)
    w = 1.0 - 1.0 / (9.0 * a) + z / (3.0 * math.sqrt(a))
    x_small = math.exp((math.log(p) + math.lgamma(a + 1.0)) / a) if not upper else 0.0
    if w > 0.2:
        x = a * w**3
        if not upper and x_small < 0.2 * a:
            x = x_small
    elif not upper:
        x = x_small
    else:
        x = a + 4.0 * math.sqrt(a) + 1.0
    if x == 0.0 or x < 1e-300:
        # P(a, x) ~ x^a / Gamma(a + 1) all the way down: the root lies at or below the
        # smallest normal float
        return x
    lo, hi = 0.0, math.inf
    for _ in range(200):
        log_p, log_q = _log_gamma_pq(a, x)
        f = (log_q - target) if upper else (log_p - target)
        if f == 0.0:
            return x
        # P rises with x, Q falls: is the root above x?
        above = (f > 0.0) if upper else (f < 0.0)
        if above:
            lo = x
        else:
            hi = x
        # d log P / dx = pdf / P, d log Q / dx = -pdf / Q; pdf = a e^log_fac / x
        log_pdf = _log_gamma_factor(a, x) + math.log(a) - math.log(x)
        slope = -math.exp(log_pdf - log_q) if upper else math.exp(log_pdf - log_p)
        step = -f / slope if slope != 0.0 and math.isfinite(slope) else math.nan
        if abs(step) <= 4.0 * _EPS * x:  # before the bracket test: a step below 1 ulp
            return x + step
        x_new = x + step
        if not (lo < x_new < hi) or not math.isfinite(x_new):  # bisect the bracket
            if math.isinf(hi):
                x_new = 2.0 * lo
            elif lo == 0.0:
                x_new = hi / 16.0
            else:
                x_new = math.sqrt(lo * hi) if hi > 4.0 * lo else 0.5 * (lo + hi)
        if abs(x_new - x) <= 4.0 * _EPS * x:
            return x_new
        x = x_new
    raise ConvergenceError(f"the inverse of P(a, x) did not converge (a = {a:g}, p = {p:g})")


def chi2_ppf(p: float, dof: float) -> float:
    """The ``p`` quantile of the chi-square distribution with ``dof`` > 0 degrees of
    freedom: ``2 gamma_p_inv(dof / 2, p)`` (scipy.stats.chi2.ppf)."""
    return 2.0 * gamma_p_inv(0.5 * float(dof), p)


# --------------------------------------------------------------------------------------
# regularised incomplete beta and the F distribution


def _beta_cf(a: float, b: float, x: float, y: float) -> float:
    """The continued fraction of I_x(a, b) (Numerical Recipes 6.4.5, modified Lentz):
    I_x(a, b) = x^a (1 - x)^b / (a B(a, b)) times the returned value; y = 1 - x.  Called
    for x < (a + 1) / (a + b + 2), where it needs O(sqrt(max(a, b))) iterations at most."""
    max_iter = 1000 + int(20.0 * math.sqrt(max(a, b)))
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c = 1.0
    # 1 - (a + b) x / (a + 1) is small near the branch point x ~ (a + 1) / (a + b + 2):
    # from 1 - x there (a cancellation of terms of size b, not of size a)
    d = (1.0 - b + qab * y) / qap if x > 0.5 else 1.0 - qab * x / qap
    if abs(d) < _TINY:
        d = _TINY
    d = 1.0 / d
    h = d
    for m in range(1, max_iter + 1):
        m2 = 2 * m
        d, c, even = _lentz(d, c, m * (b - m) * x / ((qam + m2) * (a + m2)), 1.0)
        h *= even
        d, c, delta = _lentz(d, c, -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2)), 1.0)
        h *= delta
        if abs(delta - 1.0) <= _EPS:
            return h
    raise ConvergenceError(
        f"the continued fraction of I_x(a, b) did not converge (a = {a:g}, b = {b:g}, x = {x:g})"
    )


def _log_beta_inc(a: float, b: float, x: float, log_x: float, log_1mx: float) -> float:
    """``log I_x(a, b)`` given x and the accurate logs of x and 1 - x (0 < x < 1)."""

    def log_direct(a: float, b: float, x: float, log_x: float, log_1mx: float) -> float:
        log_fac = a * log_x + b * log_1mx - _log_beta(a, b) - math.log(a)
        return log_fac + math.log(_beta_cf(a, b, x, math.exp(log_1mx)))

    if x < (a + 1.0) / (a + b + 2.0):
        return log_direct(a, b, x, log_x, log_1mx)
    # the symmetry I_x(a, b) = 1 - I_{1-x}(b, a): here the fraction converges fast and
    # I_x >= ~1/2, so the log of the complement is accurate
    return math.log1p(-math.exp(log_direct(b, a, -math.expm1(log_x), log_1mx, log_x)))


def log_beta_inc(a: float, b: float, x: float) -> float:
    """``log I_x(a, b)``, the log of the regularised incomplete beta function
    (a, b > 0, 0 <= x <= 1), finite far below the smallest float's log."""
    a, b, x = float(a), float(b), float(x)
    if not (a > 0.0 and b > 0.0 and 0.0 <= x <= 1.0):
        raise ValueError(f"log_beta_inc needs a, b > 0 and 0 <= x <= 1 (a={a}, b={b}, x={x})")
    if x == 0.0:
        return -math.inf
    if x == 1.0:
        return 0.0
    return _log_beta_inc(a, b, x, math.log(x), math.log1p(-x))


def log_f_sf(d1: float, d2: float, f: float) -> float:
    """The natural log of the F distribution's survival function ``P(F > f)`` with
    ``d1``, ``d2`` > 0 degrees of freedom (log of scipy.special.fdtrc): 0 at f <= 0, -inf
    at f = inf, finite (and accurate to about 1e-12 relative) for every finite f, also far
    beyond where the probability itself underflows.

    P(F > f) = I_x(d2 / 2, d1 / 2) with x = d2 / (d2 + d1 f) = 1 / (1 + q), q = d1 f / d2;
    log x = -log1p(q) and log(1 - x) = log q - log1p(q) from q directly."""
    d1, d2, f = float(d1), float(d2), float(f)
    if not (d1 > 0.0 and d2 > 0.0) or math.isnan(f):
        raise ValueError(f"log_f_sf needs d1, d2 > 0 and a number f (d1={d1}, d2={d2}, f={f})")
    if f <= 0.0:
        return 0.0
    if math.isinf(f):
        return -math.inf
    log_q = math.log(d1) + math.log(f) - math.log(d2)
    q = math.exp(log_q) if log_q < 700.0 else math.inf
    if q <= 1e300:
        log1p_q = math.log1p(q)
        x = 1.0 / (1.0 + q)
    else:  # log1p(q) = log q + log1p(1 / q)
        log1p_q = log_q + math.log1p(math.exp(-log_q))
        x = math.exp(-log1p_q)
    log_x, log_1mx = -log1p_q, log_q - log1p_q
    # x == 0 (q beyond the float range) takes the direct fraction, which is then 1
    return _log_beta_inc(0.5 * d2, 0.5 * d1, x, log_x, log_1mx)
