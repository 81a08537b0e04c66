"""The plain scipy script a competent user would write for the same identification.

    python benchmarks/scipy_reference.py DATA.csv STATIONS.csv --model mcv754_wxyzt \
        --out params.csv [--config trf_exact] [--timings timings.json]

Same model and data as ``volcal identify``: volcal's first-order model of the machine is
used *only* to get, per distinct pose, the nominal tool point p0 and its derivative G with
respect to the error parameters (cubic Legendre basis), so the model is the same on both
sides; everything else is what a user writes with numpy and scipy:

* residuals r = (||p0 + G theta - S_k|| - d_k - L) / sigma, sigma from the table;
* the analytic Jacobian: a dense array (``trf_exact``, ``lm``: 78 error columns and the
  free station columns) or a scipy.sparse CSR matrix (``trf_lsmr``: the error columns
  dense, the station columns one nonzero per reading);
* no datum: six station coordinates are held (3-2-1) to fix the rigid motion no
  multilateration sees, every error parameter is free (the minimiser is not unique where
  the data cannot see a combination; least_squares then returns one of them);
* ``scipy.optimize.least_squares(x_scale="jac", max_nfev=100)`` in one of the
  configurations :data:`CONFIGS` (``--config``): ``trf_exact`` (method="trf", dense, exact trust-region
  solver: scipy's default), ``lm`` (MINPACK's Levenberg-Marquardt), ``trf_lsmr``
  (method="trf", tr_solver="lsmr", sparse), each with scipy's default tolerances or
  with tight ones (``*_tight``: xtol = ftol = 1e-12, gtol = 1e-10);
* the covariance of the free parameters from the Jacobian at the solution (dense
  pseudo-inverse of J^T J, what a user would write);
* a CSV of the parameters and their standard uncertainties.

Stage timings (s) are written to ``--timings`` as JSON.
"""

from __future__ import annotations

import argparse
import json
import time

T0 = time.perf_counter()

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import scipy.optimize as so  # noqa: E402
import scipy.sparse as sps  # noqa: E402

TIGHT = {"xtol": 1e-12, "ftol": 1e-12, "gtol": 1e-10}
#: configuration name -> (least_squares options, dense Jacobian)
CONFIGS = {
    "trf_exact": ({"method": "trf", "tr_solver": "exact"}, True),
    "trf_exact_tight": ({"method": "trf", "tr_solver": "exact", **TIGHT}, True),
    "lm": ({"method": "lm"}, True),
    "lm_tight": ({"method": "lm", **TIGHT}, True),
    "trf_lsmr": ({"method": "trf", "tr_solver": "lsmr"}, False),
    "trf_lsmr_tight": ({"method": "trf", "tr_solver": "lsmr", **TIGHT}, False),
}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("data")
    ap.add_argument("stations")
    ap.add_argument("--model", default="mcv754_wxyzt")
    ap.add_argument("--out", required=True)
    ap.add_argument("--timings")
    ap.add_argument("--config", choices=list(CONFIGS), default="trf_exact")
    a = ap.parse_args()
    options, dense = CONFIGS[a.config]
    t = {"imports": time.perf_counter() - T0}

    t0 = time.perf_counter()
    meas = pd.read_csv(a.data)
    st = pd.read_csv(a.stations)
    t["read"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    from volcal.model.errors import ErrorModel
    from volcal.model.machine import Machine

    machine = Machine.from_model(a.model)
    em = ErrorModel(machine.spec)
    names = [ax.name for ax in machine.spec.axes]
    cols = [f"{n}_mm" if f"{n}_mm" in meas else n for n in names]
    q = meas[cols].to_numpy(float)
    tool = meas[[c for c in ("tool_x_mm", "tool_y_mm", "tool_z_mm") if c in meas]
                or ["tool_x", "tool_y", "tool_z"]].to_numpy(float)
    L = meas["length_mm" if "length_mm" in meas else "length"].to_numpy(float)
    sigma = meas["sigma_mm" if "sigma_mm" in meas else "sigma"].to_numpy(float)
    uniq, inv = np.unique(np.column_stack([q, tool]), axis=0, return_inverse=True)
    inv = inv.ravel()
    p0u, _, Je = machine.evaluate(uniq[:, : len(names)], uniq[:, len(names) :],
                                  np.zeros(machine.n_errors))
    Gu = np.einsum("nik,nkp->nip", Je, em.basis(uniq[:, : len(names)]))
    t["model"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    ids = list(st["station"])
    si = np.array([ids.index(s) for s in meas["station"]])
    K, P, N = len(ids), Gu.shape[2], len(L)
    S0 = st[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
    d0 = st["dead_length_mm"].to_numpy(float) if "dead_length_mm" in st else np.zeros(K)
    # hold 3-2-1 station coordinates: the rigid motion between stations and machine
    hold = [P + 0, P + 1, P + 2, P + 4, P + 5, P + 8]
    n_x = P + 4 * K
    free = np.setdiff1d(np.arange(n_x), hold)
    x_full = np.concatenate([np.zeros(P), S0.ravel(), d0])
    w = 1.0 / sigma
    rows = np.arange(N)
    G = Gu[inv]
    p0 = p0u[inv]

    def full(z):
        x = x_full.copy()
        x[free] = z
        return x[:P], x[P : P + 3 * K].reshape(K, 3), x[P + 3 * K :]

    def fun(z):
        th, S, d = full(z)
        v = p0 + G @ th - S[si]
        return (np.linalg.norm(v, axis=1) - d[si] - L) * w

    # sparsity of the Jacobian: dense error columns, one station per reading
    err_r = np.repeat(rows, P)
    err_c = np.tile(np.arange(P), N)
    st_r = np.repeat(rows, 4)
    st_c = np.column_stack([P + 3 * si, P + 3 * si + 1, P + 3 * si + 2, P + 3 * K + si]).ravel()
    r_idx = np.concatenate([err_r, st_r])
    c_idx = np.concatenate([err_c, st_c])
    keep_col = np.full(n_x, -1)
    keep_col[free] = np.arange(len(free))

    def jac_sparse(z):
        th, S, d = full(z)
        v = p0 + G @ th - S[si]
        u = v / np.linalg.norm(v, axis=1)[:, None]
        ve = np.einsum("ni,nip->np", u, G) * w[:, None]
        vs = np.column_stack([-u * w[:, None], -w])
        vals = np.concatenate([ve.ravel(), vs.ravel()])
        c = keep_col[c_idx]
        m = c >= 0
        return sps.csr_matrix((vals[m], (r_idx[m], c[m])), shape=(N, len(free)))

    # the station columns of each reading in the dense Jacobian (-1: held)
    st_cols = keep_col[np.column_stack([P + 3 * si, P + 3 * si + 1, P + 3 * si + 2,
                                        P + 3 * K + si])]

    def jac_dense(z):
        th, S, d = full(z)
        v = p0 + G @ th - S[si]
        u = v / np.linalg.norm(v, axis=1)[:, None]
        J = np.zeros((N, len(free)))
        J[:, :P] = np.einsum("ni,nip->np", u, G) * w[:, None]  # error columns: all free
        vs = np.column_stack([-u * w[:, None], -w])
        for k in range(4):
            m = st_cols[:, k] >= 0
            J[rows[m], st_cols[m, k]] = vs[m, k]
        return J

    t["setup"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    sol = so.least_squares(fun, x_full[free], jac=jac_dense if dense else jac_sparse,
                           x_scale="jac", max_nfev=100, **options)
    t["solve"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    J = sol.jac.toarray() if sps.issparse(sol.jac) else np.asarray(sol.jac)
    cov = np.linalg.pinv(J.T @ J)
    u = np.sqrt(np.clip(np.diag(cov), 0, None))
    t["covariance"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    th, S, d = full(sol.x)
    pd.DataFrame({"name": em.param_names, "value": th,
                  "u": u[: P] if len(free) >= P else np.nan}).to_csv(a.out, index=False)
    t["write"] = time.perf_counter() - t0
    t["total_in_process"] = time.perf_counter() - T0
    t["nfev"] = int(sol.nfev)
    t["cost"] = float(sol.cost)
    t["status"] = int(sol.status)
    t["config"] = a.config
    if a.timings:
        with open(a.timings, "w") as fh:
            json.dump(t, fh)


if __name__ == "__main__":
    main()
