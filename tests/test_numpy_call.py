"""Invariant: a function called through numpy buffers (volcal.model.numpy_call) returns what
CasADi's own call returns, whether the scatter pattern of a mapped function's sparse output
is read from the map or repeated from the function it maps."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from volcal.model.machine import Machine
from volcal.model.numpy_call import NumpyCall


@pytest.mark.parametrize("n", [1, 7])
def test_a_mapped_sparse_jacobian_lands_where_casadi_puts_it(n):
    f = Machine.from_model("mcv754_wxyzt").functions["tool_point"]
    assert not f.sparsity_out(2).is_dense()  # d(point)/d(errors): a sparse output
    rng = np.random.default_rng(0)
    args = [rng.normal(size=(f.size1_in(i), n)) for i in range(f.n_in())]
    mapped = f.map(n)
    ref = [np.asarray(o.full()) for o in mapped.call([ca.DM(a) for a in args])]
    for call in (NumpyCall(mapped), NumpyCall(mapped, mapped_from=f)):
        out = call(*args)
        assert len(out) == len(ref)
        for a, b in zip(out, ref):
            # (a single call's column output comes as a vector)
            assert a.size == b.size and np.array_equal(a.reshape(b.shape), b)


def test_mapped_from_refuses_a_function_that_is_not_the_map():
    x = ca.SX.sym("x", 2)
    zero = ca.SX(1, 1)  # a structural zero
    f = ca.Function("f", [x], [ca.vertcat(x[0], zero, x[1] * x[0])])
    g = ca.Function("g", [x], [ca.vertcat(zero, x[1], x[0])])
    assert not f.sparsity_out(0).is_dense() and f.nnz_out(0) == g.nnz_out(0)
    with pytest.raises(ValueError, match="side by side"):
        NumpyCall(g.map(3), mapped_from=f)
