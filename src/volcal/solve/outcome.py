"""What a solve returned, whichever solver ran it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class SolveOutcome:
    """What one IPOPT solve returned: x, the objective 0.5 ||r||^2, status and effort."""

    x: np.ndarray
    f: float
    status: str
    success: bool
    iterations: int
    seconds: float
    #: Gauss-Newton steps :func:`polish` took after IPOPT, and the objective it reached
    polish_steps: int = 0
    polish_f: float = float("nan")
