"""Error-motion parameterisation: every basis reproduces known functions, the datum
constraints hold, and the CasADi and numpy evaluations agree."""
from __future__ import annotations

import numpy as np
import pytest
from numpy.polynomial import legendre as npleg

from volcal.base.exceptions import InputError
from volcal.model.errors import ErrorForm, ErrorModel, legendre
from volcal.model.spec import resolve_model


@pytest.fixture(scope="module")
def spec():
    return resolve_model("mcv754_wxyzt")


def test_legendre_recurrence_matches_numpy():
    s = np.linspace(-1, 1, 101)
    P = legendre(s, 6)
    for n in range(7):
        c = np.zeros(n + 1)
        c[n] = 1
        assert np.allclose(P[n], npleg.legval(s, c), atol=1e-14)


def test_poly_reproduces_a_cubic_exactly(spec):
    em = ErrorModel(spec, {"EXX": ErrorForm("poly", 3)})
    f = lambda x: 1e-3 * (2.0 + 0.01 * x - 3e-5 * x ** 2 + 4e-8 * x ** 3)  # noqa: E731 (mm)
    th = em.fit_functions({"EXX": f})
    x = np.linspace(0, 754, 37)
    q = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    k = em.errors.index(next(s for s in em.errors if s.name == "EXX"))
    assert np.allclose(em.values(q, th)[:, k], f(x), rtol=0, atol=1e-15)


def test_table_reproduces_a_piecewise_linear_function_and_interpolates(spec):
    knots = (0.0, 100.0, 350.0, 754.0)
    em = ErrorModel(spec, {"EXX": ErrorForm("table", knots=knots)})
    vals = np.array([0.0, 3e-3, -2e-3, 5e-3])
    th = em.theta_from_mapping({f"EXX@{k:g}": v for k, v in zip(knots, vals)})
    x = np.linspace(0, 754, 200)
    q = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    k = [s.name for s in em.errors].index("EXX")
    assert np.allclose(em.values(q, th)[:, k], np.interp(x, knots, vals), atol=1e-15)
    # the CasADi version of the hat functions agrees, also beyond the grid (held flat)
    f = em.values_function()
    for xi in (-10.0, 0.0, 50.0, 100.0, 600.0, 754.0, 800.0):
        e = np.asarray(f([xi, 0, 0], th)).ravel()[k]
        assert e == pytest.approx(np.interp(xi, knots, vals), abs=1e-15)


def test_constant_form_and_location_errors(spec):
    em = ErrorModel(spec, {"EBX": ErrorForm("constant")})
    names = [s.name for s in em.errors]
    assert "EBX" in em.param_names and "EC0Y" in em.param_names
    th = em.theta_from_mapping({"EBX": 7e-6, "EC0Y": 2e-5})
    q = np.random.default_rng(0).uniform([0, 0, -550], [754, 500, 0], (9, 3))
    e = em.values(q, th)
    assert np.allclose(e[:, names.index("EBX")], 7e-6)
    assert np.allclose(e[:, names.index("EC0Y")], 2e-5)


@pytest.mark.parametrize("datum", ["iso230", "reference"])
@pytest.mark.parametrize("form", [ErrorForm("poly", 3), ErrorForm("poly", 5),
                                  ErrorForm("table", knots=(0.0, 200.0, 500.0, 754.0))])
def test_datum_constraints_hold(spec, datum, form):
    em = ErrorModel(spec, {"X": form}, datum=datum)
    C, labels = em.constraints()
    rng = np.random.default_rng(1)
    th = rng.normal(size=em.n_params) * 1e-3
    th -= np.linalg.pinv(C) @ (C @ th)  # the nearest parameters satisfying the datum
    names = [s.name for s in em.errors]
    for axis, (lo, hi) in (("X", (0, 754)), ("Y", (0, 500)), ("Z", (-550, 0))):
        pts = np.zeros((3, 3))
        k = "XYZ".index(axis)
        pts[:, k] = [lo, 0.0, hi]  # start, reference (0), end
        e = em.values(pts, th)
        pos = names.index(f"E{axis}{axis}")
        assert abs(e[1, pos]) < 1e-15  # positioning zero at the reference position
        for ang in "ABC":
            assert abs(e[1, names.index(f"E{ang}{axis}")]) < 1e-15
        for other in "XYZ":
            if other == axis:
                continue
            j = names.index(f"E{other}{axis}")
            if datum == "iso230":  # straightness zero at both ends of travel
                assert abs(e[0, j]) < 1e-15 and abs(e[2, j]) < 1e-15
            else:
                assert abs(e[1, j]) < 1e-15
    # dependent rows are dropped: the constraint matrix has full row rank
    assert np.linalg.matrix_rank(C) == C.shape[0] == len(labels)


def test_bad_forms_rejected(spec):
    with pytest.raises(InputError, match="unknown error/axis"):
        ErrorModel(spec, {"EXQ": ErrorForm("poly", 2)})
    with pytest.raises(InputError, match="knots"):
        ErrorModel(spec, {"EXX": ErrorForm("table", knots=(0.0, 0.0))})
    em = ErrorModel(spec)
    with pytest.raises(InputError, match="unknown parameter"):
        em.theta_from_mapping({"EXX_9": 1.0})


def test_values_and_apply_basis_are_the_basis_error_by_error(spec):
    """values and apply_basis evaluate the columns of the errors that share an axis and a
    form once: the numbers are each error's own basis, bit for bit, also where the errors
    of one axis have different forms (a truth computed error by error from the basis)."""
    forms = {
        "EXX": ErrorForm("poly", 5),
        "EYX": ErrorForm("table", knots=(0.0, 200.0, 500.0, 754.0)),
        "EAX": ErrorForm("constant"),
    }
    em = ErrorModel(spec, forms)
    rng = np.random.default_rng(3)
    lo = np.array([a.travel[0] for a in spec.axes])
    hi = np.array([a.travel[1] for a in spec.axes])
    q = lo + rng.random((40, len(lo))) * (hi - lo)
    theta = rng.normal(size=em.n_params)
    B = em.basis(q)  # (N, n_errors, n_params): each error's own columns
    e = np.zeros((len(q), em.n_errors))
    for k in range(em.n_errors):
        for j in np.flatnonzero(em.param_error_arr == k):
            e[:, k] += theta[j] * B[:, k, j]
    assert np.array_equal(em.values(q, theta), e)
    A = rng.normal(size=(len(q), 3, em.n_errors))
    want = np.empty((len(q), 3, em.n_params))
    for j in range(em.n_params):
        want[:, :, j] = A[:, :, em.param_error_arr[j]] * B[:, em.param_error_arr[j], j][:, None]
    assert np.array_equal(em.apply_basis(A, q), want)
