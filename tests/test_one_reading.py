"""One definition of each instrument's reading (issue 30).

The places in src/ that compute a distance reading are found on the AST: a distance of a
difference (``norm(a - b)``, ``sqrt(sumsqr(a - b))``, ``sqrt(sum((a - b)**2))``,
``sqrt(einsum(.., d, d))``, also through local names) from which something is subtracted
(the dead length, the reading), also written in place (``np.subtract(P, Q, out=D)``,
``np.multiply(D[0], D[0], out=L)``, ``np.sqrt(L, out=L)``, ``np.subtract(L, d, out=r)``).
Each instrument module holds exactly one; outside the instruments only the places listed
in ``REMAINING`` may, each with the reason it is still there (and each is still found: a
stale entry fails too).  A new copy of the reading anywhere else fails this test."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "volcal"
INSTRUMENTS = SRC / "measurement" / "instruments"

#: files outside the instruments that still write a distance reading, and why
REMAINING = {
    # paper 002's linear and Gauss-Newton multilateration, vectorised over thousands of
    # small problems (start values of the tracker's stations, the classic pipeline)
    "measurement/multilateration.py",
    # the Monte Carlo engine's batched gradient (StructuredLSQ._gradient_t), most of a Monte
    # Carlo run's time: the tracker's reading in place, station by station.  Its readings,
    # residuals and Jacobian evaluate the instrument's Function (a numpy tape); evaluating it
    # in the gradient too cost 12-20x this time mapped by CasADi (serial), ~4x as jit-compiled
    # C, ~2.5x replayed by the tape (measured on B = 200 trials of the bundled example, the
    # engine's module docstring).  Compared with the problem's CasADi functions whenever an
    # engine is built (StructuredLSQ.build(check=True))
    "analysis/uncertainty/engine.py",
}


#: instrument modules whose reading is not a distance (the finder sees none in them)
NOT_A_DISTANCE = {
    # a projection on the beam: v . P - offset
    "measurement/instruments/interferometer.py",
    # selects its parts' readings, written in their own modules
    "measurement/instruments/combined.py",
}


def _name(call: ast.Call) -> str:
    f = call.func
    return f.attr if isinstance(f, ast.Attribute) else (f.id if isinstance(f, ast.Name) else "")


def _is_sub(e: ast.AST) -> bool:
    return isinstance(e, ast.BinOp) and isinstance(e.op, ast.Sub)


def reading_lines(source: str) -> list[int]:
    """Line numbers where ``source`` subtracts something from a distance of a difference."""
    hits: set[int] = set()
    for fn in ast.walk(ast.parse(source)):
        if isinstance(fn, ast.FunctionDef):
            hits |= _function_hits(fn)
    return sorted(hits)


def _function_hits(fn: ast.FunctionDef) -> set[int]:
    hits: set[int] = set()
    assigns = [
        n
        for n in ast.walk(fn)
        if isinstance(n, ast.Assign) and len(n.targets) == 1 and isinstance(n.targets[0], ast.Name)
    ]
    diffs: set[str] = set()
    dists: set[str] = set()
    sumsq: set[str] = set()  # sums of squares of a difference's components, in place

    def is_diff(e: ast.AST) -> bool:
        if isinstance(e, ast.Subscript):  # a component of a difference
            e = e.value
        return _is_sub(e) or (isinstance(e, ast.Name) and e.id in diffs)

    def out_name(call: ast.Call) -> str | None:
        for kw in call.keywords:
            if kw.arg == "out" and isinstance(kw.value, ast.Name):
                return kw.value.id
        return None

    # in-place forms: D written by np.subtract(.., out=D) or D -= ..; L by
    # np.multiply(D[i], D[i], out=L) or np.square(D[i], out=L); then np.sqrt(L, out=L)
    nodes = list(ast.walk(fn))
    for n in nodes:
        if isinstance(n, ast.AugAssign) and isinstance(n.op, ast.Sub):
            if isinstance(n.target, ast.Name):
                diffs.add(n.target.id)
    in_place = [(n, out) for n in nodes if isinstance(n, ast.Call) and (out := out_name(n))]
    for _ in range(3):
        for n, out in in_place:
            name = _name(n)
            if name == "subtract" and len(n.args) >= 2 and out not in sumsq | dists:
                if not (n.args and isinstance(n.args[0], ast.Name) and n.args[0].id in dists):
                    diffs.add(out)
            elif name in ("multiply", "square") and n.args and all(map(is_diff, n.args)):
                sumsq.add(out)
            elif name == "sqrt" and n.args and isinstance(n.args[0], ast.Name):
                if n.args[0].id in sumsq:
                    dists.add(out)

    def is_dist(e: ast.AST) -> bool:
        if isinstance(e, ast.Name):
            return e.id in dists
        if not isinstance(e, ast.Call) or not e.args:
            return False
        name, a = _name(e), e.args[0]
        if name in ("norm", "norm_2"):
            return is_diff(a)
        if name != "sqrt" or not isinstance(a, ast.Call) or not a.args:
            return False
        inner = _name(a)
        if inner == "sumsqr":
            return is_diff(a.args[0])
        if inner == "sum":
            b = a.args[0]
            return isinstance(b, ast.BinOp) and isinstance(b.op, ast.Pow) and is_diff(b.left)
        return inner == "einsum" and len(a.args) == 3 and all(map(is_diff, a.args[1:]))

    for _ in range(3):  # names defined from names
        for n in assigns:
            target = n.targets[0].id  # type: ignore[attr-defined]
            if is_diff(n.value):
                diffs.add(target)
            if is_dist(n.value):
                dists.add(target)
    for n in ast.walk(fn):
        if _is_sub(n) and is_dist(n.left):  # type: ignore[attr-defined]
            hits.add(n.lineno)
        if isinstance(n, ast.Call) and _name(n) == "subtract" and n.args:
            if is_dist(n.args[0]):
                hits.add(n.lineno)
    return hits


def test_the_finder_sees_the_forms_the_reading_was_written_in():
    """The copies this issue removed (classic, the export's nominal lengths, the C
    solver's station start) are found; a distance nothing is subtracted from is not."""
    old_classic = "def f(p, Sm, d, i):\n    return np.linalg.norm(p - Sm[i], axis=1) - d[i]\n"
    old_solver = (
        "def f(us, ps, ls):\n    diff = us[:3] - ps\n    dist = ca.sqrt(ca.sumsqr(diff))\n"
        "    rr = dist - us[3] - ls\n    return rr\n"
    )
    batched = (
        "def f(P, Q, d, out):\n    D = P - Q\n    L = np.sqrt(np.einsum('ni,ni->n', D, D))\n"
        "    np.subtract(L, d, out=out)\n"
    )
    # the Monte Carlo engine's gradient, in place (its form before and after this finder)
    in_place = (
        "def f(P, Q, S, D, L, t, r):\n    np.subtract(P, Q[:, None, :], out=D)\n"
        "    np.multiply(D[0], D[0], out=L)\n    np.multiply(D[1], D[1], out=t)\n"
        "    L += t\n    np.sqrt(L, out=L)\n    np.subtract(L, S[3][None, :], out=r)\n"
        "    np.take(r, [0], axis=0, out=t)\n    r -= t\n"
    )
    assert reading_lines(old_classic) == [2]
    assert reading_lines(old_solver) == [4]
    assert reading_lines(batched) == [4]
    assert reading_lines(in_place) == [7]
    assert reading_lines("def f(u):\n    return u / ca.sqrt(ca.sumsqr(u - 1))\n") == []


def test_each_instrument_writes_its_reading_once_and_nothing_else_does():
    found = {
        str(p.relative_to(SRC)): lines
        for p in sorted(SRC.rglob("*.py"))
        if (lines := reading_lines(p.read_text()))
    }
    instruments = [
        str(p.relative_to(SRC))
        for p in sorted(INSTRUMENTS.glob("*.py"))
        if p.name not in ("__init__.py", "base.py")
    ]
    for rel in instruments:
        expected = 0 if rel in NOT_A_DISTANCE else 1
        assert len(found.get(rel, [])) == expected, (
            f"{rel}: reading written at lines {found.get(rel)}"
        )
    elsewhere = {rel: lines for rel, lines in found.items() if rel not in instruments}
    assert set(elsewhere) <= REMAINING, (
        "a reading is written outside its instrument (evaluate the instrument's reading "
        f"Function instead): {elsewhere}"
    )
    stale = REMAINING - set(elsewhere)
    assert not stale, f"no reading found any more in {stale}: take it off REMAINING"
    # in the engine only the batched gradient
    assert len(elsewhere["analysis/uncertainty/engine.py"]) == 1, elsewhere


def test_each_instruments_reading_is_the_length_numpy_computes():
    """The one reading Function of each instrument, evaluated on random points, stations
    and frames, against the length written here with numpy and scipy (tracker: the
    station moved by the small frame motion t + w x Q; multilaser: R = Rz Ry Rx, scipy's
    extrinsic x-y-z Euler angles), and its gradient against the unit beam vector."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from volcal.measurement.instruments import get_instrument

    rng = np.random.default_rng(30)
    n = 50
    P = rng.uniform(-500, 500, (n, 3))
    S = np.column_stack([rng.uniform(-2000, 2000, (n, 3)), rng.uniform(-1, 1, n)])
    g = np.r_[rng.uniform(-2, 2, 3), rng.uniform(-1e-3, 1e-3, 3)]

    tracker = get_instrument("tracker")
    v, d = tracker.evaluate(P, S, g)
    Q = S[:, :3] + g[:3] + np.cross(g[3:], S[:, :3])
    D = P - Q
    L = np.linalg.norm(D, axis=1)
    assert np.allclose(v, L - S[:, 3], rtol=0, atol=1e-9)
    assert np.allclose(d, D / L[:, None], rtol=0, atol=1e-12)

    laser = get_instrument("multilaser")
    g = np.r_[rng.uniform(-50, 50, 3), rng.uniform(-0.3, 0.3, 3)]
    v, d = laser.evaluate(P, S, g)
    R = Rotation.from_euler("xyz", g[3:]).as_matrix()
    D = P @ R.T + g[:3] - S[:, :3]
    L = np.linalg.norm(D, axis=1)
    assert np.allclose(v, L - S[:, 3], rtol=0, atol=1e-9)
    assert np.allclose(d, (D / L[:, None]) @ R, rtol=0, atol=1e-12)
