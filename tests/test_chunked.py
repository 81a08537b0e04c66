"""Invariant: the chunked evaluation (volcal.problem.chunked) is the problem's J.

The Gauss-Newton solver and the analyses take r, J^T r, J^T J and the R factor from
fixed-size chunks of poses, without the whole-problem CasADi graph.  They must equal the
whole graph's ``gram`` and the central differences of the residual Function (which uses
no structure of J) on a layout where chunking can go wrong: the chunk size does not divide
the number of poses (a padded last chunk), poses have uneven numbers of readings and are
not contiguous in the table (rows shuffled, a third dropped), several stations, readings
dropped with w = 0, and data from the independent rigid-body simulator (tests/indep_sim.py).
"""

from __future__ import annotations

import numpy as np
import pytest

import indep_sim as ind
from volcal.measurement.instruments import get_instrument
from volcal.measurement.tables import load_measurements
from volcal.model.errors import ErrorForm, ErrorModel
from volcal.model.machine import Machine
from volcal.problem.chunked import ChunkedEvaluator
from volcal.problem.residuals import IdentificationProblem, Layout


def _problem(model: str, instrument: str):
    geom = ind.load_geometry(model)
    plan = ind.grid(geom, {a.name: 3 for a in geom.axes})
    tools = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 100.0], [80.0, 0.0, 60.0]])
    truth = ind.draw_truth(geom, np.random.default_rng(2), "nonrep")
    sim = ind.simulate(geom, truth, plan, tools, np.random.default_rng(4), n_stations=4)
    machine = Machine.from_model(model)
    em = ErrorModel(machine.spec, default=ErrorForm("poly", 2))
    rng = np.random.default_rng(5)
    df = sim.measurements
    keep = rng.permutation(len(df))[: (2 * len(df)) // 3]
    meas = load_measurements(df.iloc[keep].reset_index(drop=True), machine.spec)
    lay = Layout.from_measurements(meas)
    counts = np.bincount(lay.poses[0])
    assert counts.min() < counts.max() and lay.n_stations == 4
    pr = IdentificationProblem(machine, em, get_instrument(instrument), lay)
    xs = 0.3 * rng.normal(size=pr.n_x)
    st = np.zeros((lay.n_stations, pr.instrument.n_station_params))
    true_st = sim.stations.set_index("station").loc[list(meas.station_ids)]
    st[:, :3] = true_st[["x_mm", "y_mm", "z_mm"]].to_numpy()
    xs[pr.station_slice()] += (st / 1e-3).ravel()  # scaled units of 1 um
    w = 1.0 / sim.sigma_mm[keep]
    w[rng.choice(len(w), len(w) // 7, replace=False)] = 0.0  # dropped readings
    p = pr.pack_data(meas.q_internal, meas.tool, meas.length, w)
    return pr, xs, p


@pytest.mark.parametrize(
    "model,instrument", [("mcv754_wxyzt", "tracker"), ("trunnion_ac", "multilaser")]
)
def test_chunked_sums_are_the_whole_graphs_and_the_residuals_derivatives(model, instrument):
    pr, xs, p = _problem(model, instrument)
    n_poses = len(pr.layout.poses[1])
    chunk = 7
    assert n_poses % chunk != 0  # a padded last chunk
    ch = ChunkedEvaluator(pr, pose_chunk=chunk)

    # the reference: the whole graph (IPOPT's) and central differences of its residual
    r_ref, g_ref, H_ref = (np.asarray(v.full()) for v in pr.gram(xs, p))
    r_ref, g_ref = r_ref.ravel(), g_ref.ravel()
    J = np.empty((len(r_ref), pr.n_x))
    for j in range(pr.n_x):
        h = np.zeros(pr.n_x)
        h[j] = 1e-3
        up, down = pr.residual(xs + h, p), pr.residual(xs - h, p)
        J[:, j] = (np.asarray(up) - np.asarray(down)).ravel() / 2e-3
    assert np.all(J[p[-len(r_ref) :] == 0] == 0)  # dropped readings: zero rows

    r, g, H = ch.gram(xs, p)
    scale_r = max(np.abs(r_ref).max(), 1.0)
    assert np.max(np.abs(r - r_ref)) <= 1e-12 * scale_r
    assert np.max(np.abs(ch.residuals(xs, p) - r_ref)) <= 1e-12 * scale_r
    assert ch.objective(xs, p) == pytest.approx(0.5 * r_ref @ r_ref, rel=1e-12)
    assert np.max(np.abs(g - g_ref)) <= 1e-12 * np.abs(g_ref).max()
    assert np.max(np.abs(H - H_ref)) <= 1e-12 * np.abs(H_ref).max()
    assert np.array_equal(H, H.T)
    # against the central differences (no structure of J used)
    assert np.max(np.abs(H - J.T @ J)) <= 1e-6 * np.abs(H).max()
    assert np.max(np.abs(g - J.T @ r_ref)) <= 1e-6 * np.abs(g).max()

    r_f, R = ch.r_factor(xs, p)
    assert np.array_equal(r_f, r)
    assert R.shape == (pr.n_x, pr.n_x) and np.all(np.tril(R, -1) == 0)
    assert np.max(np.abs(R.T @ R - H_ref)) <= 1e-12 * np.abs(H_ref).max()
    s_ref = np.linalg.svd(J, compute_uv=False)
    s = np.linalg.svd(R, compute_uv=False)
    assert np.max(np.abs(s - s_ref)) <= 1e-6 * s_ref[0]

    # a solve that holds every error parameter: the other blocks, without d(point)/d(theta)
    nt = pr.n_theta
    r0, g0, H0 = ch.gram(xs, p, theta=False)
    assert np.max(np.abs(r0 - r)) <= 1e-12 * scale_r
    assert np.max(np.abs(g0[nt:] - g[nt:])) <= 1e-12 * np.abs(g_ref).max()
    assert np.max(np.abs(H0[nt:, nt:] - H[nt:, nt:])) <= 1e-12 * np.abs(H_ref).max()
    assert not g0[:nt].any() and not H0[:nt].any() and not H0[:, :nt].any()

    # one chunk holding every pose gives the same sums (to rounding)
    r1, g1, H1 = ChunkedEvaluator(pr, pose_chunk=n_poses + 5).gram(xs, p)
    assert np.array_equal(r1, r)
    assert np.max(np.abs(H1 - H)) <= 1e-13 * np.abs(H).max()


def test_gauss_newton_never_builds_the_whole_graph():
    """The Gauss-Newton path (solver "gauss-newton", or "auto" on a large table) solves
    and analyses without the CasADi graph of every reading."""
    from test_identify import simulated
    from volcal.analysis.identify import identify

    machine, em, _, sim = simulated("mcv754_wxyzt", grid=3)
    res = identify(machine, sim.measurements, error_model=em, solver="gauss-newton")
    assert res.success
    pr = res.identifier.problem
    assert "_graph" not in pr.__dict__
    ref = identify(machine, sim.measurements, error_model=em, solver="ipopt")
    assert "_graph" in ref.identifier.problem.__dict__
    assert np.max(np.abs(res.theta - ref.theta)) <= 1e-9 * np.abs(ref.theta).max()
    assert np.allclose(res.cov_theta, ref.cov_theta, rtol=1e-6, atol=1e-18, equal_nan=True)


def test_the_gram_bins_are_kept_only_below_their_budget(monkeypatch):
    """The bincount bins are kept between calls for small problems (Monte Carlo trials)
    and made again per chunk above the budget (a large identification would hold
    8 (L (L + 1) / 2 + 4 L + 12) bytes per reading): both ways give the same sums, bit for
    bit."""
    import volcal.problem.chunked as chunked

    pr, xs, p = _problem("mcv754_wxyzt", "tracker")
    kept = ChunkedEvaluator(pr, pose_chunk=7)
    r, g, H = kept.gram(xs, p)
    assert kept._gram_bins  # a small problem keeps them
    monkeypatch.setattr(chunked, "GRAM_BINS_KEPT_BYTES", 0)
    remade = ChunkedEvaluator(pr, pose_chunk=7)
    for _ in range(2):
        r1, g1, H1 = remade.gram(xs, p)
        assert not remade.__dict__.get("_gram_bins")
        assert np.array_equal(r1, r) and np.array_equal(g1, g) and np.array_equal(H1, H)


def test_what_is_kept_between_passes_gives_the_numbers_evaluated_afresh(monkeypatch):
    """d(point)/d(theta) of the first-order model does not depend on theta: it is
    evaluated once per chunk and the later passes evaluate the point alone; the pass of
    an R factor is kept, and the next pass at the same point and data (the datum's R
    factor, then Gauss-Newton's first system) takes it.  Both give the numbers of an
    evaluator that keeps nothing, bit for bit; other data (other poses, other weights)
    are evaluated anew."""
    import volcal.problem.chunked as chunked

    pr, xs, p = _problem("mcv754_wxyzt", "tracker")
    ev = ChunkedEvaluator(pr, pose_chunk=7)
    calls = {"read": 0}
    R = ev.r_factor(xs, p)[1]
    assert ev._g_free and ev._g_kept and ev._pass_kept is not None
    for key, call in list(ev._calls.items()):  # the readings' maps (whole and last chunk)
        if key[0] == "read":

            def counted(*args, call=call):
                calls["read"] += 1
                return call(*args)

            ev._calls[key] = counted  # type: ignore[assignment]
    got = [ev.gram(xs, p)]  # the kept pass: no evaluation
    assert calls["read"] == 0 and ev._pass_kept is None  # taken once, then let go
    rng = np.random.default_rng(8)
    xs2 = xs + rng.normal(size=pr.n_x)
    got.append(ev.gram(xs2, p))  # the kept d(point)/d(theta), the point evaluated
    assert calls["read"] > 0
    q = p.copy()
    n_ax = pr.machine.n_axes
    q[: n_ax * pr.layout.n_readings] += 0.5  # other poses: d(point)/d(theta) anew
    got.append(ev.gram(xs2, q))
    w = p.copy()
    w[-pr.layout.n_readings :] *= 2.0  # other weights at the same point
    got.append(ev.gram(xs2, w))
    R2 = ev.r_factor(xs2, w)[1]

    monkeypatch.setattr(chunked, "PASS_KEPT_BYTES", 0)
    fresh = ChunkedEvaluator(pr, pose_chunk=7)
    want = [fresh.gram(xs, p), fresh.gram(xs2, p), fresh.gram(xs2, q), fresh.gram(xs2, w)]
    assert not fresh._g_kept and fresh._pass_kept is None
    for a, b in zip(got, want):
        assert all(np.array_equal(u, v) for u, v in zip(a, b))
    assert np.array_equal(R, fresh.r_factor(xs, p)[1])
    assert np.array_equal(R2, fresh.r_factor(xs2, w)[1])

    # the model to second order: its d(point)/d(theta) depends on theta, never kept
    exact = IdentificationProblem(pr.machine, pr.error_model, pr.instrument, pr.layout, exact=True)
    ex = ChunkedEvaluator(exact, pose_chunk=7)
    ex.gram(xs, p)
    assert not ex._g_free and not ex._g_kept


def test_a_maps_size_does_not_change_its_numbers():
    """The last, partial chunk of poses is evaluated on maps of its own size instead of
    padded to a whole chunk: each point is evaluated on its own, the same numbers, bit for
    bit, as on the whole chunk's map (and the sums then the same as with padding)."""
    pr, xs, p = _problem("mcv754_wxyzt", "tracker")
    ev = ChunkedEvaluator(pr, pose_chunk=7)
    rng = np.random.default_rng(9)
    k = 3
    for kind in ("pose", "point", "read", "value"):
        whole = ev._call(kind)
        args = [rng.normal(size=whole.f.size_in(i)) for i in range(whole.f.n_in())]
        outs = whole(*args)
        parts = ev._call(kind, k)(*[x[:, :k] for x in args])
        assert len(parts) == len(outs)
        for a, b in zip(outs, parts):
            # the k points' outputs side by side: the whole map's first columns
            assert b.shape[1] < a.shape[1] and np.array_equal(a[:, : b.shape[1]], b)


def test_a_last_chunk_of_one_pose():
    """A last chunk holding a single pose (a map over one point gives its single-column
    outputs as vectors): the same residuals, bit for bit, and the same sums and R factor
    (to rounding) as one chunk holding every pose."""
    pr, xs, p = _problem("mcv754_wxyzt", "tracker")
    n_poses = len(pr.layout.poses[1])
    one = ChunkedEvaluator(pr, pose_chunk=n_poses - 1)  # the last chunk: one pose
    whole = ChunkedEvaluator(pr, pose_chunk=n_poses + 5)
    assert np.array_equal(one.residuals(xs, p), whole.residuals(xs, p))
    r, g, H = one.gram(xs, p)
    r1, g1, H1 = whole.gram(xs, p)
    assert np.array_equal(r, r1)
    assert np.max(np.abs(g - g1)) <= 1e-13 * np.abs(g1).max()
    assert np.max(np.abs(H - H1)) <= 1e-13 * np.abs(H1).max()
    R, R1 = one.r_factor(xs, p)[1], whole.r_factor(xs, p)[1]
    assert np.max(np.abs(R.T @ R - R1.T @ R1)) <= 1e-12 * np.abs(H1).max()
