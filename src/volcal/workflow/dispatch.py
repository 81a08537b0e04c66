"""``volcal.identify``: which strategy and which orders, then the fit.

Several instruments' tables (a list as ``data``, or variance components): one problem
through :func:`volcal.analysis.fusion.identify_datasets`; ``degree="auto"``: the orders of
the error bases chosen from the data (:func:`volcal.workflow.orders.select_orders`);
otherwise one identification with the given orders (:func:`volcal.workflow.single.fit`:
the classic pipeline or the single fit).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from volcal.analysis.identify import IdentificationResult, Solved
from volcal.measurement.tables import Measurements
from volcal.model.machine import Machine
from volcal.model.spec import MachineSpec

__all__ = ["identify"]


def identify(
    model: str | Path | MachineSpec | Machine,
    data: str | Path | pd.DataFrame | Measurements | Sequence[Any],
    stations: str | Path | pd.DataFrame | None = None,
    *,
    strategy: str = "joint",
    degree: int | str = 3,
    order_criterion: str = "bic",
    cv_folds: int = 5,
    progress: bool = False,
    on_solved: Callable[[Solved], None] | None = None,
    release_graph: bool = False,
    **options: Any,
) -> IdentificationResult:
    """Identify the geometric errors of a machine from length readings (``volcal
    identify``); runs with one BLAS thread (see :mod:`volcal.base.threads`).

    model, data, stations and ``options`` (datum, error_model, forms, budget, robust,
    reject_k, exact, hessian, scale_covariance, station_method, point_method, verbose,
    datum_mode, instrument, solver, columns, max_memory_gb): as
    :func:`volcal.analysis.identify._identify` (lengths in mm, angles in rad inside).
    strategy: ``"joint"`` (default), ``"two-phase"``, ``"points-only"`` or ``"classic"``.
    degree: Legendre degree / Fourier harmonics of the component error motions, or
    ``"auto"``: per-axis orders chosen by ``order_criterion`` (``"bic"`` or ``"cv"`` with
    ``cv_folds`` folds; :mod:`volcal.workflow.orders`; ``progress``: a bar of its candidate
    fits on stderr, a single identification has none).  data: also several instruments'
    tables (a list of tables, ``(instrument, table[, budget[, name]])`` tuples or
    :class:`volcal.analysis.fusion.DataSet`), one problem with chi2/dof per table in
    ``result.instruments``; ``variance_components=True``: each table's budget scale factor
    estimated (Helmert), see :func:`volcal.analysis.fusion.identify_datasets`.
    on_solved: called with the estimates and the residual table
    (:class:`volcal.analysis.identify.Solved`) before the uncertainty stage of a single
    fit (not with several tables, ``degree="auto"`` or the classic strategy, whose
    results come from several fits or another pipeline).  release_graph: likewise for a
    single fit only, its IPOPT solver and CasADi graph of every reading freed before the
    uncertainty stage (:meth:`volcal.analysis.identify.Identifier.release_graph`; ``volcal
    identify``, which solves no more, lowers its peak memory so).
    """
    from volcal.base.threads import blas_threads

    with blas_threads(1):
        if isinstance(data, (list, tuple)) or options.get("variance_components"):
            from volcal.analysis.fusion import identify_datasets

            tables: Sequence[Any] = data if isinstance(data, (list, tuple)) else [data]
            return identify_datasets(
                model,
                tables,
                stations=stations,
                strategy=strategy,
                degree=degree,
                order_criterion=order_criterion,
                cv_folds=cv_folds,
                progress=progress,
                **options,
            )
        if degree == "auto":  # every other argument goes to each candidate fit
            from volcal.workflow.orders import select_orders

            return select_orders(
                model,
                data,
                stations,
                criterion=order_criterion,
                folds=cv_folds,
                progress=progress,
                strategy=strategy,
                **options,
            )
        from volcal.workflow.single import fit

        return fit(
            model,
            data,
            stations,
            strategy=strategy,
            degree=degree,
            on_solved=on_solved,
            release_graph=release_graph,
            **options,
        )
