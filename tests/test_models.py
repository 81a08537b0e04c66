"""Every bundled model: truncation order, lowering fidelity, Jacobians, build cache, packaging.

Independent truths used here: the exact tool point (first order must differ from it by a
term of second order in the errors), SymPy's own arithmetic on the symbolic expressions
(30-digit Floats substituted with ``xreplace``, no CasADi involved) and central finite
differences of the compiled functions.
"""
from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from volcal.model.machine import Machine
from volcal.model.spec import bundled_models, resolve_model

MODELS = sorted(bundled_models())
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def machines(tmp_path_factory) -> dict[str, Machine]:
    """Every bundled model built from its SymPy chain here (never read from a cache), each
    into an empty build cache of its own (``cache_dirs``), which the cache test then reads."""
    out = {}
    with pytest.MonkeyPatch.context() as mp:
        for name in MODELS:
            mp.setenv("VOLCAL_CACHE_DIR", str(cache_dirs(tmp_path_factory, name)))
            out[name] = Machine.from_model(name)
            assert out[name].from_cache is False
    return out


def cache_dirs(tmp_path_factory, name: str) -> Path:
    """The build cache folder of one model in this module (tmp_path_factory's base)."""
    return tmp_path_factory.getbasetemp() / "models_build_cache" / name


def random_inputs(m: Machine, rng: np.random.Generator, *, trans: float, ang: float):
    """A random pose within travel (internal units), tool offset (mm) and error vector."""
    q = np.array([rng.uniform(*a.travel) for a in m.spec.axes])
    q = m.axis_to_internal(q)
    t = rng.uniform(-150.0, 150.0, 3)
    e = np.array([rng.normal(0.0, trans if s.quantity == "translation" else ang)
                  for s in m.errors])
    return q, t, e


def call(m: Machine, fname: str, q, t, e):
    return [np.asarray(v, float) for v in m[fname](q, t, e)]


def test_there_are_bundled_models():
    assert {"mcv754_wxyzt", "xfyz", "head_bc", "trunnion_ac"} <= set(MODELS)


# --------------------------------------------------------------------------------------
# (a) first order vs exact: the difference is of second order in the errors


@pytest.mark.parametrize("name", MODELS)
def test_first_order_error_is_quadratic(machines, name):
    m = machines[name]
    rng = np.random.default_rng(1234)
    s = 1.0  # 10 um / 20 urad: second-order terms ~1e-7 mm, roundoff ~1e-13 mm
    for _ in range(6):
        q, t, e = random_inputs(m, rng, trans=0.01, ang=2e-5)
        diffs = []
        for scale in (s, s / 2):
            p1 = call(m, "tool_point", q, t, scale * e)[0]
            px = call(m, "tool_point_exact", q, t, scale * e)[0]
            diffs.append((p1 - px).ravel())
        d_s, d_half = diffs
        # second order: bounded by (angle * (length + translation)), far above roundoff
        assert 1e-11 < np.linalg.norm(d_s) < 1e-4
        ratio = np.linalg.norm(d_s) / np.linalg.norm(d_half)
        assert 3.6 < ratio < 4.4, ratio
        # the whole vector scales by 4, not only its norm
        assert np.linalg.norm(d_s - 4 * d_half) < 0.05 * np.linalg.norm(d_s)


@pytest.mark.parametrize("name", MODELS)
def test_first_order_part_is_linear_in_errors(machines, name):
    m = machines[name]
    rng = np.random.default_rng(7)
    q, t, e = random_inputs(m, rng, trans=0.01, ang=2e-5)
    p, dp, J = call(m, "tool_point", q, t, e)
    p0 = np.asarray(m["nominal"](q, t), float)
    np.testing.assert_allclose(p - p0, dp, rtol=0, atol=1e-12)
    np.testing.assert_allclose(J @ e, dp.ravel(), rtol=1e-12, atol=1e-15)
    # zero errors: exact and first order both give the nominal point
    z = np.zeros(m.n_errors)
    for f in ("tool_point", "tool_point_exact"):
        pz, dpz, _ = call(m, f, q, t, z)
        np.testing.assert_allclose(pz, p0, rtol=0, atol=1e-12)
        # first order: exactly zero; exact: px - p0 of two separately rounded products
        np.testing.assert_allclose(dpz, 0.0, rtol=0, atol=0 if f == "tool_point" else 1e-11)


# --------------------------------------------------------------------------------------
# (b) lowered CasADi functions == SymPy's own arithmetic; J == finite differences of dp


@pytest.fixture(scope="module")
def chains():
    from volcal.model.symbolic import build_chain
    return {name: build_chain(resolve_model(name)) for name in MODELS}


def sympy_values(exprs, symbols, values):
    import sympy as sp
    sub = {s: sp.Float(float(v), 30) for s, v in zip(symbols, values)}
    out = []
    for x in exprs:
        r = sp.sympify(x).xreplace(sub)
        assert r.is_Number, f"free symbols left: {r.free_symbols}"
        out.append(float(r))
    return np.array(out)


@pytest.mark.parametrize("name", MODELS)
def test_lowering_matches_sympy(machines, chains, name):
    m, ch = machines[name], chains[name]
    assert [str(s) for s in ch.e] == m.error_names
    rng = np.random.default_rng(99)
    # errors deliberately large (0.05 mm / 0.05 rad): every term must be right, not only
    # the ones that dominate at realistic magnitudes
    for k in range(2):
        q, t, e = random_inputs(m, rng, trans=0.05, ang=0.05)
        syms = [*ch.q, *ch.t, *ch.e]
        vals = [*q, *t, *e]
        p0 = sympy_values(ch.nominal, syms, vals)
        d1 = sympy_values(ch.first_order, syms, vals)
        # SymPy needs ~1 s per point for a 5-axis exact expression: one point there
        px = sympy_values(ch.exact, syms, vals) if k == 0 or m.n_axes <= 3 else None

        p, dp, _ = call(m, "tool_point", q, t, e)
        np.testing.assert_allclose(np.asarray(m["nominal"](q, t)).ravel(), p0, rtol=1e-12,
                                   atol=1e-12)
        np.testing.assert_allclose(dp.ravel(), d1, rtol=1e-10, atol=1e-10 * np.abs(d1).max())
        np.testing.assert_allclose(p.ravel(), p0 + d1, rtol=1e-12, atol=1e-10)
        if px is None:
            continue
        p, dp, _ = call(m, "tool_point_exact", q, t, e)
        np.testing.assert_allclose(p.ravel(), px, rtol=1e-12, atol=1e-10)
        np.testing.assert_allclose(dp.ravel(), px - p0, rtol=1e-10,
                                   atol=1e-10 * np.abs(px - p0).max())


@pytest.mark.parametrize("fname", ["tool_point", "tool_point_exact"])
@pytest.mark.parametrize("name", MODELS)
def test_jacobian_matches_finite_differences(machines, name, fname):
    m = machines[name]
    rng = np.random.default_rng(5)
    q, t, e = random_inputs(m, rng, trans=0.05, ang=0.01)
    J = call(m, fname, q, t, e)[2]
    assert J.shape == (3, m.n_errors)
    h = 1e-5
    Jfd = np.empty_like(J)
    for k in range(m.n_errors):
        ep, em = e.copy(), e.copy()
        ep[k] += h
        em[k] -= h
        Jfd[:, k] = (call(m, fname, q, t, ep)[1] - call(m, fname, q, t, em)[1]).ravel() / (2 * h)
    scale = max(1.0, np.abs(J).max())
    np.testing.assert_allclose(J, Jfd, rtol=0, atol=1e-7 * scale)
    assert np.abs(J).max() > 1.0  # not trivially zero


# --------------------------------------------------------------------------------------
# (c) the build cache


@pytest.mark.parametrize("name", MODELS)
def test_cached_build_is_identical(machines, tmp_path_factory, monkeypatch, name):
    # the cold build is the fixture's (built into an empty cache folder of its own)
    cache = cache_dirs(tmp_path_factory, name)
    monkeypatch.setenv("VOLCAL_CACHE_DIR", str(cache))
    cold = machines[name]
    assert cold.from_cache is False
    entries = list(cache.glob("*.casadi"))
    assert len(entries) == 1
    warm = Machine.from_model(name)
    assert warm.from_cache is True
    assert warm.error_names == cold.error_names
    rng = np.random.default_rng(3)
    for _ in range(3):
        q, t, e = random_inputs(cold, rng, trans=0.01, ang=2e-5)
        for f in ("tool_point", "tool_point_exact"):
            for a, b in zip(call(cold, f, q, t, e), call(warm, f, q, t, e)):
                assert np.array_equal(a, b)
        assert np.array_equal(np.asarray(cold["nominal"](q, t)), np.asarray(warm["nominal"](q, t)))


# --------------------------------------------------------------------------------------
# (d) packaging: every package folder is listed explicitly in pyproject.toml


def test_every_package_is_listed_in_pyproject():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(cfg["packages"])
    src = ROOT / "src"
    found = {".".join(p.parent.relative_to(src).parts)
             for p in (src / "volcal").rglob("__init__.py") if "__pycache__" not in p.parts}
    assert "volcal" in found
    missing = sorted(found - listed)
    assert not missing, f"packages missing from [tool.setuptools] packages: {missing}"
    # and every listed package exists where package-dir maps it
    dirs = cfg.get("package-dir", {})
    for pkg in listed:
        if pkg in dirs:
            folder = ROOT / dirs[pkg]
        else:
            folder = ROOT / dirs.get("", ".") / Path(*pkg.split("."))
        assert (folder / "__init__.py").is_file(), f"{pkg} listed but {folder} is no package"
