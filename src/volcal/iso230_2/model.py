"""Paper 003's continuous model of the positional deviation, fitted by generalised least squares.

The mean deviations x̄_i at the targets P_i (one curve per approach direction) are fitted by a
polynomial Δ(P) = a_0 + a_1 P + ... + a_d P^d (paper eq. 2, cubic by default).  Their
covariance (paper eqs. 7-10) is

    U(x) = diag(u²(x̄_i)) + u²(δ) 1 1ᵀ  [+ u²(ε) (P - P_ref)(P - P_ref)ᵀ]

with u(x̄_i) the type A standard uncertainty of each mean (eq. 10: s_i / sqrt(n); by default
volcal uses GUM Supplement 1's sqrt((n-1)/(n-3)) s_i / sqrt(n), see
:func:`type_a_uncertainty`) and δ the
error of the measuring instrument, the same for every reading (fully correlated), taken
from its maximum permissible error as u(δ) = MPE / sqrt(3) (rectangular distribution).  The
optional term in brackets (not in the paper) is a length-proportional instrument error
ε (P - P_ref), e.g. an interferometer's ppm specification, zeroed at P_ref.  Both
directions are fitted jointly: δ (and ε) is common to the two directions, so the
covariance of the bidirectional mean curve is exact.

The GLS estimate is β = (Xᵀ V⁻¹ X)⁻¹ Xᵀ V⁻¹ y with covariance (Xᵀ V⁻¹ X)⁻¹, and the
expanded uncertainty of the deviation at any P is U(P) = k sqrt(g(P)ᵀ cov g(P)),
g(P) = (1, P, ..., P^d).

Worth knowing: the instrument terms lie in the column space of X (a constant, a straight
line), so the GLS estimate equals the weighted least-squares estimate with weights
1/u²(x̄_i), and the covariance is the WLS covariance plus u²(δ) on the constant term (plus
u²(ε) c cᵀ, c = (-P_ref, 1, 0, ...)).  The instrument error therefore does not move the
fitted curve; it widens the band by a constant in quadrature.  The code does the general
GLS (the tests check the identity).

Internally the polynomial is built on the normalised variable t = (P - centre) / half_range
for conditioning; :meth:`PolynomialModel.raw` converts to coefficients of powers of P.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import comb

import numpy as np

__all__ = [
    "gls",
    "PolynomialModel",
    "fit_polynomial",
    "fit_axis_model",
    "to_raw_matrix",
    "type_a_uncertainty",
    "TYPE_A_METHODS",
]


def gls(X, y, V):
    """Generalised least squares: returns (beta, cov_beta, chi2).

    Whitens with the Cholesky factor of V and solves by QR.  ``chi2`` is the whitened
    residual sum of squares (Xβ - y)ᵀ V⁻¹ (Xβ - y).
    """
    X = np.asarray(X, dtype=float)
    y = np.asarray(y, dtype=float)
    V = np.asarray(V, dtype=float)
    try:
        L = np.linalg.cholesky(V)
    except np.linalg.LinAlgError:
        raise ValueError(
            "the covariance matrix of the mean deviations is not positive "
            "definite (a zero standard uncertainty?)"
        ) from None
    # (np.linalg.solve on the small triangular factors: much faster than
    # scipy's solve_triangular at these sizes, and as accurate)
    Xw = np.linalg.solve(L, X)
    yw = np.linalg.solve(L, y)
    Q, R = np.linalg.qr(Xw)
    d = np.abs(np.diag(R))
    if d.size == 0 or d.min() <= 1e-12 * d.max():
        raise ValueError(
            "the design matrix is rank deficient: too few distinct target "
            "positions for the polynomial degree"
        )
    beta = np.linalg.solve(R, Q.T @ yw)
    Rinv = np.linalg.solve(R, np.eye(R.shape[0]))
    cov = Rinv @ Rinv.T
    r = yw - Xw @ beta
    return beta, cov, float(r @ r)


def to_raw_matrix(degree: int, center: float, half_range: float) -> np.ndarray:
    """T with a = T α: α are coefficients of powers of t = (P - center)/half_range, a of P."""
    p = degree + 1
    T = np.zeros((p, p))
    for k in range(p):
        for l in range(k + 1):
            T[l, k] = comb(k, l) * (-center) ** (k - l) / half_range**k
    return T


TYPE_A_METHODS = ("gum-s1", "paper")


def type_a_uncertainty(readings, floor: float = 0.0, method: str = "gum-s1") -> np.ndarray:
    """Standard uncertainty of the mean of each row of ``readings`` (m x n), floored.

    ``"paper"``: u(x̄_i) = s_i / sqrt(n), paper 003 eq. 10 (GUM 4.2.3).
    ``"gum-s1"``: u(x̄_i) = sqrt((n-1)/(n-3)) s_i / sqrt(n), the standard deviation of the
    scaled and shifted t-distribution that JCGM 101:2008 (GUM Supplement 1, 6.4.9) assigns
    to a mean of n readings; needs n >= 4.  With n = 5 the plain s_i / sqrt(n) makes the
    weights 1/u² too large on average (E[σ²/s²] = (n-1)/(n-3) = 2) and the k = 2 band of the
    fit covered the truth in only about 82 % of simulated repetitions; see docs/iso230_2.md.
    """
    readings = np.asarray(readings, dtype=float)
    n = readings.shape[1]
    if n < 2:
        raise ValueError("at least 2 readings per mean are needed for a type A uncertainty")
    u = readings.std(axis=1, ddof=1) / np.sqrt(n)
    if method == "gum-s1":
        if n < 4:
            raise ValueError(
                f"the GUM-S1 type A uncertainty needs n >= 4 readings per mean, "
                f"got {n}; use the paper's s/sqrt(n) instead"
            )
        u = u * np.sqrt((n - 1) / (n - 3))
    elif method != "paper":
        raise ValueError(f"unknown type A method {method!r}; expected one of {TYPE_A_METHODS}")
    return np.maximum(u, floor)


@dataclass(frozen=True)
class PolynomialModel:
    """K polynomial curves of degree d over one position variable, with joint covariance.

    ``beta`` stacks the K coefficient vectors in the normalised basis (powers of t);
    ``cov`` is their (K p x K p) covariance.  Positions and values are in the units of the
    data that were fitted (internal units: mm or rad).
    """

    labels: tuple[str, ...]
    degree: int
    center: float
    half_range: float
    lower: float
    upper: float
    positions: np.ndarray  # the target positions fitted
    means: np.ndarray  # (K, m) mean deviations fitted
    u_means: np.ndarray  # (K, m) their type A standard uncertainties
    u_instrument: float  # std of the constant (fully correlated) instrument error
    u_scale: float  # relative std of the length-proportional instrument error
    reference: float  # P_ref of the length-proportional term
    beta: np.ndarray
    cov: np.ndarray
    chi2: tuple[float, ...]  # per curve, with its own block of the covariance
    dof: int  # per curve: m - (d + 1)

    @property
    def p(self) -> int:
        return self.degree + 1

    def basis(self, x) -> np.ndarray:
        t = (np.atleast_1d(np.asarray(x, dtype=float)) - self.center) / self.half_range
        return t[:, None] ** np.arange(self.p)

    def combination(self, which: str) -> np.ndarray:
        """Weights over the curves for ``which``: a label, 'bidir' (mean of up and down) or
        'reversal' (up - down)."""
        w = np.zeros(len(self.labels))
        if which in self.labels:
            w[self.labels.index(which)] = 1.0
        elif which == "bidir" and set(self.labels) == {"up", "down"}:
            w[:] = 0.5
        elif which == "reversal" and set(self.labels) == {"up", "down"}:
            w[self.labels.index("up")], w[self.labels.index("down")] = 1.0, -1.0
        else:
            raise ValueError(f"unknown curve {which!r}; have {self.labels}")
        return w

    def _G(self, x, which) -> np.ndarray:
        return np.kron(self.combination(which)[None, :], self.basis(x))

    def value(self, x, which: str | None = None) -> np.ndarray:
        """Fitted deviation at positions x."""
        return self._G(x, which or self.labels[0]) @ self.beta

    def std(self, x, which: str | None = None) -> np.ndarray:
        """Standard uncertainty of the fitted deviation at x: sqrt(g(x)ᵀ cov g(x))."""
        G = self._G(x, which or self.labels[0])
        return np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", G, self.cov, G), 0.0))

    def expanded(self, x, which: str | None = None, k: float = 2.0) -> np.ndarray:
        """Expanded uncertainty U(x) = k u(x)."""
        return k * self.std(x, which)

    def raw(self, which: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Coefficients a_0..a_d of powers of P (a_k in value-unit / position-unit^k) and
        their covariance."""
        T = to_raw_matrix(self.degree, self.center, self.half_range)
        W = np.kron(self.combination(which or self.labels[0])[None, :], T)
        return W @ self.beta, W @ self.cov @ W.T


def _fit_curves(
    labels, positions, means, u_means, *, degree, u_instrument, u_scale, reference
) -> PolynomialModel:
    P = np.asarray(positions, dtype=float)
    means = np.atleast_2d(np.asarray(means, dtype=float))
    u_means = np.atleast_2d(np.asarray(u_means, dtype=float))
    K, m = means.shape
    if P.shape != (m,) or u_means.shape != (K, m):
        raise ValueError("positions, means and u_means do not match in size")
    if degree < 0 or int(degree) != degree:
        raise ValueError(f"degree must be an integer >= 0, got {degree}")
    degree = int(degree)
    if np.unique(P).size < degree + 1:
        raise ValueError(
            f"a polynomial of degree {degree} needs at least {degree + 1} "
            f"distinct target positions, got {np.unique(P).size}"
        )
    if np.any(~np.isfinite(u_means)) or np.any(u_means <= 0.0):
        raise ValueError(
            "every mean needs a positive standard uncertainty; a target whose "
            "readings are all equal has s_i = 0 (give the reading resolution "
            "as a floor)"
        )
    if u_instrument < 0 or u_scale < 0:
        raise ValueError("instrument uncertainties must be >= 0")
    lower, upper = float(P.min()), float(P.max())
    center = 0.5 * (lower + upper)
    half = 0.5 * (upper - lower) or 1.0
    ref = lower if reference is None else float(reference)
    t = (P - center) / half
    B = t[:, None] ** np.arange(degree + 1)
    X = np.kron(np.eye(K), B)
    y = means.reshape(-1)
    one = np.ones(K * m)
    d = np.tile(P - ref, K)
    V = (
        np.diag(u_means.reshape(-1) ** 2)
        + u_instrument**2 * np.outer(one, one)
        + u_scale**2 * np.outer(d, d)
    )
    beta, cov, _ = gls(X, y, V)
    chi2 = []
    for c in range(K):
        sl = slice(c * m, (c + 1) * m)
        r = X[sl] @ beta - y[sl]
        chi2.append(float(r @ np.linalg.solve(V[sl, sl], r)))
    return PolynomialModel(
        labels=tuple(labels),
        degree=degree,
        center=center,
        half_range=half,
        lower=lower,
        upper=upper,
        positions=P.copy(),
        means=means.copy(),
        u_means=u_means.copy(),
        u_instrument=float(u_instrument),
        u_scale=float(u_scale),
        reference=ref,
        beta=beta,
        cov=cov,
        chi2=tuple(chi2),
        dof=m - (degree + 1),
    )


def fit_polynomial(
    positions,
    means,
    u_means,
    *,
    degree: int = 3,
    u_instrument: float = 0.0,
    u_scale: float = 0.0,
    reference: float | None = None,
    label: str = "fit",
) -> PolynomialModel:
    """Fit one curve: the paper's model for one approach direction.

    ``means`` are the mean deviations x̄_i at ``positions`` P_i, ``u_means`` their type A
    standard uncertainties u(x̄_i); ``u_instrument`` the standard uncertainty of the
    constant instrument error (MPE / sqrt(3)); ``u_scale`` the relative standard
    uncertainty of a length-proportional instrument error zeroed at ``reference`` (default:
    the smallest position).  All in one consistent unit system.
    """
    return _fit_curves(
        (label,),
        positions,
        [means],
        [u_means],
        degree=degree,
        u_instrument=u_instrument,
        u_scale=u_scale,
        reference=reference,
    )


def fit_axis_model(
    targets,
    up,
    down,
    *,
    degree: int = 3,
    u_instrument: float = 0.0,
    u_scale: float = 0.0,
    reference: float | None = None,
    u_floor: float = 0.0,
    type_a: str = "gum-s1",
) -> PolynomialModel:
    """Fit both approach directions from the raw deviations ``up``, ``down`` (m x n).

    The means are averages over the cycles; their standard uncertainties come from
    :func:`type_a_uncertainty` (``type_a``: "gum-s1" or "paper"), floored at ``u_floor``.
    """
    up = np.asarray(up, dtype=float)
    down = np.asarray(down, dtype=float)
    means = np.vstack([up.mean(axis=1), down.mean(axis=1)])
    u = np.vstack(
        [type_a_uncertainty(up, u_floor, type_a), type_a_uncertainty(down, u_floor, type_a)]
    )
    return _fit_curves(
        ("up", "down"),
        targets,
        means,
        u,
        degree=degree,
        u_instrument=u_instrument,
        u_scale=u_scale,
        reference=reference,
    )
