"""The identification problem evaluated in fixed-size chunks of poses, without its graph.

:class:`~volcal.problem.residuals.IdentificationProblem` builds, for IPOPT, one CasADi graph
of every reading; its sparsity patterns and index lists are per reading (about 3.4 kB a
reading in CasADi's objects), which at 10^6 readings is several GB and minutes of set-up.
The Gauss-Newton solver and the analyses need only numbers of size n_x or n_x^2 from the
readings: the whitened residuals r, the gradient J^T r, the Gauss-Newton matrix J^T J and
the R factor of J.  :class:`ChunkedEvaluator` computes them from the problem's per-pose
function (the tool point and d(point)/d(theta)) and per-reading function (the weighted
residual and d(r)/d(point, station, globals)), each mapped ONCE over a fixed number of
poses / readings, called chunk by chunk on the data vector p (a last partial chunk is
padded with copies of its last pose or reading, whose outputs are dropped), and sums the
structured products in numpy:

* J^T J's error-parameter block pose by pose, G_p^T (D_p^T D_p) G_p with D_p^T D_p the
  3 x 3 sum over the readings of pose p of d(r)/d(point) d(r)/d(point)^T, as one dense
  product per chunk: 3 n_poses n_theta^2 flops instead of N n_theta^2;
* the station and global columns (one nonzero per reading and parameter) by bincounts
  into dense arrays of the chunk's size;
* R station by station on the columns a reading touches (error parameters, its station's,
  the globals; :class:`volcal.base.linalg.StackedQR`), then the stations' triangles
  together, as :meth:`volcal.problem.residuals.DenseJacobian.r_factor` does.

Memory is O(N) (the data vector, r and the reading-to-pose order) plus one chunk; no
N x n_x array is formed.

Everything runs on the BLAS threads of the process (one for the CLI,
:mod:`volcal.base.threads`): the products of a chunk are small (QRs of a few hundred
rows of n_theta + 4 columns, n_theta x 3 n_poses products), and on the project's shared
2-core machine two OpenBLAS threads made the R factor of 10,296 readings 20x slower
(0.97 s against 0.05 s) and a CasADi thread map of the chain 3x slower, with the other
core busy.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from volcal.model.numpy_call import NumpyCall

#: the largest total size of :meth:`ChunkedEvaluator.gram`'s bincount bins kept between
#: calls (bytes); above it the bins are made again for each chunk and call
GRAM_BINS_KEPT_BYTES = 32 * 2**20

#: the largest size (bytes) of each of what :meth:`ChunkedEvaluator._chunks` keeps between
#: calls: the poses' d(point)/d(theta) when it does not depend on theta, and the outputs
#: of the last pass with derivatives; above it they are evaluated again for each pass.
#: They save a few percent of an identification's time; at 10^4 tracker readings they
#: take 5 MB; at 10^5 readings (32 MB and 44 MB) they are not kept (the first alone
#: raised the peak memory of `volcal identify` by 43 MB, 17 %)
PASS_KEPT_BYTES = 16 * 2**20

__all__ = ["ChunkedEvaluator"]

#: poses per chunk: large enough that the per-chunk Python and call overhead is small
#: against the chain's evaluation, small enough that a chunk's arrays stay in cache-sized
#: megabytes (3 x 512 x n_theta doubles of d(point)/d(theta))
POSE_CHUNK = 512


class ChunkedEvaluator:
    """r, J^T r, J^T J and R of an :class:`~volcal.problem.residuals.IdentificationProblem`
    at scaled x and data p, evaluated in chunks of ``pose_chunk`` poses (see the module
    docstring).  Built once per problem (its CasADi maps on first use, then kept); not
    thread-safe.  (The problem's class is not imported here: the problem builds this
    evaluator, and the layers check refuses an import circle.)"""

    def __init__(self, problem: Any, pose_chunk: int = POSE_CHUNK) -> None:
        self.problem = problem
        lay = problem.layout
        self.n_readings = lay.n_readings
        pose, first = lay.poses
        self.n_poses = Np = len(first)
        self.pose_chunk = int(max(1, min(pose_chunk, Np)))
        self._pose = np.asarray(pose, np.intp)
        self._first = np.asarray(first, np.intp)
        # the readings sorted by pose (stable: within a pose in table order), so that the
        # readings of a chunk of poses are one slice and a pose's readings one segment
        self._order = np.argsort(self._pose, kind="stable")
        self._starts = np.searchsorted(self._pose[self._order], np.arange(Np + 1))
        self._station = np.asarray(lay.station_index, np.intp)
        self._n_st = lay.n_stations
        self._nt, self._n_x = problem.n_theta, problem.n_x
        self._n_ps = problem.instrument.n_station_params
        self._n_g = problem.instrument.n_global_params
        self._n_ax = problem.machine.n_axes
        # the most readings of any chunk of poses: the size of the readings' map
        ends = self._starts[np.minimum(np.arange(0, Np, self.pose_chunk) + self.pose_chunk, Np)]
        self.read_chunk = int(max(1, np.max(ends - self._starts[0 : Np : self.pose_chunk])))
        self._calls: dict[tuple[str, int | None], NumpyCall] = {}
        self._dense: dict[str, ca.Function] = {}
        #: whether d(point)/d(theta) is free of theta (the first-order model: the point is
        #: linear in the error parameters); known once the pose function is built
        self._g_free = False
        #: per chunk of poses (its first pose): its q and t as evaluated and their
        #: d(point)/d(theta) output, while ``_g_free`` and small (PASS_KEPT_BYTES)
        self._g_kept: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        #: the last R factor's pass: (scaled x, p, with G, its chunks), when small, until
        #: the next pass with derivatives (the first Gauss-Newton system at that point)
        self._pass_kept: tuple[np.ndarray, np.ndarray, bool, list] | None = None

    def forget(self) -> None:
        """Drop what :meth:`_chunks` keeps between passes (the poses' d(point)/d(theta),
        the last R factor's pass): an identification does once its uncertainty is known,
        so that the results a caller holds (several strategies compared, a session's
        fits) do not each hold them; a later pass evaluates them again (the same
        numbers)."""
        self._g_kept.clear()
        self._pass_kept = None

    # ---- the mapped functions (built once, on first use) --------------------------------
    def _call(self, kind: str, n: int | None = None) -> NumpyCall:
        """The function of ``kind`` mapped over ``n`` poses / readings (default: a chunk's
        size; the last chunk of poses is evaluated at its own size, without padding).
        Each point is evaluated on its own: the numbers do not depend on the map's size."""
        call = self._calls.get((kind, n))
        if call is None:
            pr = self.problem
            f, size = {
                "pose": (pr.f_pose, self.pose_chunk),
                "point": (pr.f_point, self.pose_chunk),
                "read": (pr.f_read, self.read_chunk),
                "value": (pr.f_res, self.read_chunk),
            }[kind]
            dense = self._dense.get(kind)
            if dense is None:
                # dense outputs (structural zeros stored): the numpy side then reshapes the
                # output buffers instead of scattering their nonzeros chunk after chunk
                sx = f.sx_in()
                outs = f.call(sx)
                if kind == "pose":
                    self._g_free = not ca.depends_on(outs[1], sx[2])
                dense = ca.Function(f.name() + "_dense", sx, [ca.densify(o) for o in outs])
                self._dense[kind] = dense
            # (the first map of a Function costs milliseconds, the next ones microseconds)
            call = self._calls[(kind, n)] = NumpyCall(dense.map(size if n is None else n))
        return call

    # ---- the data vector ----------------------------------------------------------------
    def _split(self, xs: np.ndarray, p: np.ndarray):
        pr, N, n_ax = self.problem, self.n_readings, self._n_ax
        p = np.asarray(p, float).ravel()
        if p.shape != (pr.n_p,):
            raise ValueError(f"p: expected {pr.n_p} values (pack_data), got {p.shape}")
        q = p[: n_ax * N].reshape(N, n_ax)
        t = p[n_ax * N : (n_ax + 3) * N].reshape(N, 3)
        m = p[(n_ax + 3) * N : (n_ax + 4) * N]
        w = p[(n_ax + 4) * N :]
        xs = np.asarray(xs, float).ravel()
        nt, nps = self._nt, self._n_ps
        theta = xs[:nt]
        st = xs[nt : nt + nps * self._n_st].reshape(self._n_st, nps)
        glob = xs[nt + nps * self._n_st :]
        return q, t, m, w, theta, st, glob

    def readings(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(m, w): the readings (N,) and their weights 1/sigma (N,) in the data vector p."""
        n = (self._n_ax + 3) * self.n_readings
        p = np.asarray(p, float).ravel()
        return p[n : n + self.n_readings], p[n + self.n_readings :]

    @staticmethod
    def _pad(a: np.ndarray, n: int) -> np.ndarray:
        """a (k, m) with its last column repeated to n columns (a padded chunk evaluates
        copies of a real pose or reading: no singular point; their outputs are dropped)."""
        k = a.shape[1]
        return a if k == n else np.concatenate([a, np.repeat(a[:, -1:], n - k, axis=1)], 1)

    def _chunks(
        self,
        xs: np.ndarray,
        p: np.ndarray,
        derivatives: bool,
        theta: bool = True,
        keep: bool = False,
    ):
        """Per chunk of poses: (slice of poses, reading indices (pose-sorted), their local
        pose index, r, rows of d(r)/d(point, station, globals) (k, n_r) or None, G
        (n, 3, n_theta) or None).  ``theta=False``: no G (d(point)/d(theta) is not
        evaluated) even with ``derivatives``.  ``keep``: the pass is kept (read-only) for
        the next pass with derivatives, which takes it when it is at the same x with the
        same p."""
        q, t, m, w, theta_v, st, glob = self._split(xs, p)
        Bp, Br, nt = self.pose_chunk, self.read_chunk, self._nt
        with_g = derivatives and theta
        xs = np.asarray(xs, float).ravel()
        p = np.asarray(p, float).ravel()
        if derivatives:
            # a second pass at the same point with the same data (the datum's R factor,
            # then the first Gauss-Newton system at the start point): the kept one
            kept, self._pass_kept = self._pass_kept, None
            if (
                kept is not None
                and (kept[2] or not with_g)
                and np.array_equal(kept[0], xs)
                and np.array_equal(kept[1], p)
            ):
                for ps, idx, pl, r, rows, G in kept[3]:
                    yield ps, idx, pl, r, rows, G if with_g else None
                return
        f_pose = self._call("pose" if with_g else "point")
        f_read = self._call("read" if derivatives else "value")
        # d(point)/d(theta) free of theta: evaluated once per chunk of poses and kept
        # while it is small; the passes after the first evaluate the point alone (the same
        # numbers: the point is the same expression in both functions)
        keep_g = with_g and self._g_free and 8 * 3 * nt * self.n_poses <= PASS_KEPT_BYTES
        f_point = self._call("point") if keep_g and self._g_kept else f_pose
        keep_pass = (
            keep
            and derivatives
            and 8 * ((self._n_ps + self._n_g + 6) * self.n_readings + 3 * nt * self.n_poses)
            <= PASS_KEPT_BYTES
        )
        chunks = []
        TH = np.repeat(theta_v[:, None], max(Bp, 2), axis=1)
        GL = np.repeat(glob[:, None], max(Br, 2), axis=1)
        for a in range(0, self.n_poses, Bp):
            b = min(a + Bp, self.n_poses)
            n = b - a
            fr = self._first[a:b]
            idx = self._order[self._starts[a] : self._starts[b]]
            nr = len(idx)
            # a last chunk at most half full: maps of its own sizes (padded to a whole
            # chunk it evaluated up to a chunk of copies: a sixth of the work at 10^4
            # readings).  Making a map costs about as much as 1-3 of its evaluations,
            # in proportion to its size: for a chunk nearly full, padding costs less.
            small = n <= Bp // 2
            # at least two: a map over one point returns its single-column outputs as
            # vectors (volcal.model.numpy_call), a copy of the point pads it
            Bc, Rc = (max(n, 2), max(nr, 2)) if small else (Bp, Br)
            fp, fq, fr_ = f_pose, f_point, f_read
            if small:
                fp = self._call("pose" if with_g else "point", Bc)
                fq = self._call("point", Bc) if f_point is not f_pose else fp
                fr_ = self._call("read" if derivatives else "value", Rc)
            qc, tc = self._pad(q[fr].T, Bc), self._pad(t[fr].T, Bc)
            g_kept = self._g_kept.get(a) if keep_g else None
            if (
                g_kept is not None
                and np.array_equal(g_kept[0], qc)
                and np.array_equal(g_kept[1], tc)
            ):
                out = [fq(qc, tc, TH[:, :Bc])[0], g_kept[2]]
            else:
                out = fp(qc, tc, TH[:, :Bc])
                if keep_g:
                    out[1].flags.writeable = False  # shared between passes: read-only
                    self._g_kept[a] = (qc, tc, out[1])
            P = out[0]
            pl = self._pose[idx] - a
            sti = self._station[idx]
            args = (
                self._pad(P[:, pl], Rc),
                self._pad(st[sti].T, Rc),
                GL[:, :Rc],
                self._pad(m[idx][None, :], Rc),
                self._pad(w[idx][None, :], Rc),
            )
            res = fr_(*args)
            r = res[0].ravel()[:nr]
            rows = res[1][:, :nr] if derivatives else None
            # G: the transpose of (n_theta, 3 Bp) [G_0^T | G_1^T | ...]
            G = out[1][:, : 3 * n].T.reshape(n, 3, nt) if with_g else None
            item = (slice(a, b), idx, pl, r, rows, G)
            if keep_pass:
                for v in item[1:]:
                    if v is not None:
                        v.flags.writeable = False  # kept for the next pass: read-only
                chunks.append(item)
            yield item
        if keep_pass:  # every chunk evaluated (the caller did not stop early)
            self._pass_kept = (xs.copy(), p.copy(), with_g, chunks)

    # ---- what the solvers and analyses take -----------------------------------------------
    def residuals(self, xs: np.ndarray, p: np.ndarray) -> np.ndarray:
        """The whitened residuals r (N,) at scaled x, in the order of the readings."""
        r = np.empty(self.n_readings)
        for _, idx, _, rc, _, _ in self._chunks(xs, p, derivatives=False):
            r[idx] = rc
        return r

    def objective(self, xs: np.ndarray, p: np.ndarray) -> float:
        """0.5 ||r||^2 at scaled x."""
        r = self.residuals(xs, p)
        return 0.5 * float(r @ r)

    def _rest_columns(self, idx: np.ndarray) -> np.ndarray:
        """(n_r, n_ps + n_g): each reading's columns among the station and global ones
        (counted from the first of them), in the order of its derivative rows 3.."""
        nps, ng = self._n_ps, self._n_g
        return np.concatenate(
            [
                nps * self._station[idx][:, None] + np.arange(nps)[None, :],
                np.broadcast_to(nps * self._n_st + np.arange(ng), (len(idx), ng)),
            ],
            axis=1,
        )

    def _gram_index(self, start: int, idx: np.ndarray, pl: np.ndarray) -> dict[str, np.ndarray]:
        """The bins of :meth:`gram`'s bincounts for the chunk of poses from ``start`` (they
        depend on the layout only: made once per chunk and kept): a reading's station and
        global columns (``a``) and their pairs (``aa``, upper triangle: a reading's
        columns increase, and the lower triangle's sums are the same products in the same
        order), its pose's 3 point rows (``d``),
        their pairs (``dd``, the pose's 3 x 3 block) and the point rows times the columns
        (``da``)."""
        cache: dict = self.__dict__.setdefault("_gram_bins", {})
        ix = cache.get(start)
        if ix is None:
            n_rest = self._n_x - self._nt
            cols = self._rest_columns(idx)  # (n_r, L)
            c3 = np.arange(3)
            iu, ju = np.triu_indices(cols.shape[1])
            ix = {
                "a": cols.ravel(),
                "aa": (cols[:, iu] * n_rest + cols[:, ju]).ravel(),
                "d": (3 * pl[:, None] + c3[None, :]).ravel(),
                "dd": (9 * pl[:, None, None] + 3 * c3[None, :, None] + c3[None, None, :]).ravel(),
                "da": (
                    (3 * pl[:, None, None] + c3[None, :, None]) * n_rest + cols[:, None, :]
                ).ravel(),
            }
            # kept only while all chunks' bins stay small (the many small solves of a
            # Monte Carlo trial, where making them costs more than the sums): they take
            # 8 (L (L + 1) / 2 + 4 L + 12) bytes per reading, 0.8 GB at 10^6 tracker
            # readings (L = 10: 4 station and 6 global columns), more than the rest of a
            # large identification holds
            L = cols.shape[1]
            if 8 * (L * (L + 1) // 2 + 4 * L + 12) * self.n_readings <= GRAM_BINS_KEPT_BYTES:
                cache[start] = ix
        return ix

    def gram(
        self, xs: np.ndarray, p: np.ndarray, *, theta: bool = True
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(r (N,), J^T r (n_x,), J^T J (n_x, n_x)) at scaled x: the Gauss-Newton system,
        the same numbers as the problem's whole-graph ``gram`` to rounding.  With J =
        [D G_stack | A] per chunk: J^T J = [G^T (D^T D) G, G^T (D^T A); ., A^T A], where
        D^T D is block diagonal (3 x 3 per pose): 3 n_poses n_theta^2 flops, not N
        n_theta^2.  The sums over a chunk's readings of the few nonzeros each reading has
        (its 3 point derivatives, its station's and the global ones) are bincounts into
        dense arrays of the chunk's size: for the small chunks of a Monte Carlo trial a
        sparse matrix product costs more in its construction than in its arithmetic.

        ``theta=False`` (a solve that holds every error parameter, e.g. a strategy's
        station phase): the error-parameter rows and columns of J^T r and J^T J are left
        at zero and d(point)/d(theta) is not evaluated, the costly part of a chunk."""
        nt, n = self._nt, self._n_x
        L = self._n_ps + self._n_g
        n_rest = n - nt
        iu, ju = np.triu_indices(L)
        r = np.empty(self.n_readings)
        g = np.zeros(n)
        H = np.zeros((n, n))
        for ps, idx, pl, rc, rows, G in self._chunks(xs, p, derivatives=True, theta=theta):
            r[idx] = rc
            k = ps.stop - ps.start
            d, a = rows[:3], rows[3 : 3 + L]  # (3, n_r) d(r)/d(point); (L, n_r) the rest
            ix = self._gram_index(ps.start, idx, pl)
            g[nt:] += np.bincount(ix["a"], (a * rc[None, :]).T.ravel(), n_rest)
            aT = a.T
            H[nt:, nt:] += np.bincount(
                ix["aa"], (aT[:, iu] * aT[:, ju]).ravel(), n_rest * n_rest
            ).reshape(n_rest, n_rest)
            if G is None:
                continue
            Gf = G.reshape(-1, nt)  # G_stack of the chunk (3 k, n_theta)
            dT = d.T
            # D^T r (3 k,) and D^T D (k, 3, 3): per pose, sums over its readings
            Dr = np.bincount(ix["d"], (dT * rc[:, None]).ravel(), 3 * k)
            M = np.bincount(ix["dd"], (dT[:, :, None] * dT[:, None, :]).ravel(), 9 * k)
            # D^T A (3 k, n_rest): reading i adds d_c(i) a_j(i) at (3 pose + c, column j)
            DtA = np.bincount(
                ix["da"], (dT[:, :, None] * a.T[:, None, :]).ravel(), 3 * k * n_rest
            ).reshape(3 * k, n_rest)
            g[:nt] += Gf.T @ Dr
            H[:nt, :nt] += Gf.T @ (M.reshape(k, 3, 3) @ G).reshape(-1, nt)
            H[:nt, nt:] += Gf.T @ DtA
        H[nt:, nt:] += np.triu(H[nt:, nt:], 1).T  # the lower triangle: the same sums
        H[nt:, :nt] = H[:nt, nt:].T
        # G^T (D^T D G) is symmetric but for rounding; exactly so for the solvers
        H[:nt, :nt] = 0.5 * (H[:nt, :nt] + H[:nt, :nt].T)
        return r, g, H

    def r_factor(self, xs: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(r, R)``: the whitened residuals (N,) and the R factor (n_x, n_x) of J
        (``J = Q R`` up to row signs), accumulated station by station on the columns a
        reading touches and then together (module docstring); J is never held."""
        from volcal.base.linalg import StackedQR

        nt, nps, ng, n_st = self._nt, self._n_ps, self._n_g, self._n_st
        width = nt + nps + ng
        r = np.empty(self.n_readings)
        acc = [StackedQR(width, expected_rows=self.n_readings) for _ in range(n_st)]
        # kept: Gauss-Newton's first system is often at the point of the datum's R factor
        for _ps, idx, pl, rc, rows, G in self._chunks(xs, p, derivatives=True, keep=True):
            r[idx] = rc
            sti = self._station[idx]
            o = np.argsort(sti, kind="stable")
            # the chunk's rows station by station: [D G_stack | station's, globals], a
            # reading's theta row being sum_c d(r)/d(p_c) d(p_c)/d(theta) of its pose
            Jb = np.empty((len(idx), width))
            # G is a view whose last axis strides over the whole output buffer: gathered
            # as it is, the product took 7x longer (8 ms against 1.2 ms a chunk of 512 poses)
            Jb[:, :nt] = np.einsum("cr,rct->rt", rows[:3, o], np.ascontiguousarray(G)[pl[o]])
            Jb[:, nt:] = rows[3 : 3 + nps + ng, o].T
            bounds = np.searchsorted(sti[o], np.arange(n_st + 1))
            for j in np.flatnonzero(np.diff(bounds)):
                acc[j].add(Jb[bounds[j] : bounds[j + 1]])
        top = StackedQR(self._n_x)
        for k in range(n_st):
            if acc[k].rows:
                cols = np.concatenate(
                    [
                        np.arange(nt),
                        nt + nps * k + np.arange(nps),
                        nt + nps * n_st + np.arange(ng),
                    ]
                )
                Rk = np.zeros((width, self._n_x))
                Rk[:, cols] = acc[k].R
                top.add(Rk)
        return r, top.R
