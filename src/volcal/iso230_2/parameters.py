"""The ISO 230-2:2014 positioning parameters of one axis (clause 3 of the standard).

Notation: i = 1..m target index, j = 1..n cycle index, up/down = approach in the positive /
negative direction, x_ij = P_ij - P_i the positional deviation (actual minus target).

======================  ==============================================================
parameter               definition (as computed here)
======================  ==============================================================
mean_up[i]              x̄_i↑ = (1/n) Σ_j x_ij↑        (mean over the n cycles, per direction)
s_up[i]                 s_i↑ = sqrt( Σ_j (x_ij↑ - x̄_i↑)² / (n - 1) )
mean_bidir[i]           x̄_i = (x̄_i↑ + x̄_i↓) / 2
B_i[i]                  B_i = x̄_i↑ - x̄_i↓            (signed)
B                       max_i |B_i|
B_mean                  B̄ = (1/m) Σ_i B_i             (signed mean, not the mean of |B_i|)
R_up_i[i]               R_i↑ = 4 s_i↑
R_i[i]                  R_i = max( 2 s_i↑ + 2 s_i↓ + |B_i| ; R_i↑ ; R_i↓ )
R_up, R_down, R         max_i R_i↑, max_i R_i↓, max_i R_i
E_up                    max_i x̄_i↑ - min_i x̄_i↑
E                       max_i(x̄_i↑, x̄_i↓) - min_i(x̄_i↑, x̄_i↓)  (extremes over both directions
                        and all targets, possibly from different directions and targets)
M                       max_i x̄_i - min_i x̄_i
A_up                    max_i(x̄_i↑ + 2 s_i↑) - min_i(x̄_i↑ - 2 s_i↑)
A                       max_i(x̄_i↑ + 2 s_i↑, x̄_i↓ + 2 s_i↓) - min_i(x̄_i↑ - 2 s_i↑, x̄_i↓ - 2 s_i↓)
======================  ==============================================================

The functions are unit-agnostic: the parameters come out in the unit of the deviations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["IsoParameters", "iso230_2_parameters", "SCALAR_PARAMETERS"]

# scalar parameters of the axis: (attribute, report name stem, description)
SCALAR_PARAMETERS = [
    ("E_up", "E_up", "unidirectional systematic positional deviation, positive approach E↑"),
    ("E_down", "E_down", "unidirectional systematic positional deviation, negative approach E↓"),
    ("E", "E_bidir", "bidirectional systematic positional deviation E"),
    ("M", "M", "range of the mean bidirectional positional deviation M"),
    ("B", "B", "reversal value of the axis B = max |B_i|"),
    ("B_mean", "B_mean", "mean reversal value of the axis B̄ = mean B_i"),
    ("R_up", "R_up", "unidirectional repeatability of positioning R↑ = max R_i↑"),
    ("R_down", "R_down", "unidirectional repeatability of positioning R↓ = max R_i↓"),
    ("R", "R_bidir", "bidirectional repeatability of positioning R = max R_i"),
    ("A_up", "A_up", "unidirectional accuracy of positioning A↑"),
    ("A_down", "A_down", "unidirectional accuracy of positioning A↓"),
    ("A", "A_bidir", "bidirectional accuracy of positioning A"),
]


@dataclass(frozen=True)
class IsoParameters:
    """ISO 230-2 parameters; arrays are per target (length m), the rest are axis values."""

    n: int
    m: int
    mean_up: np.ndarray
    mean_down: np.ndarray
    s_up: np.ndarray
    s_down: np.ndarray
    mean_bidir: np.ndarray
    B_i: np.ndarray
    R_up_i: np.ndarray
    R_down_i: np.ndarray
    R_i: np.ndarray
    B: float
    B_mean: float
    R_up: float
    R_down: float
    R: float
    E_up: float
    E_down: float
    E: float
    M: float
    A_up: float
    A_down: float
    A: float


def iso230_2_parameters(up, down) -> IsoParameters:
    """ISO 230-2:2014 parameters from the deviations ``up[i, j]``, ``down[i, j]`` (m x n).

    Row i is target i, column j is cycle j; both directions need the same n >= 2.
    """
    up = np.asarray(up, dtype=float)
    down = np.asarray(down, dtype=float)
    if up.ndim != 2 or up.shape != down.shape:
        raise ValueError(
            f"up and down must be m x n arrays of the same shape, got {up.shape} and {down.shape}"
        )
    m, n = up.shape
    if n < 2:
        raise ValueError("at least 2 cycles are needed to estimate s_i")
    mean_up = up.mean(axis=1)  # mean over the cycles j, per target i
    mean_down = down.mean(axis=1)
    s_up = up.std(axis=1, ddof=1)  # 1/(n-1)
    s_down = down.std(axis=1, ddof=1)
    B_i = mean_up - mean_down
    R_up_i = 4.0 * s_up
    R_down_i = 4.0 * s_down
    R_i = np.maximum.reduce([2.0 * s_up + 2.0 * s_down + np.abs(B_i), R_up_i, R_down_i])
    mean_bidir = 0.5 * (mean_up + mean_down)
    both = np.concatenate([mean_up, mean_down])
    hi = np.concatenate([mean_up + 2.0 * s_up, mean_down + 2.0 * s_down])
    lo = np.concatenate([mean_up - 2.0 * s_up, mean_down - 2.0 * s_down])
    return IsoParameters(
        n=n,
        m=m,
        mean_up=mean_up,
        mean_down=mean_down,
        s_up=s_up,
        s_down=s_down,
        mean_bidir=mean_bidir,
        B_i=B_i,
        R_up_i=R_up_i,
        R_down_i=R_down_i,
        R_i=R_i,
        B=float(np.max(np.abs(B_i))),
        B_mean=float(np.mean(B_i)),
        R_up=float(R_up_i.max()),
        R_down=float(R_down_i.max()),
        R=float(R_i.max()),
        E_up=float(mean_up.max() - mean_up.min()),
        E_down=float(mean_down.max() - mean_down.min()),
        E=float(both.max() - both.min()),
        M=float(mean_bidir.max() - mean_bidir.min()),
        A_up=float((mean_up + 2.0 * s_up).max() - (mean_up - 2.0 * s_up).min()),
        A_down=float((mean_down + 2.0 * s_down).max() - (mean_down - 2.0 * s_down).min()),
        A=float(hi.max() - lo.min()),
    )
