"""The numpy tape (volcal.model.numpy_tape) replays each instrument's reading Function: the
values against CasADi's own evaluation of the Function, the reverse sweep's adjoints
against CasADi's Jacobians (its own differentiation, not the tape's), with the station and
frame shared by all readings of a trial (their adjoints summed over the readings)."""

from __future__ import annotations

import pickle

import casadi as ca
import numpy as np
import pytest

from volcal.analysis.uncertainty.engine import reading_tape
from volcal.measurement.instruments import get_instrument
from volcal.model.numpy_tape import NumpyTape

N, B = 7, 3  # readings per station, trials


def _inputs(name: str, rng: np.random.Generator):
    ins = get_instrument(name)
    ns, ng = ins.n_station_params, ins.n_global_params
    P = rng.uniform(-400, 400, (3, N, B))
    if name == "tracker":
        S = np.concatenate([rng.uniform(-2000, 2000, (3, B)), rng.uniform(-1, 1, (1, B))])
        g = np.concatenate([rng.uniform(-1, 1, (3, B)), rng.uniform(-1e-3, 1e-3, (3, B))])
    else:
        S = rng.uniform(-1, 1, (ns, B)) * (1000 if name != "interferometer" else 1)
        if name == "interferometer":  # a unit line direction, small misalignments
            S[:3] = np.array([1.0, 0.1, -0.2])[:, None] + 0.01 * rng.normal(size=(3, B))
            S[3:5] *= 1e-3
        g = rng.uniform(-0.2, 0.2, (ng, B))
    return ins, P, S, g


@pytest.mark.parametrize("name", ["tracker", "multilaser", "interferometer", "ballbar"])
def test_tape_values_and_adjoints_are_the_functions(name):
    rng = np.random.default_rng(32)
    ins, P, S, g = _inputs(name, rng)
    tape = pickle.loads(pickle.dumps(reading_tape(ins)))  # what a worker process replays
    ((v,),) = tape(P, S, g)
    seed = rng.normal(size=(N, B))
    (_, (dP, dS, dg)) = tape.vjp((P, S, g), seed)
    f = ins.reading_function
    p, s, gg = ca.SX.sym("p", 3), ca.SX.sym("s", ins.n_station_params), ca.SX.sym("g", g.shape[0])
    val = f(p, s, gg)[0]
    jac = ca.Function("j", [p, s, gg], [val, ca.jacobian(val, ca.vertcat(p, s, gg))])
    ref_v = np.empty((N, B))
    ref_adj = np.zeros((3 + len(S) + len(g), N, B))
    for b in range(B):
        for i in range(N):
            vv, jj = jac(P[:, i, b], S[:, b], g[:, b])
            ref_v[i, b] = float(vv)
            ref_adj[:, i, b] = seed[i, b] * np.asarray(jj).ravel()
    np.testing.assert_allclose(np.broadcast_to(v, (N, B)), ref_v, rtol=1e-13, atol=1e-10)
    got_p = np.array([np.broadcast_to(x, (N, B)) for x in dP])
    np.testing.assert_allclose(got_p, ref_adj[:3], rtol=1e-10, atol=1e-10)
    # station and frame: one value per trial, the adjoint summed over its readings
    for got, ref in zip([*dS, *dg], ref_adj[3:].sum(axis=1)):
        np.testing.assert_allclose(np.broadcast_to(got, (B,)), ref, rtol=1e-10, atol=1e-9)


def test_tape_refuses_what_it_cannot_replay():
    x = ca.MX.sym("x")
    with pytest.raises(TypeError, match="SX Functions"):
        NumpyTape(ca.Function("m", [x], [2 * x]))
    y = ca.SX.sym("y")
    with pytest.raises(NotImplementedError, match="OP_ERF"):
        NumpyTape(ca.Function("e", [y], [ca.erf(y)]))
