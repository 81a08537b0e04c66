"""Exported C solvers and C machine models that run without Python.

:func:`export_solver` writes a folder with a C identification solver for one machine model
and one measurement plan (the layout: station, pose and tool of every reading), generated
with CasADi and driven by hand-written C: a small documented API (``<name>.h``), an example
program (``main.c``: measurement CSV in, result CSVs out), a Makefile (gcc -O2, libc and
libm only), a README for the C user and a manifest with hashes so that an unchanged export
is reused.  :func:`export_model` writes the model function alone (tool point, volumetric
error and Jacobians) for controllers that only evaluate a compensation.
:func:`load` runs a compiled export from Python.

What is fixed at export: the model, the error parameterisation, the number of readings and
the station of each, the strategy and the variables held fixed (found by the
identifiability analysis of the plan, as :class:`volcal.analysis.identify.Identifier` finds them).
What is free: every number of the data, start values, solver options.

The solver: constrained Gauss-Newton with exact elimination of the datum constraints, a
backtracking line search, and a convergence check that the caller can trust (relative KKT
stationarity, Gauss-Newton step at the returned point, constraint violation, finiteness,
and a plausibility bound on chi2 per degree of freedom); when it stops without converging
(iteration limit, failed line search) it returns the best iterate, flagged, with its real
chi2 per degree of freedom; see :mod:`volcal.outputs.codegen.solver`.  The hand-written C, the
Makefile and the READMEs are Jinja2 templates in ``volcal/codegen/templates/``, rendered
by :mod:`volcal.outputs.codegen.templates`; golden copies for one configuration are in
``tests/golden/codegen/``.

Start stations: as :func:`volcal.analysis.identify.identify` chooses them - from the stations table
given at export when it lists a station, else computed in C from the readings on the
nominal points (the linear solution of the squared range equations refined by
Gauss-Newton on the range residual, the minimiser Python's ``calibrate_stations`` finds).
A plan without lengths needs a stations table with approximate positions (for the
export-time analysis).
"""

from volcal.outputs.codegen.export import (
    DEFAULT_OPTIONS,
    EXPORT_STRATEGIES,
    ExportInfo,
    build,
    define_solver,
    export_model,
    export_solver,
)
from volcal.outputs.codegen.loader import CompiledModel, CompiledSolver, CResult, load

__all__ = [
    "export_solver",
    "export_model",
    "build",
    "load",
    "define_solver",
    "ExportInfo",
    "CompiledSolver",
    "CompiledModel",
    "CResult",
    "DEFAULT_OPTIONS",
    "EXPORT_STRATEGIES",
]
