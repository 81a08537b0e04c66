"""Tests of volcal.measurement.multilateration on synthetic data with known truth (units: mm).

Stations: the six LaserTRACER positions of paper 000 Table 5 (MCV 754), dead lengths of a few
mm; points: a grid in the 754 x 500 x 550 mm working space with z in [-550, 0].
"""
from __future__ import annotations

from importlib import resources

import numpy as np
import pytest

from volcal.base.exceptions import InputError
from volcal.measurement.multilateration import (
    calibrate_station,
    calibrate_stations,
    condition_numbers,
    multilaterate,
)
from volcal.measurement.tables import load_stations

EPS = np.finfo(float).eps
SIGMA = 0.5e-3  # mm (0.5 um)
SEEDS = range(10)

# paper 000 Table 5, Case A with function (7), mm: the stations volcal ships
# (tests/test_simulate.py checks them against the paper's numbers)
STATIONS = load_stations(resources.files("volcal").joinpath("data", "mcv754_stations.csv")
                         )[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
DEAD = np.array([3.1, -2.4, 5.0, 1.2, -4.4, 2.2])  # mm


def grid(nx=6, ny=5, nz=5):
    gx, gy, gz = np.meshgrid(np.linspace(0, 754, nx), np.linspace(0, 500, ny),
                             np.linspace(-550, 0, nz), indexing="ij")
    return np.c_[gx.ravel(), gy.ravel(), gz.ravel()]


POINTS = grid()


def lengths(points=POINTS, stations=STATIONS, dead=DEAD, noise=0.0, seed=0):
    """(N, K) readings l = ||P - Q|| - d (+ Gaussian noise, mm)."""
    L = np.linalg.norm(points[:, None, :] - stations[None], axis=-1) - dead
    if noise:
        L = L + np.random.default_rng(seed).normal(0.0, noise, L.shape)
    return L


def long_format(L, points=POINTS):
    K = L.shape[1]
    return np.repeat(np.arange(K), len(points)), np.tile(points, (K, 1)), L.T.ravel()


def station_errors(method, points=POINTS, seeds=SEEDS):
    """Station position errors |Q - Q_true| (mm) and dead length errors over seeds."""
    ep, ed = [], []
    for seed in seeds:
        idx, pts, ll = long_format(lengths(points, noise=SIGMA, seed=seed), points)
        r = calibrate_stations(idx, pts, ll, method)
        assert r.converged.all(), r.status
        ep.append(np.linalg.norm(r.positions - STATIONS, axis=1))
        ed.append(r.dead_lengths - DEAD)
    return np.concatenate(ep), np.concatenate(ed)


def rms(a):
    return float(np.sqrt(np.mean(np.square(a))))


# ---------------------------------------------------------------------------------------------
# station calibration, no noise
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["sqrt", "squared"])
def test_station_iterative_exact_without_noise(method):
    idx, pts, ll = long_format(lengths())
    r = calibrate_stations(idx, pts, ll, method)
    assert r.converged.all()
    assert np.abs(r.positions - STATIONS).max() < 1e-9
    assert np.abs(r.dead_lengths - DEAD).max() < 1e-9
    assert r.residual_rms.max() < 1e-10
    assert (r.iterations >= 1).all() and (r.iterations <= 10).all()


@pytest.mark.parametrize("method", ["linear", "linear_taylor", "paper002"])
def test_station_linear_exact_up_to_rounding(method):
    """Without noise the linear methods are exact up to the rounding their conditioning allows.

    The error stays below 10 * cond_scaled * eps * |Q| (cond_scaled: condition number after
    scaling the unknowns; LU with partial pivoting does not see a column scaling), and is far
    below the normwise bound cond * eps * |x| of the unscaled matrix, which overstates it.
    """
    idx, pts, ll = long_format(lengths())
    r = calibrate_stations(idx, pts, ll, method)
    assert r.converged.all(), r.status
    err = np.linalg.norm(r.positions - STATIONS, axis=1)
    scale = np.linalg.norm(STATIONS, axis=1)
    assert (err <= 10 * r.condition_scaled * EPS * scale).all(), (err, r.condition_scaled)
    assert (np.abs(r.dead_lengths - DEAD) <= 10 * r.condition_scaled * EPS * scale).all()
    assert err.max() < 1e-9
    if method == "linear":
        # |x| of (Q, d, C) is dominated by C = |Q|^2 - d^2 (mm^2)
        xnorm = np.abs(np.sum(STATIONS ** 2, 1) - DEAD ** 2)
        assert (err < 1e-3 * r.condition * EPS * xnorm).all()


def test_single_station_matches_batch():
    L = lengths(noise=SIGMA, seed=3)
    idx, pts, ll = long_format(L)
    for method in ["sqrt", "squared", "linear", "linear_taylor", "paper002"]:
        batch = calibrate_stations(idx, pts, ll, method)
        for k in range(len(STATIONS)):
            one = calibrate_station(POINTS, L[:, k], method)
            assert one.converged and one.method == method and one.n_readings == len(POINTS)
            np.testing.assert_allclose(one.position, batch.positions[k], rtol=0, atol=1e-10)
            assert abs(one.dead_length - batch.dead_lengths[k]) < 1e-10


def test_station_ids_any_labels_and_frame():
    L = lengths()
    idx, pts, ll = long_format(L)
    names = np.array(["LT1", "LT2", "LT3", "LT4", "LT5", "LT6"])[idx]
    r = calibrate_stations(names, pts, ll)
    assert list(r.stations) == ["LT1", "LT2", "LT3", "LT4", "LT5", "LT6"]
    df = r.to_frame()
    assert list(df.columns[:5]) == ["station", "x", "y", "z", "dead_length"]
    assert np.abs(df[["x", "y", "z"]].to_numpy() - STATIONS).max() < 1e-9
    assert r[2].position.shape == (3,) and r[2].converged


def test_sqrt_converges_from_a_poor_start():
    L = lengths(noise=SIGMA, seed=1)
    ref = calibrate_station(POINTS, L[:, 0], "sqrt")
    far = calibrate_station(POINTS, L[:, 0], "sqrt",
                            initial=np.r_[STATIONS[0] + [150.0, -120.0, 90.0], 0.0])
    assert far.converged and far.iterations > ref.iterations
    np.testing.assert_allclose(far.position, ref.position, atol=1e-9)
    assert abs(far.dead_length - ref.dead_length) < 1e-9


def test_fixed_dead_length():
    L = lengths()
    r = calibrate_station(POINTS, L[:, 2], "sqrt", estimate_dead_length=False,
                          dead_length=DEAD[2])
    assert r.converged and r.dead_length == DEAD[2]
    assert np.abs(r.position - STATIONS[2]).max() < 1e-9
    for method in ["linear", "paper002"]:
        r = calibrate_station(POINTS, L[:, 2], method, estimate_dead_length=False,
                              dead_length=DEAD[2])
        assert r.converged and np.abs(r.position - STATIONS[2]).max() < 1e-9


def test_sigma_weighting_uniform_changes_nothing():
    L = lengths(noise=SIGMA, seed=2)
    a = calibrate_station(POINTS, L[:, 4], "sqrt")
    b = calibrate_station(POINTS, L[:, 4], "sqrt", sigma=np.full(len(POINTS), SIGMA))
    np.testing.assert_allclose(a.position, b.position, atol=1e-10)


# ---------------------------------------------------------------------------------------------
# station calibration with noise (sigma 0.5 um, 10 seeds x 6 stations)
# ---------------------------------------------------------------------------------------------
def test_noise_sqrt_at_least_as_accurate_as_squared():
    e_sqrt, d_sqrt = station_errors("sqrt")
    e_sq, d_sq = station_errors("squared")
    # measured: rms 0.32 um (sqrt) vs 0.40 um (squared)
    assert rms(e_sqrt) <= rms(e_sq)
    assert rms(d_sqrt) <= rms(d_sq)
    assert rms(e_sqrt) < 1e-3  # sub-micrometre from 150 readings of 0.5 um


def test_noise_case_b_worse_than_sqrt():
    """Paper 000's finding, measured on synthetic data: Case B is less accurate than sqrt.

    With Gaussian noise only and double precision, the factor is moderate, not the orders of
    magnitude the condition number suggests: 1.46 with the 150-point grid, 1.6 with 27
    points (measured rms station errors 0.47 vs 0.32 um and 0.90 vs 0.56 um).
    """
    e_sqrt, _ = station_errors("sqrt")
    e_b, _ = station_errors("linear")
    assert rms(e_b) > 1.3 * rms(e_sqrt)
    small = grid(3, 3, 3)
    e_sqrt27, _ = station_errors("sqrt", small)
    e_b27, _ = station_errors("linear", small)
    assert rms(e_b27) > 1.4 * rms(e_sqrt27)


def test_taylor_refinement_of_case_b():
    """Paper 000 eq. 12-14: one Taylor step for Q with Case B's dead length kept.

    It lowers the geometric (sqrt) residual of every station, but on noisy synthetic data it
    does not bring Q closer to the truth: Case B's error is mostly in the dead length, which
    the 3x3 step keeps (measured rms 0.56 um after vs 0.47 um before; sqrt 0.32 um).
    """
    for seed in SEEDS:
        idx, pts, ll = long_format(lengths(noise=SIGMA, seed=seed))
        b = calibrate_stations(idx, pts, ll, "linear")
        t = calibrate_stations(idx, pts, ll, "linear_taylor")
        assert (t.residual_rms < b.residual_rms).all()
        assert np.array_equal(t.dead_lengths, b.dead_lengths)
        assert (t.condition_taylor < 100).all()  # the 3x3 system is well conditioned
    e_b, _ = station_errors("linear")
    e_t, _ = station_errors("linear_taylor")
    e_s, _ = station_errors("sqrt")
    assert rms(e_s) < rms(e_b) < rms(e_t) < 2 * rms(e_b)


def test_paper002_start_is_close_enough_for_sqrt():
    for seed in SEEDS:
        L = lengths(noise=SIGMA, seed=seed)
        idx, pts, ll = long_format(L)
        start = calibrate_stations(idx, pts, ll, "paper002")
        assert start.converged.all()
        assert np.abs(start.positions - STATIONS).max() < 0.01  # mm
        r = calibrate_stations(idx, pts, ll, "sqrt")  # starts from paper002 by default
        assert r.converged.all() and (r.iterations <= 10).all()  # measured 4-8
        truth_start = calibrate_stations(idx, pts, ll, "sqrt",
                                         initial=np.c_[STATIONS, DEAD])
        np.testing.assert_allclose(r.positions, truth_start.positions, atol=1e-9)


def test_case_b_condition_numbers():
    idx, pts, ll = long_format(lengths())
    r = calibrate_stations(idx, pts, ll, "linear")
    # paper 000: Theorem 1 gives a lower estimate of at least 1e3; the actual value is
    # several orders larger; scaling the unknowns removes most of it.
    assert (r.condition_lower_bound >= 1e3).all()
    assert (r.condition >= r.condition_lower_bound).all()
    assert (r.condition > 1e8).all()  # measured 2.4e8 .. 1.4e9
    assert (r.condition_scaled < 1e4).all()  # measured 1.6e3 .. 3.1e3
    assert (r.condition / r.condition_scaled > 1e4).all()
    s = calibrate_stations(idx, pts, ll, "sqrt")
    assert (s.condition < 1e4).all()


def test_condition_numbers_helper():
    A = np.diag([1e6, 1.0, 1e-2])
    c, lb, cs = condition_numbers(A)
    assert c == pytest.approx(1e8) and lb == pytest.approx(1e8) and cs == pytest.approx(1.0)
    c, lb, cs = condition_numbers(np.ones((2, 2)))  # singular: inf or rounding-level huge
    assert c > 1e15 and cs > 1e15 and lb == pytest.approx(1.0)


# ---------------------------------------------------------------------------------------------
# station calibration failures
# ---------------------------------------------------------------------------------------------
def test_too_few_readings():
    L = lengths()
    for method in ["sqrt", "squared", "linear", "linear_taylor", "paper002"]:
        r = calibrate_station(POINTS[:3], L[:3, 0], method)
        assert not r.converged and "too few readings" in r.status
        assert np.isnan(r.position).all() and np.isnan(r.dead_length)
    # Case B and paper002 need 5 readings (5 unknowns, or 4 differences)
    r = calibrate_station(POINTS[[0, 7, 40, 99]], L[[0, 7, 40, 99], 0], "linear")
    assert not r.converged and "too few readings" in r.status
    # in a batch only the short station fails
    idx, pts, ll = long_format(L)
    keep = (idx != 3) | (np.arange(len(idx)) % len(POINTS) < 3)
    r = calibrate_stations(idx[keep], pts[keep], ll[keep])
    assert list(r.converged) == [True, True, True, False, True, True]
    assert "too few readings: 3 < 4" in r.status[3]


def test_collinear_points():
    t = np.linspace(0, 1, 20)[:, None]
    line = np.array([0.0, 0.0, -100.0]) + t * np.array([700.0, 400.0, -300.0])
    L = lengths(line)
    for method in ["sqrt", "squared", "linear", "linear_taylor", "paper002"]:
        r = calibrate_station(line, L[:, 0], method)
        assert not r.converged and "collinear" in r.status, r.status


def test_coplanar_points():
    plane = POINTS[POINTS[:, 2] == 0.0]
    L = lengths(plane)
    for method in ["linear", "linear_taylor", "paper002"]:
        r = calibrate_station(plane, L[:, 0], method)
        assert not r.converged and "coplanar" in r.status, r.status
    r = calibrate_station(plane, L[:, 0], "sqrt")  # no start value, mirror ambiguity
    assert not r.converged and "coplanar" in r.status and "initial" in r.status
    r = calibrate_station(plane, L[:, 0], "sqrt", initial=STATIONS[0] + 5.0)
    assert r.converged and "coplanar" in r.status
    assert np.abs(r.position - STATIONS[0]).max() < 1e-8


def test_bad_input_shapes():
    L = lengths()
    with pytest.raises(InputError):
        calibrate_station(POINTS[:, :2], L[:, 0])
    with pytest.raises(InputError):
        calibrate_station(POINTS, L[:-1, 0])
    with pytest.raises(InputError):
        calibrate_station(POINTS, L[:, 0], method="newton")
    with pytest.raises(InputError):
        calibrate_station(POINTS, L[:, 0], initial=[1.0, 2.0])
    with pytest.raises(InputError):
        calibrate_station(POINTS, L[:, 0], sigma=-1.0)
    with pytest.raises(InputError):
        multilaterate(STATIONS, DEAD, L[:, :5])
    with pytest.raises(InputError):
        multilaterate(STATIONS, DEAD[:5], L)
    with pytest.raises(InputError):
        multilaterate(STATIONS, DEAD, L, method="sphere", side=np.zeros(2))


# ---------------------------------------------------------------------------------------------
# point multilateration
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["sqrt", "squared", "linear_taylor"])
def test_points_exact_without_noise(method):
    r = multilaterate(STATIONS, DEAD, lengths(), method)
    assert r.converged.all(), r.status
    assert np.abs(r.points - POINTS).max() < 1e-9
    assert np.nanmax(r.residual_rms) < 1e-10


def test_points_linear_exact_up_to_rounding():
    r = multilaterate(STATIONS, DEAD, lengths(), "linear")
    assert r.converged.all()
    err = np.linalg.norm(r.points - POINTS, axis=1)
    scale = np.linalg.norm(STATIONS, axis=1).max()
    assert (err <= 10 * r.condition_scaled * EPS * scale).all()
    assert err.max() < 1e-9
    # every point sees the same six stations: the same ill-conditioned 4x4 matrix
    assert (r.condition > 1e8).all() and (r.condition_lower_bound >= 1e3).all()
    assert (r.condition_scaled < 1e3).all()


def test_points_noise_sqrt_vs_others():
    errs = {m: [] for m in ["sqrt", "squared", "linear", "linear_taylor"]}
    for seed in SEEDS:
        L = lengths(noise=SIGMA, seed=seed)
        for m in errs:
            r = multilaterate(STATIONS, DEAD, L, m)
            assert r.converged.all()
            errs[m].append(np.linalg.norm(r.points - POINTS, axis=1))
    e = {m: rms(v) for m, v in errs.items()}
    # measured rms: sqrt 1.56 um, squared 1.83 um, linear 2.51 um, linear_taylor = sqrt
    assert e["sqrt"] <= e["squared"] < e["linear"]
    assert e["linear"] > 1.3 * e["sqrt"]
    assert e["linear_taylor"] < 1.01 * e["sqrt"]  # one Taylor step reaches the sqrt optimum
    assert e["sqrt"] < 3e-3


def test_points_from_initial_and_missing_readings():
    L = lengths()
    rng = np.random.default_rng(5)
    drop = rng.random(L.shape) < 0.2
    drop[:, :4] = False  # keep at least four non-coplanar stations per point
    Lm = np.where(drop, np.nan, L)
    Lm[7, 2:] = np.nan  # point 7 seen by two stations only
    r = multilaterate(STATIONS, DEAD, Lm, "sqrt")
    assert not r.converged[7] and "too few readings" in r.point_status[7]
    assert np.isnan(r.points[7]).all()
    ok = np.arange(len(POINTS)) != 7
    assert r.converged[ok].all()
    assert (r.n_stations[ok] == (~drop[ok]).sum(1)).all()
    assert np.abs(r.points[ok] - POINTS[ok]).max() < 1e-9
    r2 = multilaterate(STATIONS, DEAD, Lm, "sqrt", initial=POINTS + 0.1)
    np.testing.assert_allclose(r2.points[ok], POINTS[ok], atol=1e-9)
    # with noise: same convergence pattern, errors within the geometry's amplification
    Ln = np.where(np.isnan(Lm), np.nan, lengths(noise=SIGMA, seed=4))
    rn = multilaterate(STATIONS, DEAD, Ln, "sqrt")
    assert np.array_equal(rn.converged, r.converged)
    assert "1 x too few readings" in r.status


def test_sphere_closed_form():
    L = lengths()
    r = multilaterate(STATIONS[:3], DEAD[:3], L[:, :3], "sphere", side=POINTS)
    assert r.converged.all()
    assert np.abs(r.points - POINTS).max() < 1e-9
    assert (r.stations_used == [0, 1, 2]).all()
    # the other root: reflect the truth through the plane of the three stations
    Q1, Q2, Q3 = STATIONS[:3]
    n = np.cross(Q2 - Q1, Q3 - Q1)
    n /= np.linalg.norm(n)
    mirror = POINTS - 2 * ((POINTS - Q1) @ n)[:, None] * n
    rm = multilaterate(STATIONS[:3], DEAD[:3], L[:, :3], "sphere", side=mirror)
    assert np.abs(rm.points - mirror).max() < 1e-9
    # side as a normal: per point, toward the truth
    rn = multilaterate(STATIONS[:3], DEAD[:3], L[:, :3], "sphere", side=POINTS - Q1,
                       side_type="normal")
    assert np.abs(rn.points - POINTS).max() < 1e-9
    # no side and only three stations: two roots, nothing to choose
    r0 = multilaterate(STATIONS[:3], DEAD[:3], L[:, :3], "sphere")
    assert not r0.converged.any() and "side" in r0.point_status[0]


def test_sphere_with_more_stations_says_so():
    L = lengths()
    r = multilaterate(STATIONS, DEAD, L, "sphere", side=POINTS)
    assert r.converged.all() and np.abs(r.points - POINTS).max() < 1e-9
    assert "first three" in r.status
    assert "used stations (0, 1, 2) only" in r.point_status[0]
    # without side the remaining stations pick the root
    r = multilaterate(STATIONS, DEAD, L, "sphere")
    assert r.converged.all() and np.abs(r.points - POINTS).max() < 1e-9


def test_coplanar_stations():
    Q = STATIONS[:4].copy()
    Q[:, 2] = -700.0  # four stations in one plane, below every point
    L = lengths(stations=Q, dead=DEAD[:4])
    for method in ["linear", "linear_taylor"]:
        r = multilaterate(Q, DEAD[:4], L, method)
        assert not r.converged.any() and "coplanar" in r.point_status[0], r.point_status[0]
    r = multilaterate(Q, DEAD[:4], L, "sqrt")
    assert not r.converged.any() and "coplanar" in r.point_status[0]
    assert np.isnan(r.points).all()
    for side, kind in [(POINTS, "point"), (np.array([0.0, 0.0, 1.0]), "normal")]:
        r = multilaterate(Q, DEAD[:4], L, "sqrt", side=side, side_type=kind)
        assert r.converged.all(), r.status
        assert np.abs(r.points - POINTS).max() < 1e-8
        assert "mirror root chosen by side" in r.point_status[0]


def test_collinear_stations():
    t = np.array([0.0, 0.3, 0.7, 1.0])[:, None]
    Q = np.array([-200.0, 0.0, -600.0]) + t * np.array([1200.0, 500.0, 100.0])
    L = lengths(stations=Q, dead=DEAD[:4])
    for method in ["sqrt", "squared", "linear", "linear_taylor", "sphere"]:
        r = multilaterate(Q, DEAD[:4], L, method, side=POINTS)
        assert not r.converged.any(), method
        assert "collinear" in r.point_status[0], (method, r.point_status[0])


def test_batched_sqrt_agrees_with_scipy_least_squares():
    from scipy.optimize import least_squares

    L = lengths(noise=SIGMA, seed=8)
    r = multilaterate(STATIONS, DEAD, L, "sqrt")
    for i in range(0, len(POINTS), 15):
        ref = least_squares(  # analytic Jacobian: finite differences stop ~1e-8 mm short
            lambda p, i=i: np.linalg.norm(p - STATIONS, axis=1) - (DEAD + L[i]),
            POINTS[i] + 0.01, xtol=1e-15, ftol=1e-15, gtol=1e-15,
            jac=lambda p: (p - STATIONS) / np.linalg.norm(p - STATIONS, axis=1)[:, None]).x
        np.testing.assert_allclose(r.points[i], ref, atol=1e-9)


def test_three_stations_sqrt_with_side():
    L = lengths()
    r = multilaterate(STATIONS[:3], DEAD[:3], L[:, :3], "sqrt", side=POINTS)
    assert r.converged.all() and np.abs(r.points - POINTS).max() < 1e-9
    # with noise a point near the stations' plane: the spheres miss each other, the start is
    # the clamped intersection and the solution lies on the plane, where J is singular
    Ln = lengths(noise=SIGMA, seed=1)
    r = multilaterate(STATIONS[:3], DEAD[:3], Ln[:, :3], "sqrt", side=POINTS)
    assert r.converged.sum() == len(POINTS) - 1
    assert "singular at the solution" in r.point_status[~r.converged][0]


def test_local_minimum_is_reported():
    L = lengths(noise=SIGMA, seed=1)
    r = multilaterate(STATIONS, DEAD, L, "sqrt", initial=POINTS + 200.0)
    bad = ~r.converged
    assert bad.sum() == 1 and "max_residual_rms" in r.point_status[bad][0]
    assert np.abs(r.points[~bad] - POINTS[~bad]).max() < 0.01
    # it is a genuine local minimum, 150 mm from the truth (residual rms 12.7 mm)
    r = multilaterate(STATIONS, DEAD, L, "sqrt", initial=POINTS + 200.0, max_residual_rms=None)
    assert r.converged.all()
    assert np.linalg.norm(r.points[bad] - POINTS[bad]) > 100.0
