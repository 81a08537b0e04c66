"""Estimation strategies as objects that transform the one identification problem.

A strategy never builds its own problem: it says, phase by phase, which groups of
variables of :class:`volcal.problem.residuals.IdentificationProblem` are held, which are
reset to zero at the start of the phase, whether the datum is selected for the phase and
whether one variable per null direction is held (the pivots of the identifiability
analysis).  :meth:`volcal.analysis.identify.Identifier.run` executes the phases on the one
problem and solver.  The groups are ``"errors"`` (the error parameters theta),
``"stations"`` (the instrument's per-station parameters) and ``"frame"`` (its global
parameters).

``joint``        everything together (one step);
``two-phase``    the stations on nominal points first (errors held at zero), then the
                 errors with the stations held; the frame motion is free in phase two so
                 the frame mismatch of phase one is absorbed;
``points-only``  stations held at known or analytical positions, only the errors (+ frame);
``classic``      the calibrate -> multilaterate -> fit pipeline of paper 000
                 (:mod:`volcal.analysis.classic`), which does not solve the joint problem.

A new strategy is a :class:`PhasedStrategy` with its phases (or a subclass), registered
with :func:`register`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from volcal.base.exceptions import InputError

GROUPS = ("errors", "stations", "frame")


@dataclass(frozen=True)
class Phase:
    """One solve of a strategy (see the module docstring)."""

    #: variable groups held at their start value in this phase
    hold: frozenset[str] = frozenset()
    #: variable groups set to zero at the start of the phase
    zero: frozenset[str] = frozenset()
    #: select the datum for the data at hand (False: no datum condition in force; only
    #: valid when the error parameters are held)
    datum: bool = True
    #: hold one variable per null direction of the Jacobian (the identifiability pivots)
    pivots: bool = True
    #: key prefix under which the conditioning of this phase is reported (None: not)
    report: str | None = None

    def __post_init__(self) -> None:
        bad = (set(self.hold) | set(self.zero)) - set(GROUPS)
        if bad:
            raise ValueError(f"unknown variable groups {sorted(bad)}; expected {GROUPS}")
        if not self.datum and "errors" not in self.hold:
            raise ValueError("a phase without datum must hold the error parameters")


@dataclass(frozen=True)
class Strategy:
    """Base of every strategy: its name and a one-line description."""

    name: str
    description: str = ""


@dataclass(frozen=True)
class PhasedStrategy(Strategy):
    """A strategy that solves the one problem in phases."""

    phases: tuple[Phase, ...] = ()
    #: hold every station at its start value (given table or analytical solution)
    hold_stations: bool = False


@dataclass(frozen=True)
class ClassicPipeline(Strategy):
    """Paper 000's pipeline: calibrate the stations on nominal points, multilaterate every
    point, fit the error model to the points (:mod:`volcal.analysis.classic`).

    station_method / point_method: the residual each step minimises (``"sqrt"``,
    ``"squared"``, ... see :mod:`volcal.measurement.multilateration`)."""

    station_method: str = "sqrt"
    point_method: str = "sqrt"


JOINT = PhasedStrategy("joint", "error parameters, stations and dead lengths together", (Phase(),))
TWO_PHASE = PhasedStrategy(
    "two-phase",
    "stations on nominal points first, then the errors with stations held",
    (
        Phase(
            hold=frozenset({"errors", "frame"}),
            zero=frozenset({"errors"}),
            datum=False,
            pivots=False,
            report="phase1",
        ),
        Phase(hold=frozenset({"stations"})),
    ),
)
POINTS_ONLY = PhasedStrategy(
    "points-only",
    "stations held at known or analytical positions, only the errors",
    (Phase(hold=frozenset({"stations"})),),
    hold_stations=True,
)
CLASSIC = ClassicPipeline("classic", "calibrate -> multilaterate -> fit (paper 000)")

_REGISTRY: dict[str, Strategy] = {s.name: s for s in (JOINT, TWO_PHASE, POINTS_ONLY, CLASSIC)}


def register(strategy: Strategy) -> Strategy:
    """Make a strategy available by its name."""
    _REGISTRY[strategy.name] = strategy
    return strategy


def strategies() -> list[str]:
    """Names of the registered strategies."""
    return list(_REGISTRY)


def get_strategy(strategy: str | Strategy, **options) -> Strategy:
    """A strategy object from its name (or the object itself).  ``options`` set the fields
    of a :class:`ClassicPipeline` (station_method, point_method)."""
    if isinstance(strategy, Strategy):
        return strategy
    try:
        s = _REGISTRY[str(strategy)]
    except KeyError:
        raise InputError(
            f"unknown strategy {strategy!r}; expected one of {', '.join(_REGISTRY)}"
        ) from None
    if isinstance(s, ClassicPipeline) and options:
        s = replace(s, **{k: v for k, v in options.items() if v is not None})
    return s


__all__ = [
    "Phase",
    "Strategy",
    "PhasedStrategy",
    "ClassicPipeline",
    "JOINT",
    "TWO_PHASE",
    "POINTS_ONLY",
    "CLASSIC",
    "register",
    "strategies",
    "get_strategy",
    "GROUPS",
]
