"""One identification with given orders: the classic pipeline or the single fit.

The classic strategy (stations calibrated, points multilaterated, errors fitted;
:func:`volcal.analysis.classic.classic_pipeline`) starts from the inputs
:func:`volcal.analysis.identify.prepare` reads and checks; every other strategy is the
single fit :func:`volcal.analysis.identify.identify`.  Both :func:`volcal.workflow.identify`
and the order selection (each candidate it does not take on its fast path) come here.
"""

from __future__ import annotations

import time
from typing import Any

from volcal.analysis.identify import IdentificationResult
from volcal.base.exceptions import InputError
from volcal.problem.strategies import ClassicPipeline, get_strategy

__all__ = ["fit"]


def fit(
    model, data, stations=None, *, strategy: str = "joint", **options: Any
) -> IdentificationResult:
    """One identification (arguments as :func:`volcal.analysis.identify._identify`, lengths
    in mm, angles in rad) by ``strategy``; ``degree`` must be an order, not ``"auto"``."""
    strat = get_strategy(
        strategy,
        station_method=options.get("station_method", "sqrt"),
        point_method=options.get("point_method", "sqrt"),
    )
    if isinstance(strat, ClassicPipeline):
        options.pop("on_solved", None)  # a pipeline of its own, not the single fit
        options.pop("release_graph", None)
        return _classic(model, data, stations, **options)
    from volcal.analysis.identify import _identify

    return _identify(model, data, stations, strategy=strategy, **options)


#: options of the joint problem that the classic pipeline has no use for
_JOINT_ONLY = (
    "robust",
    "reject_k",
    "exact",
    "hessian",
    "scale_covariance",
    "verbose",
    "datum_mode",
    "solver",
)


def _classic(model, data, stations, **options: Any) -> IdentificationResult:
    """The classic pipeline on the inputs :func:`~volcal.analysis.identify.prepare` checks."""
    from volcal.analysis.classic import classic_pipeline
    from volcal.analysis.identify import prepare
    from volcal.base.progress import reset_timings

    t_start = time.perf_counter()
    reset_timings()  # the stage timings recorded with the result are this run's
    for k in _JOINT_ONLY:
        options.pop(k, None)
    prep = prepare(model, data, stations, strategy="classic", **options)
    if prep.ins.name != "tracker":
        raise InputError(
            f"the classic pipeline calibrates tracker stations; it does not "
            f"apply to the {prep.ins.name} instrument"
        )
    strat = prep.strat
    assert isinstance(strat, ClassicPipeline)  # fit() sent only the classic strategy here
    return classic_pipeline(
        prep.machine,
        prep.error_model,
        prep.meas,
        prep.st0,
        prep.sigma,
        station_method=strat.station_method,
        point_method=strat.point_method,
        t_start=t_start,
        sigma_source=prep.sigma_source,
        notes=prep.notes,
    )
