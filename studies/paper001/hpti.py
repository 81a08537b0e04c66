"""Paper 001's simultaneous three-laser telescopic instrument (HPTI): the study's simulator,
noise model, solvers and trial runner.

Study code (it moved here from ``volcal.analysis.multilaser``): the library's instrument is
:class:`volcal.measurement.instruments.multilaser.MultiLaserInstrument`, whose CasADi reading
the estimator below evaluates; the study's own NLP (points as unknowns, the Levenberg-damped
solve of the rank-deficient joint problem, the variable scalings its tables compare) is not
a volcal problem, see studies/paper001/README.md.

Aguado, Brosed, Acero, Aguilar, Santolaria, Pueo, "Influence of high precision telescopic
instrument characterization on multilateration points accuracy", IOP Conf. Ser. Mater. Sci.
Eng. 1193 (2021) 012061.  Units: mm, rad, s inside the code; reported errors in um.

Observation model
-----------------
Frames: the machine frame (MTCRS, where the nominal points are given) and the instrument
frame (ICRS), built from the lasers themselves (paper sec. 3): the origin of laser 1 is the
origin, the origin of laser 2 lies on the x axis, the origin of laser 3 in the xy plane::

    Q1 = (0, 0, 0),   Q2 = (x1, 0, 0),   Q3 = (x2, y2, 0)          (mm, ICRS)

so that the 9 laser coordinates reduce to the 3 parameters ``x1, x2, y2`` (the 6 others are
the gauge of the instrument frame, fixed by that convention).  The frame parameters
``instrument_T_machine = (tx, ty, tz, rx, ry, rz)`` (mm, rad) map a machine point into the
instrument frame, eq. (5)::

    P_I = R(rx, ry, rz) P_M + t,    R = Rz(rz) Ry(ry) Rx(rx)   (exact rotation)

Reading of laser i at point p, eq. (1), (4), (9): the physical (moorage to moorage) length is
the interferometer reading plus the laser's two fixed offsets ``d_mi + d_rm`` (one number per
laser here, ``offset_i``), hence::

    reading_ip = ||P_I,p - Q_i|| - offset_i        (+ noise, see below)

(eq. 14 of the paper adds the offsets to the computed length instead; eq. 1/4/9, which define
them, subtract them from the moorage distance; only the sign convention of ``offset_i``
differs.)

Inter-laser distances (eq. 10-12): with ``d_ij`` the distance from laser i to the origin of
laser j, ``x1 = d12``, ``x2 = (d12^2 + d13^2 - d23^2) / (2 d12)``, ``y2 = sqrt(d13^2 - x2^2)``
(the text extraction of eq. 12 lost the square of x2; this is the law of cosines).

Noise (section 5)
-----------------
Eq. (2) models drift and vibration as ``f(t) = sum_k A_k sin(w_k t + phi_k)`` with amplitudes
1.77e-6 ... 8.939e-6 that the paper gives without unit.  They are read in **metres** (1.8 to
8.9 um; standard deviation of f ``sqrt(sum A^2 / 2) = 8.4 um``, |f| <= 27.0 um), t in s and
w in rad/s (6.283 rad/s = 1 Hz): this is :data:`volcal.analysis.uncertainty.PAPER001_DRIFT`, and the
only reading under which the paper's sphere-intersection errors (6.5 um mean, 24.8 um max) are
possible.  Eq. (3) adds f(t) to the length outside the square root; eq. (6)-(8), used for the
paper's tests in the ICRS, print it under the root, where (lengths in mm) it changes a length
by f / (2 L), below 0.01 um.

:class:`NoiseModel` (all seeded by the caller's Generator):

* each realisation (trial) draws new phases of f (a stationary process with the paper's
  spectrum);
* ``drift_mode="common"`` (default, eq. 3 literally: one f(t) with no laser index, the three
  lasers reading at the same instant) adds the same f(t_p) to the three readings of point p;
  ``"per_laser"`` gives each laser its own phases;
* ``drift_on_readings``: True adds f to every point reading (eq. 3); False leaves the point
  readings without it (eq. 6-8 as printed; with it the paper's Table 1 is reproduced, see
  studies/paper001/README.md);
* point p is read at ``t_p = (p + 1 + U(0, 1)) dwell_s`` (a random instant inside its dwell
  window; with readings exactly on whole seconds the near-integer-Hz terms of eq. 2 would
  alias to a constant);
* the inter-laser distances d12, d13, d23 are measured by the instrument too, in one cycle at
  one instant before the mesh (laser 1 reads d12 and d13, laser 2 reads d23), always with f
  and the white noise: the analytic x1, x2, y2 are therefore uncertain (paper sec. 5, "as
  these values should be obtained with the own instrument, measured values have to be
  affected by equation (2)");
* ``length_sigma_mm``: white Gaussian noise per reading (an assumption: the paper only quotes
  the 5 pm interferometer resolution);
* ``offset_sigma_mm``: error of the characterised offsets (0: known exactly, as the paper
  assumes).

Strategies (:class:`HPTIEstimator`)
-----------------------------------
One IPOPT NLP per layout (number of points), built once, with the data as parameters and a
Gauss-Newton ``hess_lag``; every strategy is a choice of free variables (equal bounds fix the
others), so nothing is rebuilt between strategies or trials.

Variables ``x = [P_M (3N), frame (6), x1 x2 y2, offset1..3]``, scaled so that one unit is 1 um
(or 1 urad) and measured from a reference vector passed in ``p`` (the start values).

``"sphere"``: closed-form intersection of the three spheres
    (:func:`volcal.measurement.multilateration.multilaterate`, ``method="sphere"``) with the
    analytic laser origins and the characterised offsets; the root above the laser plane.
``"points-only"``: points free, instrument fixed at its analytic values (eq. 10-12).
``"two-phase"``: phase 1 estimates the instrument (by default frame, x1 x2 y2 and offsets;
    the paper: x1 x2 y2 only) with the points held at their reference values (the start
    values) on a calibration subset; phase 2 the points with the instrument fixed.
``"joint"``: points with x1 x2 y2 (by default also the offsets, and the frame) at once.

Gauge freedoms are detected, not hard-coded: before a solve the Jacobian at the start is
analysed (:func:`volcal.analysis.analyse_jacobian`) over the free point and frame columns; the
null directions there (the rigid motion of the point set against the instrument frame: 6)
are fixed by holding their pivot variables (the frame parameters are preferred).  What
remains rank deficient after that is reported (``unidentifiable``): in the joint problem every
instrument parameter trades against the points (3N readings cannot determine 3N + 3 or
3N + 6 unknowns).  Those directions are either fixed as well (``fix_unidentifiable``) or
left to a slightly damped Gauss-Newton (Levenberg term ``1e-5 * mean diag(J^T J)``): the
answer is then the start values plus (nearly) minimum-norm corrections, in the metric of the
variable scaling -- which is what the paper's joint optimisation computes.

Initial accuracy (Table 1, first column: "Initial data accuracy vs nominal point (%)", "the
difference in percentage from initial optimization values and the actual point's position
(defined by their nominal values)"): the start values of the points are ``a * P_nominal``
(machine-frame coordinates scaled by a = 1.00, 0.95, 0.90).  With ``scale_instrument=True``
the start values of x1 x2 y2 and the offsets are scaled by a too (another reading of the
column); the points-only strategy always fixes the instrument at its analytic values.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import casadi as ca
import numpy as np

from volcal.analysis import analyse_jacobian
from volcal.base.threads import set_blas_threads
from volcal.measurement.budget import PAPER001_DRIFT, DriftModel
from volcal.measurement.instruments.multilaser import FRAME_NAMES, MultiLaserInstrument
from volcal.measurement.multilateration import multilaterate

__all__ = [
    "LASERS",
    "FRAME_NAMES",
    "GEOMETRY_NAMES",
    "OFFSET_NAMES",
    "STRATEGIES",
    "rotation_matrix",
    "laser_origins",
    "geometry_from_distances",
    "distances_from_geometry",
    "MultiLaserInstrument",
    "HPTI",
    "NoiseModel",
    "Experiment",
    "HPTIData",
    "paper_mesh",
    "section5_experiment",
    "simulate",
    "HPTIEstimator",
    "CoreEstimator",
    "ESTIMATORS",
    "point_cloud_spec",
    "JacobianReport",
    "Estimate",
    "trial_rng",
    "StudyRunner",
    "TrialKernel",
    "Case",
    "cases_from_config",
    "experiment_from_config",
    "noise_from_config",
]

LASERS = ("laser1", "laser2", "laser3")
GEOMETRY_NAMES = ("x1_mm", "x2_mm", "y2_mm")
OFFSET_NAMES = ("offset1_mm", "offset2_mm", "offset3_mm")
STRATEGIES = ("sphere", "points-only", "two-phase", "joint")
#: who solves the NLP strategies of the study: volcal's core or the study's own IPOPT problem
ESTIMATORS = ("core", "study")
GROUPS = ("points", "frame", "geometry", "offsets")


# --------------------------------------------------------------------------------------
# geometry helpers (numpy)


def rotation_matrix(r: Sequence[float]) -> np.ndarray:
    """R = Rz(rz) Ry(ry) Rx(rx) for r = (rx, ry, rz) in rad (numpy)."""
    rx, ry, rz = (float(v) for v in r)
    cx, sx, cy, sy, cz, sz = (
        math.cos(rx),
        math.sin(rx),
        math.cos(ry),
        math.sin(ry),
        math.cos(rz),
        math.sin(rz),
    )
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def laser_origins(geometry: Sequence[float]) -> np.ndarray:
    """(3, 3) laser origins in the instrument frame (mm) from (x1, x2, y2), eq. 10-12."""
    x1, x2, y2 = (float(v) for v in geometry)
    return np.array([[0.0, 0.0, 0.0], [x1, 0.0, 0.0], [x2, y2, 0.0]])


def geometry_from_distances(d12: float, d13: float, d23: float) -> np.ndarray:
    """(x1, x2, y2) in mm from the inter-laser distances (mm), paper eq. (10)-(12).

    ``x1 = d12``; ``x2 = (d12^2 + d13^2 - d23^2) / (2 d12)``; ``y2 = sqrt(d13^2 - x2^2)``.
    Raises ValueError when the three distances violate the triangle inequality.
    """
    d12, d13, d23 = float(d12), float(d13), float(d23)
    if d12 <= 0:
        raise ValueError(f"d12 must be > 0 mm, got {d12:g}")
    x2 = (d12 * d12 + d13 * d13 - d23 * d23) / (2.0 * d12)
    yy = d13 * d13 - x2 * x2
    if yy <= 0:
        raise ValueError(
            f"the distances d12={d12:g}, d13={d13:g}, d23={d23:g} mm do not form "
            "a triangle (laser 3 would lie on the x axis or off it)"
        )
    return np.array([d12, x2, math.sqrt(yy)])


def distances_from_geometry(geometry: Sequence[float]) -> np.ndarray:
    """(d12, d13, d23) in mm of the laser origins of (x1, x2, y2)."""
    Q = laser_origins(geometry)
    return np.array(
        [np.linalg.norm(Q[1] - Q[0]), np.linalg.norm(Q[2] - Q[0]), np.linalg.norm(Q[2] - Q[1])]
    )


# --------------------------------------------------------------------------------------
# observation model as a volcal instrument (per-station params + global params)


# --------------------------------------------------------------------------------------
# instrument state, noise, experiment, simulation


@dataclass(frozen=True)
class HPTI:
    """State of the instrument: geometry (x1, x2, y2) mm, offsets (3,) mm and
    ``instrument_T_machine`` frame (tx, ty, tz mm, rx, ry, rz rad)."""

    geometry: tuple[float, float, float]
    offsets: tuple[float, float, float] = (0.0, 0.0, 0.0)
    frame: tuple[float, ...] = (0.0,) * 6

    @classmethod
    def from_distances(cls, d12: float, d13: float, d23: float, **kw) -> HPTI:
        return cls(tuple(geometry_from_distances(d12, d13, d23)), **kw)

    @property
    def origins(self) -> np.ndarray:
        """(3, 3) laser origins, instrument frame, mm."""
        return laser_origins(self.geometry)

    @property
    def vector(self) -> np.ndarray:
        """(12,) [frame, geometry, offsets] in the estimator's order."""
        return np.r_[self.frame, self.geometry, self.offsets].astype(float)

    @classmethod
    def from_vector(cls, v: np.ndarray) -> HPTI:
        v = np.asarray(v, float)
        return cls(tuple(v[6:9]), tuple(v[9:12]), tuple(v[0:6]))

    def to_instrument(self, points_machine: np.ndarray) -> np.ndarray:
        """(N, 3) machine points -> instrument frame (eq. 5)."""
        P = np.asarray(points_machine, float)
        return P @ rotation_matrix(self.frame[3:6]).T + np.asarray(self.frame[0:3])

    def lengths(self, points_machine: np.ndarray) -> np.ndarray:
        """(N, 3) noise-free readings (mm) of the three lasers."""
        PI = self.to_instrument(points_machine)
        return (
            np.linalg.norm(PI[:, None, :] - self.origins[None], axis=-1)
            - np.asarray(self.offsets)[None, :]
        )


@dataclass(frozen=True)
class NoiseModel:
    """Noise of the readings (see the module docstring).  mm, s.

    drift: f(t) of eq. (2) (None: no drift); drift_mode: ``"common"`` (one f for the three
    simultaneous readings) or ``"per_laser"`` (independent phases per laser);
    drift_on_readings: True adds f to every point reading (eq. 3); False leaves the point
    readings without it (eq. 6-8 as printed put f under the square root, where its effect
    is below 0.01 um: the paper's own section-5 tests behave that way, see
    studies/paper001/README.md) -- the inter-laser distances always carry it;
    dwell_s: time per point; length_sigma_mm: white noise per reading (and per distance);
    offset_sigma_mm: error of the characterised offsets."""

    drift: DriftModel | None = PAPER001_DRIFT
    drift_mode: Literal["common", "per_laser"] = "common"
    drift_on_readings: bool = True
    dwell_s: float = 10.0
    length_sigma_mm: float = 1e-4
    offset_sigma_mm: float = 0.0

    def __post_init__(self) -> None:
        if self.drift_mode not in ("common", "per_laser"):
            raise ValueError(f"drift_mode must be 'common' or 'per_laser', got {self.drift_mode!r}")
        if self.dwell_s <= 0 or self.length_sigma_mm < 0 or self.offset_sigma_mm < 0:
            raise ValueError("dwell_s must be > 0 s; sigmas must be >= 0 mm")

    @property
    def reading_sigma_mm(self) -> float:
        """Standard deviation of one point reading's error (drift at a random instant when
        it is on the readings, plus the white noise)."""
        s = self.drift.sigma_mm if (self.drift is not None and self.drift_on_readings) else 0.0
        return float(math.hypot(s, self.length_sigma_mm))

    @property
    def nominal_sigma_mm(self) -> float:
        """The instrument's nominal reading uncertainty, used for the weights: the drift's
        standard deviation and the white noise in quadrature, whether or not the drift is on
        the point readings (the estimator does not know the simulation's choice)."""
        s = self.drift.sigma_mm if self.drift is not None else 0.0
        return float(math.hypot(s, self.length_sigma_mm))

    @classmethod
    def none(cls) -> NoiseModel:
        return cls(drift=None, length_sigma_mm=0.0, offset_sigma_mm=0.0)


@dataclass(frozen=True)
class Experiment:
    """A measurement plan: nominal points (machine frame, mm), the true instrument, noise.

    ``point_sigma_mm``: standard deviation of the actual points about the nominal ones (the
    machine's errors; 0 as in the paper, where actual = nominal)."""

    points_nominal: np.ndarray
    instrument: HPTI
    noise: NoiseModel = field(default_factory=NoiseModel)
    point_sigma_mm: float = 0.0

    @property
    def n_points(self) -> int:
        return int(len(self.points_nominal))


@dataclass
class HPTIData:
    """One simulated data set.

    lengths (N, 3) mm (laser 1..3), times (N,) s, distances (3,) measured d12, d13, d23 mm,
    offsets_characterised (3,) mm (what the user believes the offsets are), points_nominal
    and points_true (N, 3) machine frame mm, truth: the true instrument.
    """

    lengths: np.ndarray
    times: np.ndarray
    distances: np.ndarray
    offsets_characterised: np.ndarray
    points_nominal: np.ndarray
    points_true: np.ndarray
    truth: HPTI

    @property
    def n_points(self) -> int:
        return int(len(self.lengths))

    @property
    def geometry_analytic(self) -> np.ndarray:
        """x1, x2, y2 (mm) from the measured inter-laser distances (eq. 10-12)."""
        return geometry_from_distances(*self.distances)

    @property
    def points_true_instrument(self) -> np.ndarray:
        return self.truth.to_instrument(self.points_true)

    def to_frame(self):
        """The readings as a DESIGN.md measurement table (one row per reading)."""
        import pandas as pd

        N = self.n_points
        P = np.repeat(self.points_nominal, 3, axis=0)
        return pd.DataFrame(
            {
                "station": np.tile(LASERS, N),
                "point": np.repeat(np.arange(N), 3),
                "X": P[:, 0],
                "Y": P[:, 1],
                "Z": P[:, 2],
                "length": self.lengths.ravel(),
                "time": np.repeat(self.times, 3),
            }
        )


def paper_mesh(
    x=(0.0, 1000.0, 250.0), y=(0.0, 600.0, 200.0), z=(300.0, 600.0, 150.0)
) -> np.ndarray:
    """Regular mesh (start, stop, step) per axis, mm, x varying slowest.

    Paper sec. 5: 0 <= x <= 1000 step 250, 0 <= y <= 600 step 200, 300 <= z <= 600 "with
    intervals of 200 mm" and 60 points.  5 x 4 levels need 3 z levels for 60 points; a 200 mm
    step in [300, 600] gives only 2 (40 points), so the default takes z = 300, 450, 600.
    """
    axes = [np.arange(a, b + 1e-9 * max(1.0, abs(b)), s) for a, b, s in (x, y, z)]
    g = np.meshgrid(*axes, indexing="ij")
    return np.c_[g[0].ravel(), g[1].ravel(), g[2].ravel()]


def section5_experiment(
    *,
    d12: float = 1000.0,
    d13: float = 1166.1904,
    d23: float = 600.0,
    offsets: Sequence[float] = (100.0, 100.0, 100.0),
    frame: Sequence[float] = (0.0,) * 6,
    noise: NoiseModel | None = None,
    mesh: np.ndarray | None = None,
    point_sigma_mm: float = 0.0,
) -> Experiment:
    """Paper 001 section 5: 60-point mesh, d12 = 1000, d13 = 1166.1904, d23 = 600 mm
    (x1 = 1000, x2 = 1000, y2 = 600 mm), tests in the ICRS (frame = identity).  The paper
    gives no offset values; 100 mm per laser is an assumption (it matters only when the
    offsets are estimated)."""
    inst = HPTI.from_distances(
        d12,
        d13,
        d23,
        offsets=tuple(float(o) for o in offsets),
        frame=tuple(float(f) for f in frame),
    )
    return Experiment(
        paper_mesh() if mesh is None else np.asarray(mesh, float),
        inst,
        NoiseModel() if noise is None else noise,
        float(point_sigma_mm),
    )


def simulate(exp: Experiment, rng: np.random.Generator | int) -> HPTIData:
    """One realisation of the experiment (see the module docstring for the noise model).

    Instants: the inter-laser distances are read together (one cycle of the instrument) at
    ``t_0 = U(0, dwell)``, point p at ``t_p = (p + 1 + U(0, 1)) dwell``.  Draw order (fixed,
    so a seed gives the same data whatever else changes): actual points, instants, drift
    phases (one set, or one per laser), white length noise (points, then distances),
    offset characterisation errors.
    """
    g = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(int(rng))
    nz = exp.noise
    N = exp.n_points
    Pn = np.asarray(exp.points_nominal, float)
    Pt = Pn + (g.normal(0.0, exp.point_sigma_mm, Pn.shape) if exp.point_sigma_mm > 0 else 0.0)
    t_all = (np.arange(N + 1) + g.uniform(0.0, 1.0, N + 1)) * nz.dwell_s
    t_p = t_all[1:]
    f_points = np.zeros((N, 3))
    f_dist = np.zeros(3)
    if nz.drift is not None:
        reader = (0, 0, 1)  # the laser that reads d12, d13, d23
        if nz.drift_mode == "common":
            f = nz.drift.sample(t_all, g)
            f_points[:] = f[1:, None]
            f_dist[:] = f[0]
        else:
            for i in range(3):
                f = nz.drift.sample(t_all, g)
                f_points[:, i] = f[1:]
                for k in range(3):
                    if reader[k] == i:
                        f_dist[k] = f[0]
        if not nz.drift_on_readings:
            f_points[:] = 0.0
    white = g.normal(0.0, 1.0, (N + 1, 3)) * nz.length_sigma_mm
    off_err = g.normal(0.0, 1.0, 3) * nz.offset_sigma_mm
    L = exp.instrument.lengths(Pt) + f_points + white[:N]
    d = distances_from_geometry(exp.instrument.geometry) + f_dist + white[N]
    return HPTIData(L, t_p, d, np.asarray(exp.instrument.offsets) + off_err, Pn, Pt, exp.instrument)


# --------------------------------------------------------------------------------------
# estimation


@dataclass
class JacobianReport:
    """Rank analysis of one solve (scaled Jacobian at the start values).

    unknowns: free variables after gauge fixing; readings: readings with non-zero weight;
    rank; redundancy = readings - rank; null: unknowns - rank; condition: of the column-scaled
    Jacobian over its identifiable part; gauge: the detected gauge directions (fixed);
    unidentifiable: null directions left after gauge fixing (named)."""

    step: str
    unknowns: int
    readings: int
    rank: int
    condition: float
    gauge: list[str]
    gauge_fixed: list[str]
    unidentifiable: list[str]
    unidentifiable_pivots: list[int] = field(default_factory=list)
    fixed_unidentifiable: bool = False
    damping: float = 0.0

    @property
    def unidentifiable_leads(self) -> list[str]:
        """The variable each unidentifiable direction is named after."""
        return [c.split()[0] for c in self.unidentifiable]

    @property
    def redundancy(self) -> int:
        return self.readings - self.rank

    @property
    def null(self) -> int:
        return self.unknowns - self.rank

    def as_dict(self) -> dict:
        return {
            "step": self.step,
            "unknowns": self.unknowns,
            "readings": self.readings,
            "rank": self.rank,
            "redundancy": self.redundancy,
            "null": self.null,
            "condition": self.condition,
            "gauge": "; ".join(self.gauge),
            "gauge_fixed": ", ".join(self.gauge_fixed),
            "unidentifiable": ", ".join(self.unidentifiable_leads),
            "fixed_unidentifiable": self.fixed_unidentifiable,
            "damping": self.damping,
        }


@dataclass
class Estimate:
    """Result of one strategy: points in the instrument frame and in the machine frame
    (N, 3) mm, the estimated instrument, solver status per step, Jacobian reports."""

    strategy: str
    points_instrument: np.ndarray
    points_machine: np.ndarray
    instrument: HPTI
    success: bool
    status: list[str]
    iterations: int
    seconds: float
    reports: list[JacobianReport] = field(default_factory=list)

    def errors_um(self, data: HPTIData) -> np.ndarray:
        """(N,) distance between estimated and true point, instrument frame, um."""
        return 1e3 * np.linalg.norm(self.points_instrument - data.points_true_instrument, axis=1)


_OK = {"Solve_Succeeded", "Solved_To_Acceptable_Level"}


class HPTIEstimator:
    """IPOPT point/instrument estimation for N points, built once (data as parameters).

    ``p = [reference x (n_x, physical units), scale (n_x), readings (3N), weights 1/sigma
    (3N), damping]``; the variables are ``(x - reference) / scale`` (default scale 1 um,
    1 urad), fixed ones by equal bounds; ``hess_lag`` is ``J^T J + damping I`` (damping 0
    except for rank-deficient steps, see :meth:`_step`).
    """

    def __init__(
        self,
        n_points: int,
        *,
        tol: float = 1e-10,
        max_iter: int = 200,
        verbose: bool = False,
        ipopt_options: dict | None = None,
    ):
        N = int(n_points)
        self.n_points = N
        self.n_readings = 3 * N
        self.names = (
            [f"P{p}.{c}_mm" for p in range(N) for c in "xyz"]
            + list(FRAME_NAMES)
            + list(GEOMETRY_NAMES)
            + list(OFFSET_NAMES)
        )
        n = self.n_x = 3 * N + 12
        self.slices = {
            "points": slice(0, 3 * N),
            "frame": slice(3 * N, 3 * N + 6),
            "geometry": slice(3 * N + 6, 3 * N + 9),
            "offsets": slice(3 * N + 9, 3 * N + 12),
        }
        self.scale = np.full(n, 1e-3)
        self.scale[3 * N + 3 : 3 * N + 6] = 1e-6
        self.instrument = MultiLaserInstrument()

        # one point: three simultaneous readings, one SX expression per reading
        P, fr = ca.SX.sym("P", 3), ca.SX.sym("frame", 6)
        ge, of = ca.SX.sym("geometry", 3), ca.SX.sym("offsets", 3)
        Q: list[Any] = [ca.vertcat(0, 0, 0), ca.vertcat(ge[0], 0, 0), ca.vertcat(ge[1], ge[2], 0)]
        m = ca.vertcat(*[self.instrument.reading(P, ca.vertcat(Q[i], of[i]), fr) for i in range(3)])
        self.point_function = ca.Function(
            "hpti_point",
            [P, fr, ge, of],
            [m],
            ["P_machine", "frame", "geometry", "offsets"],
            ["lengths"],
            {"cse": True},
        )

        xs = ca.MX.sym("x", n)
        ref, sc = ca.MX.sym("ref", n), ca.MX.sym("scale", n)
        meas, w = ca.MX.sym("m", 3 * N), ca.MX.sym("w", 3 * N)
        mu = ca.MX.sym("damping")
        p = ca.vertcat(ref, sc, meas, w, mu)
        xp = ref + xs * sc
        Pm = ca.reshape(xp[: 3 * N], 3, N)
        vals = self.point_function.map(N)(
            Pm, xp[3 * N : 3 * N + 6], xp[3 * N + 6 : 3 * N + 9], xp[3 * N + 9 :]
        )
        r = w * (ca.vec(vals) - meas)
        J = ca.jacobian(r, xs)
        # built in MX with map, then expanded to SX: for a few hundred variables the SX
        # evaluation is several times faster than the MX graph
        self.residual_jacobian = ca.Function(
            "hpti_rJ", [xs, p], [r, J], ["x", "p"], ["r", "J"]
        ).expand()
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", 0)
        H = lam_f * (ca.mtimes(J.T, J) + mu * ca.MX.eye(n))
        hess = ca.Function(
            "nlp_hess_l",
            [xs, p, lam_f, lam_g],
            [ca.triu(H)],
            ["x", "p", "lam_f", "lam_g"],
            ["triu_hess_gamma_x_x"],
        ).expand()
        opts = {
            "expand": True,
            "ipopt.print_level": 5 if verbose else 0,
            "print_time": False,
            "ipopt.sb": "yes",
            "ipopt.tol": tol,
            "ipopt.max_iter": max_iter,
            "ipopt.acceptable_tol": 1e-8,
            "ipopt.acceptable_iter": 3,
            "ipopt.nlp_scaling_method": "none",
            "error_on_fail": False,
            "hess_lag": hess,
        }
        opts.update({f"ipopt.{k}": v for k, v in (ipopt_options or {}).items()})
        self.solver = ca.nlpsol("hpti", "ipopt", {"x": xs, "p": p, "f": 0.5 * ca.sumsqr(r)}, opts)
        self._gauge_cache: dict = {}

    # ---- helpers -----------------------------------------------------------------------
    def mask(self, *groups: str) -> np.ndarray:
        m = np.zeros(self.n_x, bool)
        for gname in groups:
            if gname not in self.slices:
                raise ValueError(f"unknown variable group {gname!r}; groups: {GROUPS}")
            m[self.slices[gname]] = True
        return m

    def pack(self, points_machine: np.ndarray, inst: HPTI) -> np.ndarray:
        return np.r_[np.asarray(points_machine, float).ravel(), inst.vector]

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, HPTI]:
        x = np.asarray(x, float).ravel()
        return x[: 3 * self.n_points].reshape(-1, 3), HPTI.from_vector(x[3 * self.n_points :])

    def _p(self, ref, lengths, weights, scale=None, damping=0.0):
        sc = self.scale if scale is None else np.asarray(scale, float)
        return np.r_[
            ref,
            sc,
            np.asarray(lengths, float).ravel(),
            np.asarray(weights, float).ravel(),
            float(damping),
        ]

    def jacobian(self, x: np.ndarray, lengths: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """Whitened Jacobian (3N, n_x) w.r.t. the unit-scaled variables (1 um, 1 urad) at x
        (physical)."""
        _, J = self.residual_jacobian(np.zeros(self.n_x), self._p(x, lengths, weights))
        return np.asarray(ca.DM(J).full())

    def jacobi_scale(self, x: np.ndarray, lengths, weights) -> np.ndarray:
        """Variable scale that gives every Jacobian column unit norm at x (physical units
        per scaled unit).  With it, IPOPT's regularisation of a singular Gauss-Newton
        matrix, delta * I in the scaled variables, is Marquardt's delta * diag(J^T J)."""
        norms = np.linalg.norm(self.jacobian(x, lengths, weights), axis=0)
        return self.scale / np.where(norms > 0, norms, 1.0)

    # ---- rank analysis and gauge -------------------------------------------------------
    def analyse(
        self, x: np.ndarray, lengths, weights, free: np.ndarray, step: str = ""
    ) -> tuple[np.ndarray, JacobianReport]:
        """Detect and fix gauge freedoms among the free variables, then analyse the rest.

        Gauge = null directions of the Jacobian over the free point and frame columns (the
        rigid motion between point frame and instrument frame); each is fixed by holding
        its pivot variable (frame variables preferred).  Returns (the free mask after
        fixing, the report)."""
        J = self.jacobian(x, lengths, weights)
        w = np.asarray(weights, float).ravel()
        J = J[w > 0]
        free = np.asarray(free, bool).copy()
        cand = free & self.mask("points", "frame")
        prefer = self.mask("frame").astype(float)
        gauge, fixed_names = [], []
        if cand.any():
            g = analyse_jacobian(J, self.names, fixed=~cand, prefer=prefer)
            gauge = list(g.combinations)
            for pv in g.pivots:
                free[pv] = False
                fixed_names.append(self.names[pv])
        a = analyse_jacobian(
            J, self.names, fixed=~free, prefer=self.mask("geometry", "offsets").astype(float)
        )
        rep = JacobianReport(
            step,
            int(free.sum()),
            int(J.shape[0]),
            int(a.rank),
            float(a.condition),
            gauge,
            fixed_names,
            list(a.combinations),
            [int(i) for i in a.pivots],
        )
        return free, rep

    # ---- solves ------------------------------------------------------------------------
    def solve(
        self,
        x_ref: np.ndarray,
        lengths,
        weights,
        free: np.ndarray,
        scale=None,
        damping: float = 0.0,
    ):
        """IPOPT from x_ref (physical) with the free variables; returns (x, status, ok,
        iterations, seconds).  scale: physical units per scaled unit (default 1 um /
        1 urad)."""
        n = self.n_x
        sc = self.scale if scale is None else np.asarray(scale, float)
        lb, ub = np.full(n, -np.inf), np.full(n, np.inf)
        lb[~free] = ub[~free] = 0.0
        t0 = time.perf_counter()
        sol = self.solver(
            x0=np.zeros(n), p=self._p(x_ref, lengths, weights, sc, damping), lbx=lb, ubx=ub
        )
        dt = time.perf_counter() - t0
        st = self.solver.stats()
        status = str(st.get("return_status", "unknown"))
        x = np.asarray(x_ref, float) + np.asarray(sol["x"]).ravel() * sc
        ok = status in _OK and bool(np.all(np.isfinite(x)))
        return x, status, ok, int(st.get("iter_count", -1)), dt

    def _step(
        self,
        step,
        x_ref,
        lengths,
        weights,
        free,
        cache_key,
        scaling="units",
        fix_unidentifiable=False,
        damping_rel=1e-5,
    ):
        """Gauge detection and rank analysis (cached per key: they depend on the layout and
        the free set, not on the noise), then the solve.

        Null directions left after gauge fixing are either fixed too (their pivot variables
        held at the start values, ``fix_unidentifiable``) or left to a damped Gauss-Newton:
        ``damping_rel`` times the mean diagonal of J^T J (free scaled variables) is added
        to the Hessian, so every step is (nearly) the minimum-norm Gauss-Newton step and
        the answer is reproducible -- without it, steps along the numerically near-null
        directions are set by rounding.  Well-posed steps get no damping."""
        if cache_key is not None and cache_key in self._gauge_cache:
            free2, rep = self._gauge_cache[cache_key]
        else:
            free2, rep = self.analyse(x_ref, lengths, weights, free, step)
            if rep.null and fix_unidentifiable:
                free2 = free2.copy()
                free2[rep.unidentifiable_pivots] = False
                rep = replace(rep, fixed_unidentifiable=True)
            if cache_key is not None:
                self._gauge_cache[cache_key] = (free2, rep)
        scale = self._scale(scaling, x_ref, lengths, weights)
        mu = 0.0
        if rep.null and not rep.fixed_unidentifiable:
            J = self.jacobian(x_ref, lengths, weights)[:, free2]
            if scale is not None:
                J = J * (scale / self.scale)[free2]
            mu = float(damping_rel * np.mean(np.sum(J * J, axis=0)))
        x, status, ok, it, dt = self.solve(x_ref, lengths, weights, free2, scale, mu)
        return x, status, ok, it, dt, replace(rep, damping=mu)

    def _scale(self, scaling, x, lengths, weights):
        if scaling == "units":
            return None
        if scaling == "jacobian":
            return self.jacobi_scale(x, lengths, weights)
        raise ValueError(f"scaling must be 'units' or 'jacobian', got {scaling!r}")

    def start_values(
        self,
        data: HPTIData,
        accuracy: float = 1.0,
        *,
        scale_instrument: bool = False,
        frame0: Sequence[float] | None = None,
    ) -> np.ndarray:
        """Start values: points a * nominal (machine frame), x1 x2 y2 analytic from the
        measured distances and the characterised offsets (both times a when
        ``scale_instrument``), the frame at ``frame0`` (default identity)."""
        a = float(accuracy)
        geom = data.geometry_analytic
        off = np.asarray(data.offsets_characterised, float)
        if scale_instrument:
            geom, off = a * geom, a * off
        inst = HPTI(tuple(geom), tuple(off), tuple(frame0) if frame0 is not None else (0.0,) * 6)
        return self.pack(a * np.asarray(data.points_nominal, float), inst)

    def estimate(
        self,
        data: HPTIData,
        strategy: str,
        accuracy: float = 1.0,
        *,
        scale_instrument: bool = False,
        weights: np.ndarray | None = None,
        phase1: Sequence[str] = ("frame", "geometry", "offsets"),
        calibration_points: Sequence[int] | None = None,
        joint_groups: Sequence[str] = ("points", "frame", "geometry", "offsets"),
        fix_unidentifiable: bool = False,
        scaling: str = "units",
        damping_rel: float = 1e-5,
        start: np.ndarray | None = None,
        cache_key=None,
    ) -> Estimate:
        """Estimate the points with one strategy (see the module docstring).

        weights: (N, 3) 1/sigma of the readings (default ones); phase1: variable groups of
        the two-phase calibration step; calibration_points: indices of the points used in
        phase 1 (default all); joint_groups: groups the joint step frees;
        fix_unidentifiable: also fix the null directions left after gauge fixing (in the
        joint step the instrument then stays at its start values).  scaling: variable
        scaling of every IPOPT solve, ``"units"`` (1 um, 1 urad) or ``"jacobian"`` (unit
        Jacobian columns at the start, :meth:`jacobi_scale`); it changes only the path of
        a well-posed solve, but it selects the answer of a rank-deficient one (joint).
        damping_rel: Levenberg damping of a step that stays rank deficient (see
        :meth:`_step`).  start: start values (n_x,) in physical units, overriding
        :meth:`start_values` (accuracy and scale_instrument are then ignored).
        cache_key: reuse the gauge detection of an earlier call with the same key (same
        layout, strategy, accuracy)."""
        if data.n_points != self.n_points:
            raise ValueError(
                f"this estimator is built for {self.n_points} points, the data have {data.n_points}"
            )
        N = self.n_points
        L = np.asarray(data.lengths, float)
        W = np.ones((N, 3)) if weights is None else np.broadcast_to(weights, (N, 3)).astype(float)
        t0 = time.perf_counter()
        if strategy == "sphere":
            inst = HPTI(tuple(data.geometry_analytic), tuple(data.offsets_characterised))
            ml = multilaterate(
                inst.origins,
                np.asarray(inst.offsets),
                L,
                method="sphere",
                side=np.array([0.0, 0.0, 1.0]),
                side_type="normal",
                max_residual_rms=None,
            )
            PI = ml.points
            return Estimate(
                strategy,
                PI,
                PI.copy(),
                inst,
                bool(np.all(ml.converged)),
                [ml.status],
                0,
                time.perf_counter() - t0,
            )
        x0 = self.start_values(data, accuracy, scale_instrument=scale_instrument)
        if start is not None:
            x0 = np.asarray(start, float).ravel().copy()
            if x0.shape != (self.n_x,):
                raise ValueError(f"start must have {self.n_x} values, got {x0.shape}")

        def key(s):
            return None if cache_key is None else (cache_key, s)

        reports, status, iters, ok_all = [], [], 0, True
        if strategy == "points-only":
            if start is None:
                x0 = self.start_values(data, accuracy, scale_instrument=False)
            free = self.mask("points", "frame")
            x, st, ok, it, _, rep = self._step(
                "points-only", x0, L, W, free, key("p"), scaling, fix_unidentifiable, damping_rel
            )
            reports.append(rep)
            status.append(st)
            iters += it
            ok_all &= ok
        elif strategy == "two-phase":
            W1 = W.copy()
            if calibration_points is not None:
                use = np.zeros(N, bool)
                use[np.asarray(calibration_points, int)] = True
                W1[~use] = 0.0
            x1, st, ok, it, _, rep = self._step(
                "two-phase: 1 instrument",
                x0,
                L,
                W1,
                self.mask(*phase1),
                key("1"),
                scaling,
                fix_unidentifiable,
                damping_rel,
            )
            reports.append(rep)
            status.append(st)
            iters += it
            ok_all &= ok
            x, st, ok, it, _, rep = self._step(
                "two-phase: 2 points",
                x1,
                L,
                W,
                self.mask("points"),
                key("2"),
                scaling,
                fix_unidentifiable,
                damping_rel,
            )
            reports.append(rep)
            status.append(st)
            iters += it
            ok_all &= ok
        elif strategy == "joint":
            x, st, ok, it, _, rep = self._step(
                "joint",
                x0,
                L,
                W,
                self.mask(*joint_groups),
                key("j"),
                scaling,
                fix_unidentifiable,
                damping_rel,
            )
            reports.append(rep)
            status.append(st)
            iters += it
            ok_all &= ok
        else:
            raise ValueError(f"unknown strategy {strategy!r}; strategies: {STRATEGIES}")
        PM, inst = self.unpack(x)
        return Estimate(
            strategy,
            inst.to_instrument(PM),
            PM,
            inst,
            ok_all,
            status,
            iters,
            time.perf_counter() - t0,
            reports,
        )


# --------------------------------------------------------------------------------------
# the same estimation through volcal's core (identify's one problem and solvers)


def point_cloud_spec(n_points: int) -> Any:
    """A volcal machine whose error parameters are the deviations of ``n_points`` points
    from their nominal positions (mm), so that free points are the unknowns of volcal's one
    identification problem.

    One linear axis ``P`` whose position is the point's index, with the translational
    error motions EXP, EYP, EZP as tables with a knot at every index (piecewise linear:
    at an index exactly the knot's value) and no other error; the nominal point enters as
    the tool offset (mm) of its readings, so the tool point of pose k is
    ``(k, 0, 0) + tool offset + (EXP, EYP, EZP)@k = nominal_k + deviation_k``.  The
    structural point of the core (errors zero, where gauge and datum are decided) is then
    the nominal point cloud."""
    from volcal.model.spec import AxisSpec, ErrorForm, MachineSpec

    n = int(n_points)
    knots = tuple(float(k) for k in range(n))
    axis = AxisSpec(
        "P",
        "linear",
        "+x",
        "tool",
        (0.0, float(n - 1)),
        errors=("EXP", "EYP", "EZP"),
        location="none",
        basis=ErrorForm("table", knots=knots),
    )
    return MachineSpec(f"pointcloud{n}", (axis,), "free points (paper 001)", tool_errors="none")


class CoreEstimator:
    """The NLP strategies of :class:`HPTIEstimator` through volcal's core: the one problem
    of :class:`volcal.analysis.identify.Identifier` with the :class:`MultiLaserInstrument`
    on the point cloud of :func:`point_cloud_spec`.

    Variables: the points' deviations from nominal (``errors``), the lasers' origins and
    offsets (``stations``; the ICRS convention holds 6 of the 9 coordinates) and the frame
    (``frame``).  points-only and two-phase are :class:`volcal.problem.strategies.PhasedStrategy`
    objects run by ``Identifier.run`` (IPOPT, then the core's Gauss-Newton polish).  joint:
    the gauge (null directions over the points and the frame, the stations held) is found
    by ``Identifier.analyse`` and held on its pivots (the frame); the null directions that
    remain (x1 x2 y2, and the offsets when free, trade against the points) are left to the
    core's fixed-metric Levenberg solve
    (:meth:`volcal.solve.gauss_newton.GaussNewtonSolver.solve_levenberg`) with the study's
    damping: ``damping_rel`` times the mean diagonal of J^T J over the free variables in
    the scaling ``scaling`` (``"units"``: 1 um / 1 urad; ``"jacobian"``: unit Jacobian
    columns at the start).

    Everything that depends on the layout is built once per object and reused for every
    trial: the problem and its chunked evaluator, the solvers, the phased strategies'
    plans (datum and pivots, :meth:`volcal.analysis.identify.Identifier.plan`) and the
    joint's held gauge, each decided at its first call (the study runner makes that call on
    noise-free data, so the decisions do not depend on which trial a worker runs first).

    solver: the core solver of the phased strategies, ``"gauss-newton"`` (default: the
    core's Levenberg-Marquardt on the chunked evaluation, the faster here) or ``"ipopt"``
    (IPOPT then the Gauss-Newton polish); both reach the same minimiser."""

    def __init__(self, n_points: int, *, solver: str = "gauss-newton") -> None:
        from volcal.analysis.identify import Identifier
        from volcal.model.errors import ErrorModel
        from volcal.model.machine import Machine
        from volcal.problem.residuals import Layout

        N = self.n_points = int(n_points)
        spec = point_cloud_spec(N)
        layout = Layout(np.tile(np.arange(3), N), 3, LASERS, np.repeat(np.arange(N), 3))
        self.identifier = Identifier(
            Machine.from_model(spec),
            ErrorModel(spec, datum="none"),
            layout,
            instrument=MultiLaserInstrument(),
            solver=solver,
        )
        pr = self.identifier.problem
        self._q = np.repeat(np.arange(N, dtype=float), 3)[:, None]
        names = pr.names
        self._geometry = [names.index(n) for n in ("laser2.x_mm", "laser3.x_mm", "laser3.y_mm")]
        self._offsets = [names.index(f"{lz}.offset_mm") for lz in LASERS]
        # the ICRS convention (the instrument's own held station parameters)
        self._icrs = self.identifier.station_fixed(np.zeros(3, bool))
        # joint: (held mask with the gauge pivots, rank deficient after them) per free set;
        # decided once, at the structural point (nominal points), as the study does
        self._joint_cache: dict[tuple, tuple[np.ndarray, bool]] = {}
        # points-only / two-phase: the strategy's plan (datum, pivots) per strategy
        self._plans: dict[tuple, Any] = {}

    def data(self, data: HPTIData, weights: np.ndarray | float) -> np.ndarray:
        """The problem's data vector p: pose index, nominal point as tool offset, readings
        (mm) and weights 1/sigma (1/mm), laser 1..3 per point."""
        N = self.n_points
        tool = np.repeat(data.points_nominal - np.c_[np.arange(N), np.zeros((N, 2))], 3, axis=0)
        w = np.broadcast_to(np.asarray(weights, float), (N, 3)).ravel()
        return self.identifier.problem.pack_data(self._q, tool, data.lengths.ravel(), w)

    def start(self, points_machine: np.ndarray, data: HPTIData, inst: HPTI) -> np.ndarray:
        """x (physical units) from points (machine frame, mm) and an instrument state."""
        dev = np.asarray(points_machine, float) - data.points_nominal
        g, o = inst.geometry, inst.offsets
        st = np.array([[0, 0, 0, o[0]], [g[0], 0, 0, o[1]], [g[1], g[2], 0, o[2]]], float)
        return self.identifier.problem.pack_x(dev.T.ravel(), st, np.asarray(inst.frame, float))

    def unpack(self, x: np.ndarray, data: HPTIData) -> tuple[np.ndarray, HPTI]:
        """(points, machine frame mm; instrument state) from x."""
        theta, st, frame = self.identifier.problem.unpack_x(x)
        points = data.points_nominal + theta.reshape(3, -1).T
        return points, HPTI((st[1, 0], st[2, 0], st[2, 1]), tuple(st[:, 3]), tuple(frame))

    def estimate(
        self,
        data: HPTIData,
        strategy: str,
        accuracy: float = 1.0,
        *,
        scale_instrument: bool = False,
        weights: np.ndarray | float = 1.0,
        phase1: Sequence[str] = ("frame", "geometry", "offsets"),
        joint_groups: Sequence[str] = ("points", "frame", "geometry", "offsets"),
        scaling: str = "units",
        damping_rel: float = 1e-5,
    ) -> Estimate:
        """As :meth:`HPTIEstimator.estimate` for ``"points-only"``, ``"two-phase"`` (all
        calibration points) and ``"joint"``, from the same start values (points
        a * nominal, x1 x2 y2 analytic, characterised offsets, frame identity)."""
        if strategy not in ("points-only", "two-phase", "joint"):
            raise ValueError(
                f"strategy {strategy!r} is not run through the core here; "
                "expected 'points-only', 'two-phase' or 'joint'"
            )
        for key, groups, allowed in (
            ("phase1", phase1, GROUPS[1:]),
            ("joint_groups", joint_groups, GROUPS),
        ):
            bad = sorted(set(groups) - set(allowed))
            if bad:
                raise ValueError(f"{key}: unknown group(s) {bad}; expected {allowed}")
        if scaling not in ("units", "jacobian"):
            raise ValueError(f"scaling must be 'units' or 'jacobian', got {scaling!r}")
        a = float(accuracy)
        geom, off = data.geometry_analytic, np.asarray(data.offsets_characterised, float)
        if scale_instrument and strategy != "points-only":
            geom, off = a * geom, a * off
        x0 = self.start(a * data.points_nominal, data, HPTI(tuple(geom), tuple(off)))
        p = self.data(data, weights)
        t0 = time.perf_counter()
        if strategy == "joint":
            x, outs = self._joint(x0, p, tuple(joint_groups), scaling, float(damping_rel))
        else:
            x, outs = self._phased(strategy, x0, p, phase1)
        PM, inst = self.unpack(x, data)
        return Estimate(
            strategy,
            inst.to_instrument(PM),
            PM,
            inst,
            all(o.success for o in outs),
            [o.status for o in outs],
            sum(o.iterations for o in outs),
            time.perf_counter() - t0,
        )

    def _joint(self, x0, p, groups: tuple[str, ...], scaling: str, damping_rel: float):
        """The joint step: gauge held on its pivots, the rest by the core's fixed-metric
        Levenberg solve (see the class docstring)."""
        idf = self.identifier
        key = (groups, scaling)
        if key not in self._joint_cache:
            held = self._icrs.copy()
            if "points" not in groups:
                held |= idf.is_theta
            if "frame" not in groups:
                held |= idf.is_frame
            if "geometry" not in groups:
                held[self._geometry] = True
            if "offsets" not in groups:
                held[self._offsets] = True
            gauge = idf.analyse(x0, p, held | idf.is_station)
            fixed = held.copy()
            fixed[list(gauge.pivots)] = True
            deficient = len(idf.analyse(x0, p, fixed).pivots) > 0
            self._joint_cache[key] = (fixed, deficient)
        fixed, deficient = self._joint_cache[key]
        free = ~fixed
        _, J = idf.jacobian(x0, p)  # whitened, wrt the scaled variables (1 um, 1 urad)
        norms = np.linalg.norm(J, axis=0)
        # the solver's metric: scaled variable z = u * c (u in 1 um / 1 urad), c = 1 or the
        # column norms at the start; damping mu I in z is mu c^2 in u
        c = np.where(norms > 0, norms, 1.0) if scaling == "jacobian" else np.ones_like(norms)
        mu = damping_rel * float(np.mean((norms[free] / c[free]) ** 2)) if deficient else 0.0
        out = idf.gauss_newton.solve_levenberg(x0, p, mu * c**2, fixed=fixed, max_iter=200)
        return out.x, [out]

    def _phased(self, strategy: str, x0, p, phase1: Sequence[str]):
        """points-only and two-phase as core strategies run by ``Identifier.run``, on a
        plan (:meth:`volcal.analysis.identify.Identifier.plan`) made at the first call per
        strategy: the datum and the held pivots are structural, decided once as the
        study's estimator does, not per trial."""
        from volcal.problem.strategies import POINTS_ONLY, Phase, PhasedStrategy

        key = (strategy, tuple(phase1) if strategy == "two-phase" else ())
        plan = self._plans.get(key)
        if plan is not None:
            x, outs, _, _ = self.identifier.run(plan, x0, p)
            return x, outs
        held = self._icrs.copy()
        if strategy == "points-only":
            strat = POINTS_ONLY
        else:
            # phase 1: the instrument groups of ``phase1`` on the points held at their start
            # values (not zeroed, as the study's); phase 2: the points alone
            if "geometry" not in phase1:
                held[self._geometry] = True
            if "offsets" not in phase1:
                held[self._offsets] = True
            hold1 = {"errors"} | ({"frame"} if "frame" not in phase1 else set())
            strat = PhasedStrategy(
                "paper001 two-phase",
                "the instrument on the start points, then the points",
                (
                    Phase(hold=frozenset(hold1), datum=False, pivots=False),
                    Phase(hold=frozenset({"stations", "frame"})),
                ),
            )
        plan = self._plans[key] = self.identifier.plan(strat, x0, p, user_fixed=held)
        x, outs, _, _ = self.identifier.run(plan, x0, p)
        return x, outs


# --------------------------------------------------------------------------------------
# Monte Carlo study (used by run.py; importable so that worker processes find it)


def trial_rng(seed: int, index: int) -> np.random.Generator:
    """The random generator of trial ``index``: SeedSequence(seed, spawn_key=(index,)), so a
    trial's data do not depend on which worker runs it or in which order."""
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(int(index),)))


def noise_from_config(d: dict) -> NoiseModel:
    """NoiseModel from a ``[scenario.<name>]`` table (um in the file)."""
    drift = None
    name = d.get("drift", "paper001")
    if name == "paper001":
        drift = replace(PAPER001_DRIFT, random_phase=bool(d.get("random_phase", True)))
    elif name != "none":
        raise ValueError(f"drift must be 'paper001' or 'none', got {name!r}")
    return NoiseModel(
        drift=drift,
        drift_mode=d.get("drift_mode", "common"),
        drift_on_readings=bool(d.get("drift_on_readings", True)),
        dwell_s=float(d.get("dwell_s", 10.0)),
        length_sigma_mm=1e-3 * float(d.get("length_sigma_um", 0.1)),
        offset_sigma_mm=1e-3 * float(d.get("offset_sigma_um", 0.0)),
    )


def experiment_from_config(cfg: dict, scenario: str | None = None) -> Experiment:
    """Experiment from the study config (studies/paper001/config.toml) and a scenario name
    (a ``[scenario.<name>]`` table: the noise; default the first one listed)."""
    ins, mesh = cfg.get("instrument", {}), cfg.get("mesh", {})
    scen = cfg.get("scenario", {})
    if scenario is None:
        scenario = next(iter(scen), None)
    if scenario is not None and scenario not in scen:
        raise ValueError(f"unknown scenario {scenario!r}; scenarios: {list(scen)}")
    noise = noise_from_config(scen[scenario] if scenario is not None else {})
    pts = paper_mesh(
        tuple(mesh.get("x_mm", (0, 1000, 250))),
        tuple(mesh.get("y_mm", (0, 600, 200))),
        tuple(mesh.get("z_mm", (300, 600, 150))),
    )
    frame = list(ins.get("frame_translation_mm", (0.0, 0.0, 0.0))) + list(
        ins.get("frame_rotation_rad", (0.0, 0.0, 0.0))
    )
    point_sigma = scen[scenario].get("point_sigma_um", 0.0) if scenario is not None else 0.0
    return section5_experiment(
        d12=float(ins.get("d12_mm", 1000.0)),
        d13=float(ins.get("d13_mm", 1166.1904)),
        d23=float(ins.get("d23_mm", 600.0)),
        offsets=ins.get("offsets_mm", (100.0, 100.0, 100.0)),
        frame=frame,
        noise=noise,
        mesh=pts,
        point_sigma_mm=1e-3 * float(point_sigma),
    )


_CASE_KEYS = {
    "name",
    "strategy",
    "phase1",
    "groups",
    "scaling",
    "fix_unidentifiable",
    "calibration_points",
    "note",
}


@dataclass(frozen=True)
class Case:
    """One strategy variant at one initial accuracy (None for the sphere intersection)."""

    name: str
    strategy: str
    accuracy: float | None
    phase1: tuple[str, ...] = ("frame", "geometry", "offsets")
    groups: tuple[str, ...] = ("points", "frame", "geometry", "offsets")
    scaling: str = "units"
    fix_unidentifiable: bool = False
    calibration_points: tuple[int, ...] | None = None

    @property
    def label(self) -> str:
        return self.name if self.accuracy is None else f"{self.name} @ {100 * self.accuracy:g} %"


def cases_from_config(cfg: dict) -> list[Case]:
    """The ``[[case]]`` tables times the initial accuracies (sphere: once)."""
    st = cfg.get("study", {})
    accs = [float(a) / 100.0 for a in st.get("initial_accuracy_percent", (100, 95, 90))]
    raw = cfg.get("case") or [{"name": s, "strategy": s} for s in STRATEGIES]
    out = []
    for d in raw:
        bad = sorted(set(d) - _CASE_KEYS)
        if bad:
            raise ValueError(
                f"[[case]] {d.get('name')!r}: unknown key(s) {bad}; allowed {sorted(_CASE_KEYS)}"
            )
        strat = d.get("strategy", d.get("name"))
        if strat not in STRATEGIES:
            raise ValueError(
                f"[[case]] {d.get('name')!r}: unknown strategy {strat!r}; strategies: {STRATEGIES}"
            )
        for key in ("phase1", "groups"):
            for gname in d.get(key, ()):
                if gname not in GROUPS:
                    raise ValueError(
                        f"[[case]] {d.get('name')!r}: {key} has unknown group "
                        f"{gname!r}; groups: {GROUPS}"
                    )
        cal = d.get("calibration_points", "all")
        kw: dict[str, Any] = dict(
            phase1=tuple(d.get("phase1", Case.phase1)),
            groups=tuple(d.get("groups", Case.groups)),
            scaling=str(d.get("scaling", "units")),
            fix_unidentifiable=bool(d.get("fix_unidentifiable", False)),
            calibration_points=None if cal == "all" else tuple(int(i) for i in cal),
        )
        name = str(d.get("name", strat))
        for a in [None] if strat == "sphere" else accs:
            out.append(Case(name, strat, a, **kw))
    return out


class StudyRunner:
    """Runs trials of the paper-001 study for one scenario; its estimators (volcal's core
    and the study's IPOPT problem) are built once per instance and reused for every trial.

    :meth:`trial` returns errors (n_cases, N) um (instrument frame), success (n_cases,),
    iterations (n_cases,) and the estimated x1 x2 y2 (n_cases, 3) mm, in the order of
    :attr:`cases`."""

    def __init__(
        self,
        cfg: dict,
        scenario: str | None = None,
        *,
        threads_one: bool = True,
        estimator: str | None = None,
    ):
        """threads_one: limit BLAS to one thread for the rest of the process (small SVDs;
        several processes share the cores).  estimator: ``"core"`` (volcal's core,
        :class:`CoreEstimator`) or ``"study"`` (:class:`HPTIEstimator`, the study's own
        IPOPT problem) for the NLP strategies; default the config's ``study.estimator``,
        else ``"core"``.  The sphere intersection is closed-form either way."""
        st = cfg.get("study", {})
        self.cfg = cfg
        self.scenario = scenario
        self.seed = int(st.get("seed", 1))
        self.experiment = experiment_from_config(cfg, scenario)
        applies = st.get("initial_accuracy_applies_to", "points")
        if applies not in ("points", "points+instrument"):
            raise ValueError(
                "initial_accuracy_applies_to must be 'points' or "
                f"'points+instrument', got {applies!r}"
            )
        self.scale_instrument = applies == "points+instrument"
        self.cases = cases_from_config(cfg)
        self.estimator_name = str(estimator or st.get("estimator", "core"))
        if self.estimator_name not in ESTIMATORS:
            raise ValueError(
                f"study.estimator must be one of {ESTIMATORS}, got {self.estimator_name!r}"
            )
        if self.estimator_name == "core":
            for case in self.cases:
                if case.calibration_points is not None or case.fix_unidentifiable:
                    raise ValueError(
                        f"[[case]] {case.name!r}: calibration_points and fix_unidentifiable "
                        "are options of the study's estimator only (study.estimator = "
                        "'study')"
                    )
        if threads_one:
            set_blas_threads(1)
        # the study's own estimator: the sphere intersection, the rank analyses of the
        # `jacobian` table and the cross-check of the core (run.py --core-check)
        self.estimator = HPTIEstimator(self.experiment.n_points)
        self.core = (
            CoreEstimator(self.experiment.n_points) if self.estimator_name == "core" else None
        )
        # weights 1 / nominal reading uncertainty (uniform: they scale the objective, which
        # matters only to the damping of rank-deficient steps)
        self.sigma = self.experiment.noise.nominal_sigma_mm or 1e-3
        # gauge detection and rank analysis once per case, on noise-free data, so that the
        # variables a worker fixes never depend on which trial it happened to run first
        self._reference = simulate(replace(self.experiment, noise=NoiseModel.none()), 0)
        for case in self.cases:
            if case.strategy != "sphere":
                self.estimate(self._reference, case, by="study")
                if self.core is not None:
                    self.estimate(self._reference, case)

    def case_labels(self) -> list[str]:
        return [c.label for c in self.cases]

    def estimate(
        self,
        data: HPTIData,
        case: Case,
        *,
        cache: bool = True,
        damping_rel: float = 1e-5,
        by: str | None = None,
    ) -> Estimate:
        """One case on one data set by ``by`` (``"core"`` or ``"study"``; default the
        runner's estimator; the sphere intersection is the study's closed form).  cache:
        the study's estimator reuses its gauge decisions per case (False: decide afresh,
        with the rank reports); the core always reuses its plans."""
        a = 1.0 if case.accuracy is None else case.accuracy
        by = by or self.estimator_name
        if by not in ESTIMATORS:
            raise ValueError(f"by must be one of {ESTIMATORS}, got {by!r}")
        if by == "core" and case.strategy != "sphere":
            if self.core is None:
                self.core = CoreEstimator(self.experiment.n_points)
            return self.core.estimate(
                data,
                case.strategy,
                a,
                scale_instrument=self.scale_instrument,
                weights=1.0 / self.sigma,
                phase1=case.phase1,
                joint_groups=case.groups,
                scaling=case.scaling,
                damping_rel=damping_rel,
            )
        return self.estimator.estimate(
            data,
            case.strategy,
            a,
            scale_instrument=self.scale_instrument,
            weights=np.full((data.n_points, 3), 1.0 / self.sigma),
            phase1=case.phase1,
            calibration_points=case.calibration_points,
            joint_groups=case.groups,
            fix_unidentifiable=case.fix_unidentifiable,
            scaling=case.scaling,
            damping_rel=damping_rel,
            cache_key=(case.name, case.accuracy) if cache else None,
        )

    def simulate(self, index: int) -> HPTIData:
        return simulate(self.experiment, trial_rng(self.seed, index))

    def trial(self, index: int) -> dict:
        data = self.simulate(index)
        n, N = len(self.cases), self.experiment.n_points
        err = np.full((n, N), np.nan)
        ok = np.zeros(n, bool)
        it = np.zeros(n, int)
        geom = np.full((n, 3), np.nan)
        for c, case in enumerate(self.cases):
            e = self.estimate(data, case)
            err[c] = e.errors_um(data)
            ok[c] = e.success
            it[c] = e.iterations
            geom[c] = e.instrument.geometry
        return {
            "index": int(index),
            "errors_um": err,
            "success": ok,
            "iterations": it,
            "geometry_mm": geom,
        }

    def jacobian_reports(self) -> list[tuple[Case, JacobianReport]]:
        """The rank analysis of every NLP step (and of the per-point system the sphere
        intersection solves) at the start values of a noise-free data set: the rank
        structure does not depend on the noise."""
        data = self._reference
        out = []
        for case in self.cases:
            if case.strategy == "sphere":
                est = self.estimator
                x0 = est.start_values(data, 1.0)
                W = np.full((data.n_points, 3), 1.0 / self.sigma)
                _, rep = est.analyse(
                    x0, data.lengths, W, est.mask("points"), "sphere: points in the ICRS"
                )
                out.append((case, rep))
                continue
            e = self.estimate(data, case, cache=False, by="study")
            out += [(case, r) for r in e.reports]
        return out


class TrialKernel:
    """The trials of one scenario as a kernel of
    :func:`volcal.analysis.uncertainty.parallel.run_chunks` (a chunk is a list of trial
    indices): the :class:`StudyRunner` (its estimators built once) is made on first use in
    each process and never pickled, so a worker builds its own."""

    def __init__(self, cfg: dict, scenario: str | None = None) -> None:
        self.cfg, self.scenario = cfg, scenario
        self._runner: StudyRunner | None = None

    def __getstate__(self) -> dict:
        return {"cfg": self.cfg, "scenario": self.scenario, "_runner": None}

    @property
    def runner(self) -> StudyRunner:
        if self._runner is None:
            self._runner = StudyRunner(self.cfg, self.scenario)
        return self._runner

    def run_chunk(self, indices: Sequence[int]) -> list[dict]:
        """:meth:`StudyRunner.trial` of every index."""
        return [self.runner.trial(k) for k in indices]
