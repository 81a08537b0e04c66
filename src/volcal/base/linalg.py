"""Small numerical kernels shared by the layers (numpy only)."""

from __future__ import annotations

import numpy as np


def scale_columns(
    J: np.ndarray, fixed: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The free columns of J scaled to unit norm: (free indices, their norms, d = 1 / norm,
    J[:, free] * d).

    Rank and null-space decisions are taken on the scaled matrix so that they do not depend
    on the units of the variables; a zero column keeps d = 1."""
    J = np.asarray(J, float)
    fixed = np.zeros(J.shape[1], bool) if fixed is None else np.asarray(fixed, bool)
    free = np.flatnonzero(~fixed)
    Jf = J[:, free]  # a copy: scaled in place (one tall array, not two)
    norms = np.linalg.norm(Jf, axis=0)
    d = 1.0 / np.where(norms == 0, 1.0, norms)
    Jf *= d
    return free, norms, d, Jf
