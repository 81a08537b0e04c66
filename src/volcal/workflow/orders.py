"""Per-axis order of the error bases chosen from the data (``degree="auto"``).

``volcal identify --degree auto`` / ``identify(..., degree="auto")`` lands here.  Each axis
whose component error motions have an order (Legendre degree, Fourier harmonics, B-spline
segments) gets the order that minimises an information criterion, found by a greedy
coordinate search: starting from the declared orders (default 3), one axis at a time tries
every candidate order with the other axes held, keeps the best, and the sweeps over the
axes repeat until none changes (at most ``max_sweeps``); fits are cached by their orders.
With ``bic``, the joint strategy and nested bases (Legendre, Fourier) every candidate is
fitted on one problem built for the largest orders (:mod:`volcal.analysis.nested`: the
same chi2 and rank as its own identification, without covariance or tables) and only the
chosen model is identified in full; otherwise (B-splines, ``cv``, other strategies,
``robust``) every candidate is a full identification (:func:`volcal.workflow.single.fit`)
with an explicit ``error_model``.

Criteria (smaller is better):

``bic``  Bayesian information criterion on the whitened residuals:
         chi2 + k ln N, chi2 the sum of squared normalised residuals of the N readings
         used, k the rank of the identification (the number of independent combinations
         of errors, stations and dead lengths the data determine; unidentifiable orders
         add nothing to it, nor to the fit, so they never win).
``cv``   K-fold cross-validation on held-out readings: the poses (point ids) are split
         into K folds (seeded); each fold's readings are left out of one fit (their
         standard uncertainty is set to 1e6 mm, which removes them from the objective)
         and predicted by it; the value is the sum over all held-out readings of
         (residual / sigma)^2, sigma from the data or the budget.  K fits per candidate.

Ties (within 1e-9 relative) go to the lower order.  Candidate orders are limited to those
the data can separate: an axis measured at P distinct positions takes at most P basis
functions (Legendre degree <= P - 1, Fourier harmonics <= (P - 1) / 2, B-spline segments
<= P - 3; angles of a full-turn axis are counted modulo 360 deg).  Axes whose errors are
tables or constants are not searched.  An axis with mixed kinds gets one order n for all
(degree n, n harmonics, n segments).

The result is the identification with the chosen orders; ``result.order_selection`` is a
DataFrame with one row per candidate fit (``sweep, axis, kind, order, orders, n_params,
criterion, value, chi2, k, n_readings, status, chosen``), written by
:func:`volcal.outputs.results.save_result` as ``order_selection.csv`` and summarised in report.md.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import pandas as pd

from volcal.base.exceptions import InputError, SolverError
from volcal.model.errors import Datum, ErrorForm, ErrorModel

log = logging.getLogger(__name__)

__all__ = ["select_orders", "CANDIDATES", "CRITERIA", "with_orders", "axis_orders"]

#: candidate orders per basis kind (Legendre degree, Fourier harmonics, B-spline segments)
CANDIDATES: dict[str, tuple[int, ...]] = {
    "poly": (1, 2, 3, 4, 5, 6),
    "fourier": (1, 2, 3, 4, 5),
    "bspline": (1, 2, 3, 4, 5, 6, 7, 8),
}
CRITERIA = ("bic", "cv")
#: standard uncertainty (mm) that takes a held-out reading out of a cross-validation fit
HELD_OUT_SIGMA_MM = 1e6
_ORDERED = ("poly", "fourier", "bspline")


def _order(f: ErrorForm) -> int:
    return f.segments if f.kind == "bspline" else f.degree


def _with_order(f: ErrorForm, n: int) -> ErrorForm:
    if f.kind == "bspline":
        return ErrorForm("bspline", segments=n)
    if f.kind in ("poly", "fourier"):
        return ErrorForm(f.kind, n)
    return f


def axis_orders(em: ErrorModel) -> dict[str, tuple[str, int]]:
    """{axis: (kind, order)} of the axes whose component error motions have an order
    (the first such motion of the axis names the kind and the current order)."""
    out: dict[str, tuple[str, int]] = {}
    for s, f in zip(em.errors, em.forms):
        if s.kind == "component" and f.kind in _ORDERED and s.axis not in out:
            out[s.axis] = (f.kind, _order(f))
    return out


def with_orders(em: ErrorModel, orders: Mapping[str, int]) -> ErrorModel:
    """``em`` with the component error motions of each axis in ``orders`` at that order
    (kinds kept; tables and constants untouched)."""
    forms = {
        s.name: (_with_order(f, orders[s.axis]) if s.axis in orders else f)
        for s, f in zip(em.errors, em.forms)
        if s.kind == "component"
    }
    return ErrorModel(em.spec, forms, datum=em.datum)


def _n_params(kind: str, n: int) -> int:
    return _with_order(ErrorForm(kind), n).n_params  # type: ignore[arg-type]  # kind from BASIS_KINDS


def _distinct_positions(meas, spec) -> dict[str, int]:
    out = {}
    for j, a in enumerate(spec.axes):
        q = meas.q_internal[:, j]
        if a.full_turn:
            q = np.mod(q, 2 * np.pi)
            q = np.where(np.isclose(q, 2 * np.pi, rtol=0, atol=1e-9), 0.0, q)
        out[a.name] = len(np.unique(np.round(q, 9)))
    return out


def _label(orders: Mapping[str, int], kinds: Mapping[str, str]) -> str:
    return " ".join(f"{a}={kinds[a]}:{n}" for a, n in orders.items())


def select_orders(
    model,
    data,
    stations=None,
    *,
    criterion: str = "bic",
    folds: int = 5,
    candidates: Mapping[str, Iterable[int]] | None = None,
    error_model: ErrorModel | None = None,
    forms: Mapping[str, ErrorForm] | None = None,
    datum: Datum = "iso230",
    max_sweeps: int = 3,
    seed: int = 0,
    progress: bool = False,
    **identify_options: Any,
):
    """Identify with per-axis orders chosen by ``criterion`` (module docstring).

    model, data, stations: as :func:`volcal.workflow.identify`; criterion: ``"bic"`` or
    ``"cv"``; folds: K of the cross-validation; candidates: {kind: orders} replacing those
    of :data:`CANDIDATES`; error_model / forms / datum: the starting error model (kinds and
    starting orders; default Legendre degree 3, Fourier 3 on full-turn rotary axes, plus
    the model file's declarations); identify_options: passed to every fit (strategy,
    budget, robust, ...); progress: a progress bar of the candidate fits on stderr (their
    number is not known in advance: the search stops when no order changes).  Returns the
    :class:`~volcal.analysis.identify.IdentificationResult` of the chosen orders with
    ``order_selection`` (DataFrame) set and a note.
    """
    from volcal.analysis.identify import build_error_model, initial_stations, reading_sigma
    from volcal.measurement.budget import Budget, load_budget
    from volcal.measurement.tables import Measurements, load_measurements, load_stations
    from volcal.model.machine import Machine

    t0 = time.perf_counter()
    if criterion not in CRITERIA:
        raise InputError(
            f"unknown order criterion {criterion!r}; expected one of {list(CRITERIA)}",
            source="order_criterion",
        )
    if isinstance(folds, bool) or not isinstance(folds, (int, np.integer)) or folds < 2:
        raise InputError(
            f"expected at least 2 cross-validation folds, got {folds!r}", source="cv_folds"
        )
    identify_options.pop("degree", None)
    machine = model if isinstance(model, Machine) else Machine.from_model(model)
    spec = machine.spec
    st_table = None
    if stations is not None:
        st_table = (
            stations
            if isinstance(stations, pd.DataFrame)
            and "x_mm" in stations
            and "dead_length_given" in stations
            else load_stations(stations)
        )
    meas = (
        data if isinstance(data, Measurements) else load_measurements(data, spec, stations=st_table)
    )
    em0 = error_model or build_error_model(spec, degree=3, datum=datum, forms=dict(forms or {}))
    cand = {**CANDIDATES, **{k: tuple(int(n) for n in v) for k, v in (candidates or {}).items()}}
    for kind, ns in cand.items():
        if kind not in _ORDERED or not ns or min(ns) < (1 if kind == "bspline" else 0):
            raise InputError(f"bad candidate orders {ns!r} for {kind!r}", source="candidates")

    start = axis_orders(em0)
    kinds = {a: k for a, (k, _) in start.items()}
    n_pos = _distinct_positions(meas, spec)
    options: dict[str, list[int]] = {}
    for a, (kind, _) in start.items():
        ok = [n for n in sorted(set(cand[kind])) if _n_params(kind, n) <= n_pos[a]]
        options[a] = ok or [min(cand[kind])]
    orders = {
        a: (n0 if n0 in options[a] else min(options[a], key=lambda n: abs(n - n0)))
        for a, (_, n0) in start.items()
    }

    # cross-validation: folds of poses and the standard uncertainty of every reading
    if criterion == "cv":
        bud = identify_options.get("budget", "paper002")
        bud = bud if isinstance(bud, Budget) else load_budget(bud)
        st0, _, _ = initial_stations(machine, meas, st_table)
        sig = meas.sigma.copy()
        miss = ~np.isfinite(sig)
        if miss.any():
            sig[miss] = reading_sigma(machine, bud, meas, st0)[miss]
        n_pts = len(meas.point_ids)
        k_folds = min(int(folds), n_pts)
        perm = np.random.default_rng(seed).permutation(n_pts)
        fold_of_point = np.empty(n_pts, int)
        fold_of_point[perm] = np.arange(n_pts) % k_folds
        fold_of_reading = fold_of_point[meas.point_index]

    # BIC of nested bases: every candidate on one problem built for the largest orders
    nested = (
        _nested_fits(machine, meas, st_table, em0, options, kinds, datum, identify_options)
        if criterion == "bic"
        else None
    )

    cache: dict[tuple, dict[str, Any]] = {}
    results: dict[tuple, Any] = {}
    from volcal.base.progress import counter

    # fits counted as they run (their number depends on the sweeps): a bar on a terminal,
    # plain lines in logs; closed below once the sweeps end
    counting = counter(None, "order selection", "fit", on=progress)
    bar = counting.__enter__()

    def fit(em: ErrorModel, m):
        from volcal.workflow.single import fit as fit_one  # classic or the single fit

        return fit_one(machine, m, st_table, error_model=em, **identify_options)

    def score(orders_: Mapping[str, int]) -> dict[str, Any]:
        key = tuple(orders_[a] for a in orders)
        if key in cache:
            return cache[key]
        em = with_orders(em0, orders_)
        row: dict[str, Any] = {
            "orders": _label(orders_, kinds),
            "n_params": em.n_params,
            "criterion": criterion,
        }
        try:
            if nested is not None:
                nf = nested.fit(em)
                if not nf.success:
                    raise SolverError("candidate fit did not converge", status=nf.status)
                row.update(
                    value=nf.chi2 + nf.k * math.log(nf.n),
                    chi2=nf.chi2,
                    k=nf.k,
                    n_readings=nf.n,
                    status=nf.status,
                )
            elif criterion == "bic":
                res = fit(em, meas)
                used = ~np.asarray(res.residuals["rejected"], bool)
                r = res.residuals["normalised_residual"].to_numpy(float)[used]
                chi2 = float(np.sum(r**2))
                k = (
                    res.identifiability.rank
                    if res.identifiability is not None
                    else int(np.sum(res.identifiable))
                )
                n = int(used.sum())
                row.update(
                    value=chi2 + k * math.log(n), chi2=chi2, k=k, n_readings=n, status=res.status
                )
                results[key] = res
            else:
                held_chi2, train_chi2, k, statuses = 0.0, 0.0, 0, []
                for f in range(k_folds):
                    held = fold_of_reading == f
                    m = dataclasses.replace(
                        meas, sigma=np.where(held, HELD_OUT_SIGMA_MM, meas.sigma)
                    )
                    res = fit(em, m)
                    resid_mm = res.residuals["residual_um"].to_numpy(float) * 1e-3
                    used = ~np.asarray(res.residuals["rejected"], bool)
                    held_chi2 += float(np.sum((resid_mm[held] / sig[held]) ** 2))
                    train_chi2 += float(np.sum((resid_mm[~held & used] / sig[~held & used]) ** 2))
                    k = max(
                        k,
                        res.identifiability.rank
                        if res.identifiability is not None
                        else int(np.sum(res.identifiable)),
                    )
                    statuses.append(res.status)
                row.update(
                    value=held_chi2,
                    chi2=train_chi2,
                    k=k,
                    n_readings=len(meas),
                    status="; ".join(dict.fromkeys(statuses)),
                )
        except SolverError as exc:
            row.update(
                value=math.inf,
                chi2=math.nan,
                k=0,
                n_readings=len(meas),
                status=f"failed: {exc.status or exc}",
            )
        log.info("order selection: %s -> %s %.6g", row["orders"], criterion, row["value"])
        bar.update(1, note=f"last {row['orders']}")
        cache[key] = row
        return row

    rows: list[dict[str, Any]] = []
    base = score(orders)
    rows.append({"sweep": 0, "axis": "", "kind": "", "order": np.nan, **base})
    sweeps = 0
    for sweep in range(1, max_sweeps + 1):
        sweeps = sweep
        changed = False
        for a in orders:
            trial_rows = []
            for n in options[a]:
                r = score({**orders, a: n})
                trial_rows.append((n, r))
                rows.append({"sweep": sweep, "axis": a, "kind": kinds[a], "order": n, **r})
            best_v = min(r["value"] for _, r in trial_rows)
            tol = 1e-9 * abs(best_v) if math.isfinite(best_v) else 0.0
            best_n = min(n for n, r in trial_rows if r["value"] <= best_v + tol)
            if best_n != orders[a]:
                changed = True
                orders[a] = best_n
        if not changed:
            break
    key = tuple(orders.values())
    if math.isinf(cache[key]["value"]):
        raise SolverError(
            "order selection: no candidate error model could be identified",
            status=cache[key]["status"],
        )
    chosen_label = _label(orders, kinds)
    res = results.get(key)
    if res is None:  # cv or nested candidates: the chosen orders identified in full
        res = fit(with_orders(em0, orders), meas)
        if nested is not None:
            # the candidate fit and the full one solve the same problem: the same minimum
            full = float(np.sum(res.residuals["normalised_residual"].to_numpy(float) ** 2))
            cand = cache[key]["chi2"]
            if not math.isclose(full, cand, rel_tol=1e-6):
                log.warning(
                    "order selection: the chosen model's chi2 %.9g (full fit) differs from "
                    "its candidate fit's %.9g",
                    full,
                    cand,
                )
    table = pd.DataFrame(
        rows,
        columns=[
            "sweep",
            "axis",
            "kind",
            "order",
            "orders",
            "n_params",
            "criterion",
            "value",
            "chi2",
            "k",
            "n_readings",
            "status",
        ],
    )
    table["chosen"] = table["orders"] == chosen_label
    res.order_selection = table
    counting.__exit__(None, None, None)
    n_fits = len(cache) * (k_folds if criterion == "cv" else 1) + (criterion == "cv")
    how = f"{n_fits} fits"
    if nested is not None:
        how = (
            f"{len(cache)} candidate fits on one problem of the largest orders "
            f"({nested.gradients} gradients, {nested.grams} Gram "
            f"{'matrix' if nested.grams == 1 else 'matrices'}), then the chosen "
            "model identified in full"
        )
    what = "BIC (chi2 + k ln N)" if criterion == "bic" else f"{k_folds}-fold cross-validation"
    res.notes.append(
        f"error-basis orders chosen per axis by {what}: "
        + ", ".join(f"{a} {kinds[a]} {n}" for a, n in orders.items())
        + f" ({len(cache)} candidates, {how}, {sweeps} sweep(s); "
        "order_selection.csv)"
    )
    res.seconds = time.perf_counter() - t0
    return res


def _nested_fits(machine, meas, st_table, em0, options, kinds, datum, identify_options):
    """The candidate fits of nested bases on one problem
    (:class:`volcal.analysis.nested.NestedFits`), or None where a candidate must be a full
    identification: B-spline axes (not nested), another strategy than joint (phases), robust
    rejection (the rejected set changes with the model), the ``impose-all`` datum (decided
    on the largest model's rows), another instrument than the tracker."""
    from volcal.analysis.identify import Identifier, prepare
    from volcal.analysis.nested import NestedFits
    from volcal.base.progress import stage
    from volcal.measurement.instruments import get_instrument
    from volcal.problem.residuals import Layout
    from volcal.problem.strategies import get_strategy

    opts = identify_options
    strategy = get_strategy(opts.get("strategy", "joint"))
    if (
        any(k not in ("poly", "fourier") for k in kinds.values())
        or strategy.name != "joint"
        or opts.get("robust", False)
        or opts.get("datum_mode", "minimal") != "minimal"
        or get_instrument(opts.get("instrument")).name != "tracker"
    ):
        return None
    largest = with_orders(em0, {a: max(ns) for a, ns in options.items()})
    prepared = prepare(
        machine,
        meas,
        st_table,
        error_model=largest,
        datum=datum,
        **{
            k: opts[k]
            for k in ("budget", "station_method", "point_method", "columns", "max_memory_gb")
            if k in opts
        },
    )
    what = f"order selection: building the problem of the largest orders ({len(meas)} readings)"
    with stage(what):
        ider = Identifier(
            prepared.machine,
            largest,
            Layout.from_measurements(prepared.meas),
            exact=opts.get("exact", False),
            instrument=prepared.ins,
            solver="gauss-newton",  # IPOPT is not used for the candidates
        )
        pr = ider.problem
        x0 = pr.pack_x(np.zeros(largest.n_params), prepared.st0, prepared.glob0)
        m = prepared.meas
        p = pr.pack_data(m.q_internal, m.tool, m.length, 1.0 / prepared.sigma)
        return NestedFits(ider, x0, p, ider.station_fixed(prepared.st_fixed))
