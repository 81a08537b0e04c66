"""ISO 230-2 positioning evaluation, with paper 003's continuous error model and uncertainty.

Usage::

    from volcal.iso230_2 import evaluate, write_report, example_path
    result = evaluate(example_path(), mpe_um=0.5)     # CSV path or pandas DataFrame
    result.parameters_table()                          # ISO parameters per axis
    write_report(result, "out_dir", spacing_mm=10)     # same files as ``volcal iso230-2``

Notation: target i = 1..m at position P_i, cycle j = 1..n, approach ↑ (positive, "+", "up")
or ↓ (negative, "-", "down"); P_ij the actual position reached, x_ij = P_ij - P_i the
positional deviation (actual minus target: an error in the sense of ISO 230-1).

ISO 230-2:2014 parameters (clause 3; computed in :mod:`.parameters`)
-------------------------------------------------------------------
- mean unidirectional positional deviation at a position: x̄_i↑ = (1/n) Σ_j x_ij↑, the mean
  over the n cycles of one direction (likewise ↓);
- mean bidirectional positional deviation at a position: x̄_i = (x̄_i↑ + x̄_i↓) / 2;
- reversal value at a position: B_i = x̄_i↑ - x̄_i↓ (signed);
  reversal value of the axis B = max_i |B_i|; mean reversal value B̄ = (1/m) Σ_i B_i (signed);
- estimator of the unidirectional standard uncertainty of positioning at a position:
  s_i↑ = sqrt( (1/(n-1)) Σ_j (x_ij↑ - x̄_i↑)² );
- unidirectional repeatability at a position R_i↑ = 4 s_i↑; of the axis R↑ = max_i R_i↑;
- bidirectional repeatability at a position R_i = max(2 s_i↑ + 2 s_i↓ + |B_i|, R_i↑, R_i↓)
  (the max matters when one direction scatters much more than the other and B_i is small);
  of the axis R = max_i R_i;
- unidirectional systematic positional deviation E↑ = max_i x̄_i↑ - min_i x̄_i↑;
- bidirectional systematic positional deviation E = max_i(x̄_i↑, x̄_i↓) - min_i(x̄_i↑, x̄_i↓):
  the largest and the smallest mean over both directions and all targets, which may come
  from different directions (so E can exceed both E↑ and E↓);
- range of the mean bidirectional positional deviation M = max_i x̄_i - min_i x̄_i;
- unidirectional accuracy A↑ = max_i(x̄_i↑ + 2 s_i↑) - min_i(x̄_i↑ - 2 s_i↑);
- bidirectional accuracy A = max_i(x̄_i↑ + 2 s_i↑, x̄_i↓ + 2 s_i↓) - min_i(x̄_i↑ - 2 s_i↑,
  x̄_i↓ - 2 s_i↓), again with the extremes over both directions and all targets.

Mistakes of some published tools that these definitions rule out (the tests check each on
asymmetric data): averaging over both directions or all targets instead of over the cycles;
s with 1/n; R_i without the max over R_i↑, R_i↓; E taken as max(E↑, E↓) or as M; A taken
as max(A↑, A↓); B̄ as the mean of |B_i|.

Paper 003 (Halaj et al., "The positional deviation in two axes"; :mod:`.model`, :mod:`.plane`)
----------------------------------------------------------------------------------------
A polynomial Δ(P) = a_0 + a_1 P + ... + a_d P^d (paper: cubic, eq. 2) is fitted to the mean
deviations per direction by generalised least squares with the covariance of eqs. 7-10,
U(x) = diag(u²(x̄_i)) + u²(δ) 1 1ᵀ, with u(x̄_i) the type A uncertainty of each mean and
u(δ) the standard uncertainty of the instrument's error, common to all readings: u(δ) = MPE /
sqrt(3) (rectangular distribution).  The paper's eq. 10 takes u(x̄_i) = s_i / sqrt(n); with
the n = 5 cycles of ISO 230-2 the weights 1/u² are then too large on average and the k = 2
band covered the truth in only about 82 % of simulated repetitions, so by default volcal
uses the GUM Supplement 1 value sqrt((n-1)/(n-3)) s_i / sqrt(n) (about 93 % measured);
``type_a="paper"`` reproduces eq. 10.  The instrument term lies in the column space of the
design (a constant), so it leaves the fitted curve unchanged and adds u²(δ) to the variance
of the constant coefficient.  It gives the coefficients, their covariance and the
expanded uncertainty U(P) = k sqrt(g(P)ᵀ cov g(P)) of the deviation anywhere in [P_1, P_m].
The two-axis model of eq. 13 (no interactions) is :func:`fit_plane`.  The paper's text has
slips read correctly here: the ISO band is x̄ ± 2s (the text reads "+3s" for one limit),
and eq. 3's wording ("difference between the target and the actual position") is taken as
its formula gives it: actual minus target.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

# names exported lazily from their submodules (PEP 562): importing the package (as the
# command line does for `volcal --help`) must not import pandas, scipy and matplotlib.
# The file reader lives in the measurement layer (the laser interferometer reads the same
# files through it)
_LAZY = {
    "volcal.measurement.iso230_2_files": (
        "LINEAR",
        "ROTARY",
        "AxisReadings",
        "AxisUnits",
        "load_readings",
    ),
    "evaluate": ("AxisResult", "Iso230Result", "evaluate", "mpe_to_standard_uncertainty"),
    "model": ("PolynomialModel", "fit_axis_model", "fit_polynomial", "gls", "type_a_uncertainty"),
    "parameters": ("IsoParameters", "iso230_2_parameters"),
    "plane": (
        "PlaneModel",
        "PlaneResult",
        "evaluate_plane",
        "fit_plane",
        "load_plane",
        "write_plane_report",
    ),
    "report": ("OUTPUT_FILES", "markdown_report", "plot", "write_report"),
}
_WHERE = {name: mod for mod, names in _LAZY.items() for name in names}


def __getattr__(name: str) -> Any:
    mod = _WHERE.get(name)
    if mod is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    full = mod if mod.startswith("volcal.") else f"{__name__}.{mod}"
    value = getattr(importlib.import_module(full), name)
    globals()[name] = value
    return value


__all__ = [
    "evaluate",
    "write_report",
    "example_path",
    "Iso230Result",
    "AxisResult",
    "load_readings",
    "AxisReadings",
    "AxisUnits",
    "LINEAR",
    "ROTARY",
    "iso230_2_parameters",
    "IsoParameters",
    "fit_polynomial",
    "fit_axis_model",
    "PolynomialModel",
    "gls",
    "type_a_uncertainty",
    "mpe_to_standard_uncertainty",
    "fit_plane",
    "PlaneModel",
    "load_plane",
    "evaluate_plane",
    "PlaneResult",
    "write_plane_report",
    "markdown_report",
    "plot",
    "OUTPUT_FILES",
]


def example_path() -> Path:
    """Path of the bundled example data set ``volcal/data/iso230_2_example.csv``."""
    from importlib.resources import files

    return Path(str(files("volcal") / "data" / "iso230_2_example.csv"))
