"""The numpy kernels of volcal.base.linalg against scipy.linalg, the calls they replace on
``volcal identify``'s path (scipy is the independent reference here: the kernels exist only
so that a short identification does not import it)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import scipy.linalg as sla

from volcal.base.linalg import (
    LAPACK_TPQRT_ROWS,
    StackedQR,
    cholesky_solve,
    cholesky_upper,
    null_space,
    pivot_order,
    solve_triangular,
)


@pytest.mark.parametrize("seed", range(3))
def test_pivot_order_is_lapacks_choice(seed: int) -> None:
    """geqp3's pivots (scipy.linalg.qr(pivoting=True)) on matrices of the shapes the
    identifiability analysis pivots (k null directions x n variables).  (Columns of
    exactly equal norms are a tie the two break differently: the next test.)"""
    rng = np.random.default_rng(seed)
    for _ in range(300):
        k = int(rng.integers(1, 12))
        n = int(rng.integers(k, 120))
        W = rng.standard_normal((k, n))
        W[:, rng.integers(0, n, size=n // 6)] = 0.0  # variables the directions leave out
        expected = sla.qr(W, pivoting=True, mode="economic")[2]
        np.testing.assert_array_equal(pivot_order(W)[:k], expected[:k])


def test_pivot_order_takes_the_first_of_equal_columns() -> None:
    """Of two identical columns (two parameters entering the null directions alike) the
    first is the pivot, whatever their place in memory; LAPACK's choice between copies
    depends on the last bits of its blocked updates."""
    rng = np.random.default_rng(7)
    W = rng.standard_normal((3, 10))
    W[:, 6] = W[:, 2] * 3.0  # the largest column, twice
    W[:, 8] = W[:, 6]
    piv = pivot_order(W)
    assert piv[0] == 6
    assert set(piv) == set(range(10))
    # a column equal to the pivot is left with nothing: chosen last among the first k
    assert 8 not in piv[:2]


def test_null_space_spans_scipys() -> None:
    rng = np.random.default_rng(3)
    for m, n in [(1, 5), (6, 91), (7, 20), (3, 3), (0, 4)]:
        A = rng.standard_normal((m, n))
        if m > 1:
            A[-1] = A[0] + A[1]  # one dependent row: a larger null space
        Z = null_space(A)
        Zs = sla.null_space(A) if m else np.eye(n)
        assert Z.shape == Zs.shape
        np.testing.assert_allclose(Z.T @ Z, np.eye(Z.shape[1]), atol=1e-12)
        np.testing.assert_allclose(Z @ Z.T, Zs @ Zs.T, atol=1e-12)  # the same subspace


def test_triangular_and_cholesky_solves() -> None:
    rng = np.random.default_rng(4)
    n = 40
    R = np.triu(rng.standard_normal((n, n))) + 4.0 * np.eye(n)
    b = rng.standard_normal((n, 3))
    np.testing.assert_allclose(solve_triangular(R, b), sla.solve_triangular(R, b), rtol=1e-12)
    np.testing.assert_allclose(
        solve_triangular(R.T, b, lower=True),
        sla.solve_triangular(R.T, b, lower=True),
        rtol=1e-12,
    )
    M = rng.standard_normal((60, n))
    S = M.T @ M
    U = cholesky_upper(S)
    np.testing.assert_allclose(U, sla.cholesky(S), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(
        cholesky_solve(U, b), sla.cho_solve(sla.cho_factor(S), b), rtol=1e-10
    )
    with pytest.raises(np.linalg.LinAlgError):
        cholesky_upper(-S)


def test_stacked_qr_numpy_and_lapack_streams_agree() -> None:
    """Below LAPACK_TPQRT_ROWS the stream is factorised by numpy, above by tpqrt: the
    same R up to row signs and rounding, and A^T A either way."""
    rng = np.random.default_rng(5)
    A = rng.standard_normal((2000, 30))
    short, long_ = StackedQR(30), StackedQR(30, expected_rows=LAPACK_TPQRT_ROWS)
    for start in range(0, len(A), 300):
        short.add(A[start : start + 300])
        long_.add(A[start : start + 300])
    assert short.rows == long_.rows == len(A)
    np.testing.assert_allclose(np.abs(short.R), np.abs(long_.R), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(short.R.T @ short.R, A.T @ A, rtol=1e-9, atol=1e-8)


def test_a_whole_identification_imports_no_scipy(tmp_path) -> None:
    """`volcal identify` with its default outputs, as the program (its plotting children
    forked from it included: an audit hook is inherited by a fork), imports no scipy
    module at all: scipy's import was ~0.15 s of a run at 10^4 readings.  (Other commands
    may: planning and Monte Carlo import scipy.linalg where they need it.)"""
    sim = tmp_path / "sim"
    subprocess.run(
        [sys.executable, "-m", "volcal", "-q", "simulate", "--example", "mcv754", "--seed", "3",
         "--out", str(sim)],
        check=True, capture_output=True, text=True,
    )  # fmt: skip
    log = tmp_path / "imports.txt"
    code = (
        "import sys\n"
        "def hook(event, args):\n"
        "    if event == 'import' and str(args[0]).split('.')[0] == 'scipy':\n"
        f"        with open({str(log)!r}, 'a') as fh:\n"
        "            fh.write(str(args[0]) + '\\n')\n"
        "sys.addaudithook(hook)\n"
        f"sys.argv = ['volcal', '-q', 'identify', '--model', 'mcv754_wxyzt', '--data',"
        f" {str(sim / 'measurements.csv')!r}, '--out', {str(tmp_path / 'out')!r}]\n"
        "from volcal.cli.main import main\n"
        "sys.exit(main())\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert (tmp_path / "out" / "residuals.png").exists()  # the plotting children ran
    assert not log.exists(), log.read_text()
