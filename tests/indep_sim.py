"""An independent rigid-body simulator of multilateration on a machine tool, for tests.

Written from the physics with numpy only: exact 4x4 homogeneous transforms and exact
rotation matrices (Rodrigues' formula), no first-order truncation anywhere, and no use of
volcal's model code (``volcal.model.symbolic``, ``machine``, ``errors``, ``simulate``, ``plans``).
The model files are read with :mod:`tomllib` for the travel, reference and centre of each
axis only.  The truth it simulates is drawn from families that are *not* volcal's error
bases and does not satisfy any datum convention.

Conventions (those of docs/conventions.md, restated here as this program implements them):

* Chain: workpiece -> workpiece-branch axes (listed from the workpiece towards the frame)
  -> machine frame -> tool-branch axes (from the frame towards the tool) -> tool.  The tool
  point is expressed in the workpiece frame, which coincides with the machine frame when
  every axis is at zero.
* A positive command moves the tool in the + direction relative to the workpiece: a
  tool-branch axis moves its carriage by +q along its direction, a workpiece-branch axis
  moves the table by -q.
* Each axis contributes the pose of its moving component relative to the component that
  carries it.  For a workpiece-branch axis the chain passes through that pose backwards
  (its inverse), so its errors act on the tool point with the opposite sign.
* Linear axis J along machine axis e_i, m = +-1 the sign of its direction, negated on
  the workpiece branch: ``T = Trans(m q R(w) e_i) Trans(delta) R(eps)``: travel along the
  actual direction R(w) e_i (w = squareness rotation vector EA0J, EB0J, EC0J, zero where
  the model has no such error), then the component error motion: translation
  delta = (EXJ, EYJ, EZJ) in the carrier's orientation and rotation eps = (EAJ, EBJ, ECJ)
  about the carriage position.
* Rotary axis J about e_i (m as above), nominal centre c, location errors l = (EX0J,
  EY0J, EZ0J) (offset of the average line) and phi = (EA0J, EB0J, EC0J) (its tilt):
  ``T = Trans(c) Trans(delta) R(eps) Trans(-c) . Trans(c + l) Rot(R(phi) e_i, m q) Trans(-c - l)``:
  the nominal rotation about the actual average line, then the component error motion
  (delta, eps) about the nominal centre, in the carrier's orientation.  At q = 0 the
  location errors leave the carried part where it is.
* Tool: the spindle frame sits on the last tool-branch carriage at ``Trans(EX0T, EY0T,
  EZ0T) R(EA0T, EB0T, EC0T)`` (its zero position and orientation; zero unless the truth
  sets them), and the reflector is at the tool offset t in that frame.
* Small rotations are exact rotations by the rotation vector (Rodrigues); volcal's exact
  model uses Rx Ry Rz: the two differ at second order only.
* Volumetric error = actual - nominal tool point, in the workpiece frame.
* Units inside: mm and rad; rotary positions in deg in tables (``Geometry.to_internal``).
* Readings: ``length = |station - actual point| - dead_length``
  (volcal.measurement.tables's meaning of
  the dead length), stations fixed in the workpiece frame.

Noise (paper 002, Table 1, read as volcal reads it: tabulated values in um, rectangular
magnitudes are half-widths): laser length U = 0.2 + 0.3 L/1000 um at k = 2 (normal),
resolution 0.5 um, stability of the fixed sphere 0.1 um, form of the reflector 0.03 um
(rectangular), combined per reading; positioning repeatability of X, Y, Z 0.8, 0.6, 0.3 um
(rectangular half-widths), drawn once per visit of a pose (every reading is a visit in
sequential multilateration).  Rotary axes have no repeatability unless asked for.

The last section holds the tests' reference figure: a plain least-squares fit of the
simulated readings with volcal's own parameterisation (``Machine.evaluate`` and
``ErrorModel.basis``, passed in by the caller, so this module imports nothing from volcal)
and no datum on the errors (six station coordinates hold the rigid motion no
multilateration sees), solved by ``scipy.optimize.least_squares`` or by a minimum-norm
Gauss-Newton iteration.
"""
from __future__ import annotations

import math
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

MODELS_DIR = Path(__file__).resolve().parents[1] / "models"
_DIRS = {"+x": (0, 1), "-x": (0, -1), "+y": (1, 1), "-y": (1, -1), "+z": (2, 1), "-z": (2, -1)}
TRANS = "XYZ"
ROTS = "ABC"


# ======================================================================================
# geometry (travel, reference, centre: from the model file)


@dataclass(frozen=True)
class Axis:
    name: str
    kind: str  # "linear" | "rotary"
    index: int  # 0, 1, 2 = x, y, z
    sign: int  # +1 / -1: nominal direction
    branch: str  # "workpiece" | "tool"
    travel: tuple[float, float]  # file units (mm / deg)
    reference: float  # file units
    center: tuple[float, float, float]  # mm

    @property
    def rotary(self) -> bool:
        return self.kind == "rotary"

    @property
    def travel_internal(self) -> tuple[float, float]:
        lo, hi = self.travel
        return (math.radians(lo), math.radians(hi)) if self.rotary else (lo, hi)

    @property
    def reference_internal(self) -> float:
        return math.radians(self.reference) if self.rotary else self.reference

    @property
    def full_turn(self) -> bool:
        return self.rotary and self.travel[1] - self.travel[0] >= 360.0 - 1e-9

    @property
    def move_sign(self) -> int:
        """Sign of the nominal motion of the moving component relative to its carrier."""
        return self.sign if self.branch == "tool" else -self.sign


@dataclass(frozen=True)
class Geometry:
    name: str
    axes: tuple[Axis, ...]

    @property
    def axis_names(self) -> list[str]:
        return [a.name for a in self.axes]

    def axis(self, name: str) -> Axis:
        return next(a for a in self.axes if a.name == name)

    def to_internal(self, q_file: np.ndarray) -> np.ndarray:
        """Axis positions mm / deg -> mm / rad (last dimension in model order)."""
        q = np.array(q_file, dtype=float, copy=True)
        for k, a in enumerate(self.axes):
            if a.rotary:
                q[..., k] = np.deg2rad(q[..., k])
        return q

    def to_file(self, q_internal: np.ndarray) -> np.ndarray:
        q = np.array(q_internal, dtype=float, copy=True)
        for k, a in enumerate(self.axes):
            if a.rotary:
                q[..., k] = np.rad2deg(q[..., k])
        return q


def load_geometry(model: str | Path) -> Geometry:
    """Travel, reference, direction, branch and centre of each axis of a model file (a
    bundled name such as ``"mcv754_wxyzt"`` or a path)."""
    path = Path(model)
    if not path.suffix:
        path = MODELS_DIR / f"{model}.toml"
    doc = tomllib.loads(path.read_text(encoding="utf-8"))
    axes = []
    for d in doc["axis"]:
        idx, sgn = _DIRS[d["direction"]]
        axes.append(Axis(d["name"], d["kind"], idx, sgn, d["branch"],
                         (float(d["travel"][0]), float(d["travel"][1])),
                         float(d.get("reference", 0.0)),
                         tuple(float(v) for v in d.get("center", (0.0, 0.0, 0.0)))))
    return Geometry(doc["name"], tuple(axes))


# ======================================================================================
# exact transforms


def rotation(w: np.ndarray) -> np.ndarray:
    """Exact rotation matrices (N, 3, 3) of rotation vectors w (N, 3), Rodrigues."""
    w = np.atleast_2d(np.asarray(w, float))
    th2 = np.einsum("ni,ni->n", w, w)
    th = np.sqrt(th2)
    small = th < 1e-6
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(small, 1.0 - th2 / 6.0, np.sin(th) / np.where(small, 1.0, th))
        b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(th)) / np.where(small, 1.0, th2))
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -w[:, 2], w[:, 1]
    K[:, 1, 0], K[:, 1, 2] = w[:, 2], -w[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -w[:, 1], w[:, 0]
    return np.eye(3)[None] + a[:, None, None] * K + b[:, None, None] * (K @ K)


def hom(R: np.ndarray | None = None, t: np.ndarray | None = None, n: int | None = None
        ) -> np.ndarray:
    """Homogeneous transforms (N, 4, 4) from rotations (N, 3, 3) and translations (N, 3)."""
    if n is None:
        n = len(R) if R is not None else len(t)
    T = np.tile(np.eye(4), (n, 1, 1))
    if R is not None:
        T[:, :3, :3] = R
    if t is not None:
        T[:, :3, 3] = t
    return T


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (N, 4, 4)."""
    R = T[:, :3, :3]
    Rt = np.transpose(R, (0, 2, 1))
    return hom(Rt, -np.einsum("nij,nj->ni", Rt, T[:, :3, 3]))


# ======================================================================================
# the truth: error motions as functions of axis position, constants


Motion = Callable[[np.ndarray], np.ndarray]


@dataclass
class Truth:
    """True errors of a machine.  ``motions``: component error motions by ISO name
    (``EXX`` ... ``ECC``) as functions of the internal axis position (mm / rad) giving mm /
    rad; ``constants``: squareness (``EC0Y`` ...), rotary location errors (``EX0C`` ...)
    and the tool's zero position / orientation (``EX0T`` ... ``EC0T``); ``families``: the
    family each motion was drawn from (for messages).  Missing names are zero."""

    motions: dict[str, Motion] = field(default_factory=dict)
    constants: dict[str, float] = field(default_factory=dict)
    families: dict[str, str] = field(default_factory=dict)

    def motion(self, name: str, x: np.ndarray) -> np.ndarray:
        f = self.motions.get(name)
        return np.zeros_like(x, dtype=float) if f is None else np.broadcast_to(
            np.asarray(f(x), float), np.shape(x)).astype(float)

    def const(self, name: str) -> float:
        return float(self.constants.get(name, 0.0))

    def scaled(self, factor: float) -> Truth:
        """The same truth with every error multiplied by ``factor``."""
        return Truth({k: (lambda x, f=f: factor * np.asarray(f(x), float))
                      for k, f in self.motions.items()},
                     {k: factor * v for k, v in self.constants.items()}, dict(self.families))


ZERO = Truth()


def _axis_pose(a: Axis, x: np.ndarray, truth: Truth) -> np.ndarray:
    """Pose (N, 4, 4) of the component moved by axis a relative to its carrier."""
    n = len(x)
    J = a.name
    delta = np.column_stack([truth.motion(f"E{c}{J}", x) for c in TRANS])
    eps = np.column_stack([truth.motion(f"E{c}{J}", x) for c in ROTS])
    err = hom(None, delta, n) @ hom(rotation(eps))  # about the carriage / centre
    if a.kind == "linear":
        w = np.array([truth.const(f"E{c}0{J}") for c in ROTS])
        u = rotation(w[None])[0][:, a.index]  # actual direction of e_i (squareness tilt)
        nominal = hom(None, np.outer(a.move_sign * x, u), n)
        return nominal @ err
    c = np.asarray(a.center, float)
    loc = np.array([truth.const(f"E{c_}0{J}") for c_ in TRANS])
    tilt = np.array([truth.const(f"E{c_}0{J}") for c_ in ROTS])
    axis_dir = rotation(tilt[None])[0][:, a.index]  # actual direction of e_i
    R = rotation(np.outer(a.move_sign * x, axis_dir))
    pivot = c + loc
    move = hom(None, np.tile(pivot, (n, 1))) @ hom(R) @ hom(None, np.tile(-pivot, (n, 1)))
    err_c = hom(None, np.tile(c, (n, 1))) @ err @ hom(None, np.tile(-c, (n, 1)))
    return err_c @ move


def chain(geom: Geometry, q: np.ndarray, truth: Truth = ZERO) -> np.ndarray:
    """Pose (N, 4, 4) of the spindle frame in the workpiece frame at internal poses q."""
    q = np.atleast_2d(np.asarray(q, float))
    n = len(q)
    M = np.tile(np.eye(4), (n, 1, 1))
    for k, a in enumerate(geom.axes):
        T = _axis_pose(a, q[:, k], truth)
        M = M @ (inverse(T) if a.branch == "workpiece" else T)
    tz = np.array([truth.const(f"E{c}0T") for c in TRANS])
    tr = np.array([truth.const(f"E{c}0T") for c in ROTS])
    spindle = hom(rotation(tr[None]), tz[None])
    return M @ spindle


def tool_points(geom: Geometry, q: np.ndarray, tools: np.ndarray, truth: Truth = ZERO
                ) -> np.ndarray:
    """Tool (reflector) points (N, 3) mm in the workpiece frame; q internal (N, n_axes),
    tools (N, 3) or (3,) mm in the tool frame."""
    q = np.atleast_2d(np.asarray(q, float))
    t = np.broadcast_to(np.asarray(tools, float), (len(q), 3))
    M = chain(geom, q, truth)
    return np.einsum("nij,nj->ni", M[:, :3, :3], t) + M[:, :3, 3]


def true_error_um(geom: Geometry, truth: Truth, q: np.ndarray, tools: np.ndarray
                  ) -> np.ndarray:
    """True volumetric error (N, 3) um: actual - nominal tool point, workpiece frame."""
    return (tool_points(geom, q, tools, truth) - tool_points(geom, q, tools)) * 1e3


# ======================================================================================
# error motion families


def _u(a: Axis, x: np.ndarray) -> np.ndarray:
    lo, hi = a.travel_internal
    return 2.0 * (np.asarray(x, float) - lo) / (hi - lo) - 1.0


def poly_motion(a: Axis, coeffs: Sequence[float]) -> Motion:
    """c0 + c1 u + c2 u^2 + c3 u^3 in the normalised position u in [-1, 1] (monomials)."""
    c = np.asarray(coeffs, float)
    return lambda x: np.polynomial.polynomial.polyval(_u(a, x), c)


def fourier_motion(c0: float, cos: Sequence[float], sin: Sequence[float]) -> Motion:
    """c0 + sum_k (a_k cos k x + b_k sin k x), x the angle (rad)."""
    ca, sa = np.asarray(cos, float), np.asarray(sin, float)
    k = np.arange(1, len(ca) + 1)
    return lambda x: c0 + (np.cos(np.multiply.outer(np.asarray(x, float), k)) @ ca
                           + np.sin(np.multiply.outer(np.asarray(x, float), k)) @ sa)


def sines_motion(a: Axis, terms: Sequence[tuple[float, float, float]], const: float = 0.0,
                 slope: float = 0.0) -> Motion:
    """const + slope u + sum amp sin(2 pi u / period + phase), periods in units of u."""
    return lambda x: (const + slope * _u(a, x)
                      + sum(amp * np.sin(2 * np.pi * _u(a, x) / per + ph)
                            for amp, per, ph in terms))


def step_motion(a: Axis, height: float, centre: float, width: float, const: float = 0.0,
                slope: float = 0.0) -> Motion:
    """const + slope u + height tanh((u - centre) / width): a smooth step."""
    return lambda x: const + slope * _u(a, x) + height * np.tanh((_u(a, x) - centre) / width)


def table_motion(a: Axis, values: Sequence[float]) -> Motion:
    """Piecewise-linear interpolation of values at evenly spaced positions over the travel."""
    v = np.asarray(values, float)
    knots = np.linspace(-1.0, 1.0, len(v))
    return lambda x: np.interp(_u(a, x), knots, v)


def _amplitudes(a: Axis, comp: str) -> float:
    """Typical size of a component error motion (mm or rad)."""
    if a.kind == "linear":
        if comp in TRANS:
            return 12e-3 if TRANS.index(comp) == a.index else 6e-3
        return 20e-6
    if comp in TRANS:
        return 3e-3
    return 20e-6 if ROTS.index(comp) == a.index else 10e-6


def _violates_datum(a: Axis, comp: str, f: Motion, amp: float) -> bool:
    """True when f is clearly not zero at the reference, and (straightness) at either end
    of travel and not equal at both (no ISO 230 condition can hold)."""
    lo, hi = a.travel_internal
    ref = a.reference_internal
    vals = np.asarray(f(np.array([ref, lo, hi])), float)
    ok = abs(vals[0]) > 0.2 * amp
    if a.kind == "linear" and comp in TRANS and TRANS.index(comp) != a.index:
        ok = ok and abs(vals[1]) > 0.2 * amp and abs(vals[2]) > 0.2 * amp \
            and abs(vals[2] - vals[1]) > 0.2 * amp
    return ok


def _draw_motion(a: Axis, comp: str, family: str, rng: np.random.Generator, k: int,
                 scale: float) -> tuple[Motion, str]:
    amp = _amplitudes(a, comp) * scale
    sgn = lambda: rng.choice([-1.0, 1.0])  # noqa: E731
    for _ in range(200):
        const = sgn() * rng.uniform(0.3, 0.8) * amp
        if family == "constant":
            f, name = (lambda x, c=const: np.full(np.shape(x), c)), "constant"
        elif family == "fourier":  # full-turn rotary axes: harmonics 1-3 of the angle
            h = rng.uniform(0.3, 0.6, 3) * amp * np.array([1.0, 0.7, 0.5])
            ph = rng.uniform(0, 2 * np.pi, 3)
            f, name = fourier_motion(const, h * np.cos(ph), h * np.sin(ph)), "fourier h1-3"
        elif family == "fourier-high":  # full turn, not representable: harmonics 1-6
            h = rng.uniform(0.15, 0.4, 6) * amp
            ph = rng.uniform(0, 2 * np.pi, 6)
            f, name = fourier_motion(const, h * np.cos(ph), h * np.sin(ph)), "fourier h1-6"
        elif family == "cubic":
            c = rng.uniform(-0.5, 0.5, 4) * amp
            c[0] = const
            c[1] = sgn() * rng.uniform(0.25, 0.6) * amp
            f, name = poly_motion(a, c), "cubic"
        elif family == "nonrep":  # sines of non-integer periods, smooth steps, tables
            kind = ("sines", "step", "table")[k % 3]
            slope = sgn() * rng.uniform(0.2, 0.5) * amp
            if kind == "sines":
                terms = [(rng.uniform(0.15, 0.4) * amp, per, rng.uniform(0, 2 * np.pi))
                         for per in rng.uniform(0.45, 1.7, 2)]
                f = sines_motion(a, terms, const, slope)
            elif kind == "step":
                f = step_motion(a, sgn() * rng.uniform(0.2, 0.4) * amp, rng.uniform(-0.5, 0.5),
                                rng.uniform(0.08, 0.2), const, slope)
            else:
                n = int(rng.integers(6, 10))
                vals = const + slope * np.linspace(-1, 1, n) + rng.uniform(-0.4, 0.4, n) * amp
                f = table_motion(a, vals)
            name = kind
        else:
            raise ValueError(f"unknown family {family!r}")
        if _violates_datum(a, comp, f, amp):
            return f, name
    raise RuntimeError(f"could not draw a motion for E{comp}{a.name}")


def draw_truth(geom: Geometry, rng: np.random.Generator, family: str = "representable", *,
               full_turn: str | None = None, rotary_scale: float = 1.0,
               tool_orientation: bool = True) -> Truth:
    """Random true errors.

    family: ``"representable"``: cubic polynomials in the position of linear and
        partial-turn rotary axes, Fourier series (harmonics 1-3 of the angle plus a
        constant) for full-turn rotary axes; ``"nonrep"``: sums of sines with
        non-integer periods, smooth steps (tanh) and piecewise-linear tables, each plus a
        constant and a slope (full-turn axes: harmonics 1-6).
    full_turn: family of the full-turn rotary axes instead (``"fourier"``,
        ``"fourier-high"``, ``"constant"``, ``"cubic"``).
    rotary_scale: factor on the rotary axes' error motions and location errors.
    Every motion is clearly non-zero at its reference position (a straightness also at
    both ends of travel, with different values there); squareness, rotary location
    errors and, with ``tool_orientation``, the spindle's zero orientation are non-zero.
    """
    if family not in ("representable", "nonrep"):
        raise ValueError(f"unknown family {family!r}")
    tr = Truth()
    k = 0
    sgn = lambda: rng.choice([-1.0, 1.0])  # noqa: E731
    linear_dirs = {a.index for a in geom.axes if a.kind == "linear"}
    for a in geom.axes:
        if a.full_turn:
            fam = full_turn or ("fourier" if family == "representable" else "fourier-high")
        else:
            fam = "cubic" if family == "representable" else "nonrep"
        scale = rotary_scale if a.rotary else 1.0
        for comp in TRANS + ROTS:
            f, name = _draw_motion(a, comp, fam, rng, k, scale)
            tr.motions[f"E{comp}{a.name}"] = f
            tr.families[f"E{comp}{a.name}"] = name
            k += 1
        if a.kind == "linear":
            # squareness: the later axis of each pair of linear axes (x < y < z) carries it
            for j in range(3):
                m = 3 - a.index - j
                if j != a.index and m != a.index and m < a.index and m in linear_dirs:
                    tr.constants[f"E{ROTS[j]}0{a.name}"] = sgn() * rng.uniform(20e-6, 60e-6)
        else:
            for j in range(3):
                if j != a.index:
                    tr.constants[f"E{TRANS[j]}0{a.name}"] = \
                        sgn() * rng.uniform(5e-3, 15e-3) * scale
                    tr.constants[f"E{ROTS[j]}0{a.name}"] = \
                        sgn() * rng.uniform(10e-6, 30e-6) * scale
    if tool_orientation:
        for c in ROTS:
            tr.constants[f"E{c}0T"] = sgn() * rng.uniform(10e-6, 40e-6)
    return tr


# ======================================================================================
# plans, stations, noise, measurement


def linspace_travel(a: Axis, n: int) -> np.ndarray:
    """n evenly spaced positions (file units) over the travel; a full turn without its
    duplicate end."""
    lo, hi = a.travel
    return np.linspace(lo, hi, n + 1)[:-1] if a.full_turn else np.linspace(lo, hi, n)


def grid(geom: Geometry, counts: dict[str, int], fixed: dict[str, float] | None = None
         ) -> np.ndarray:
    """Full grid (n_poses, n_axes) in file units: ``counts[axis]`` positions per axis;
    axes not in counts sit at ``fixed[axis]`` (default 0)."""
    fixed = fixed or {}
    levels = [linspace_travel(a, counts[a.name]) if a.name in counts
              else np.array([fixed.get(a.name, 0.0)]) for a in geom.axes]
    mesh = np.meshgrid(*levels, indexing="ij")
    return np.column_stack([m.ravel() for m in mesh])


def diagonals(geom: Geometry, n: int, fixed: dict[str, float] | None = None) -> np.ndarray:
    """The 4 body diagonals of the linear-axis box, n interior points each (file units)."""
    fixed = fixed or {}
    lin = [k for k, a in enumerate(geom.axes) if a.kind == "linear"]
    s = np.arange(1, n + 1) / (n + 1)
    rows = []
    for flips in ((0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)):
        q = np.zeros((n, len(geom.axes)))
        for k, a in enumerate(geom.axes):
            q[:, k] = fixed.get(a.name, 0.0)
        for k, f in zip(lin, flips):
            lo, hi = geom.axes[k].travel
            q[:, k] = lo + (hi - lo) * (1 - s if f else s)
        rows.append(q)
    return np.vstack(rows)


def place_stations(points: np.ndarray, n: int, rng: np.random.Generator, *,
                   margin: float = 300.0) -> np.ndarray:
    """n station positions (n, 3) mm around a point cloud: on an ellipse around its
    bounding box grown by ``margin``, alternating low and high, with a seeded jitter."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    c, half = (lo + hi) / 2, (hi - lo) / 2
    ax = half[:2] * np.sqrt(2) + margin
    dz = max(hi[2] - lo[2], 200.0)
    phi = 2 * np.pi * (np.arange(n) + 0.25 + rng.uniform(-0.12, 0.12, n)) / n
    z = c[2] + np.where(np.arange(n) % 2 == 0, -0.35, 0.35) * dz + rng.uniform(-0.05, 0.05, n) * dz
    S = np.column_stack([c[0] + ax[0] * np.cos(phi), c[1] + ax[1] * np.sin(phi), z])
    dmin = np.linalg.norm(points[:, None] - S[None], axis=-1).min()
    assert dmin > 100.0, dmin
    return S


@dataclass(frozen=True)
class Noise:
    """Paper 002's budget (Table 1) as this module reads it (see the module docstring)."""

    laser_um: float = 0.2  # U = laser_um + laser_per_m_um * L[m], k = 2
    laser_per_m_um: float = 0.3
    rect_um: tuple[float, ...] = (0.5, 0.1, 0.03)  # resolution, fixed sphere, reflector
    repeat_um: dict = field(default_factory=lambda: {"X": 0.8, "Y": 0.6, "Z": 0.3})
    repeat_rad: dict = field(default_factory=dict)  # rotary axes: none unless given

    def length_sigma_mm(self, L_mm: np.ndarray) -> np.ndarray:
        u_laser = (self.laser_um + self.laser_per_m_um * np.abs(L_mm) / 1000.0) / 2.0
        u2 = u_laser ** 2 + sum((a / math.sqrt(3)) ** 2 for a in self.rect_um)
        return np.sqrt(u2) * 1e-3

    def draw_length_mm(self, L_mm: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        n = len(L_mm)
        e = rng.normal(0.0, (self.laser_um + self.laser_per_m_um * np.abs(L_mm) / 1000) / 2, n)
        for a in self.rect_um:
            e = e + rng.uniform(-a, a, n)
        return e * 1e-3

    def axis_half_width(self, a: Axis) -> float:
        """Half-width of the positioning repeatability in internal units (mm / rad)."""
        return (self.repeat_rad.get(a.name, 0.0) if a.rotary
                else self.repeat_um.get(a.name, 0.0) * 1e-3)


@dataclass
class Simulation:
    geometry: Geometry
    truth: Truth
    measurements: pd.DataFrame  # volcal's input format
    stations: pd.DataFrame  # true: station, x_mm, y_mm, z_mm, dead_length_mm
    stations_start: pd.DataFrame  # approximate: station, x_mm, y_mm, z_mm
    sigma_mm: np.ndarray  # standard uncertainty of each reading (this module's budget)
    poses: np.ndarray  # (n_poses, n_axes) file units
    tools: np.ndarray  # (K, 3) mm


def simulate(geom: Geometry, truth: Truth, poses_file: np.ndarray, tools: np.ndarray,
             rng: np.random.Generator, *, n_stations: int = 6, noise: Noise | None = Noise(),
             axis_repeatability: bool = True, start_jitter_mm: float = 2.0,
             stations: np.ndarray | None = None) -> Simulation:
    """Sequential multilateration: every station measures every (pose, tool); each
    reading is its own visit of the pose (own repeatability draw).  ``stations``: their
    true positions (K, 3) mm; default drawn around the points."""
    poses_file = np.atleast_2d(np.asarray(poses_file, float))
    tools = np.atleast_2d(np.asarray(tools, float))
    P, K = len(poses_file), len(tools)
    q_cmd = geom.to_internal(poses_file)
    # points = (tool, pose), tool-major
    pi = np.tile(np.arange(P), K)
    ti = np.repeat(np.arange(K), P)
    nominal = tool_points(geom, q_cmd[pi], tools[ti])
    if stations is None:
        S = place_stations(nominal, n_stations, rng)
    else:  # given positions (mm), e.g. a plan's
        S = np.asarray(stations, float).reshape(-1, 3)
        n_stations = len(S)
    dead = rng.uniform(-2.0, 2.0, n_stations)
    n_pt = P * K
    si = np.repeat(np.arange(n_stations), n_pt)  # station-major readings
    ri = np.tile(np.arange(n_pt), n_stations)
    q_act = q_cmd[pi[ri]].copy()
    if noise is not None and axis_repeatability:
        for k, a in enumerate(geom.axes):
            h = noise.axis_half_width(a)
            if h:
                q_act[:, k] += rng.uniform(-h, h, len(ri))
    actual = tool_points(geom, q_act, tools[ti[ri]], truth)
    dist = np.linalg.norm(actual - S[si], axis=1)
    length = dist - dead[si]
    if noise is not None:
        length = length + noise.draw_length_mm(length, rng)
    # the standard uncertainty of each reading: length part and the axis repeatability
    # projected on the beam (derivative of the nominal distance by finite differences)
    nom = nominal[ri]
    beam = (nom - S[si]) / np.linalg.norm(nom - S[si], axis=1)[:, None]
    nz = noise or Noise()
    var = nz.length_sigma_mm(length) ** 2
    for k, a in enumerate(geom.axes):
        h = nz.axis_half_width(a)
        if not h:
            continue
        dq = np.zeros_like(q_cmd)
        step = 1e-6
        dq[:, k] = step
        d_nom = (tool_points(geom, (q_cmd + dq)[pi], tools[ti]) - nominal)[ri] / step
        var = var + (np.einsum("ni,ni->n", beam, d_nom) * h / math.sqrt(3)) ** 2
    ids = np.array([f"S{j + 1}" for j in range(n_stations)], dtype=object)
    width = len(str(n_pt))
    pids = np.array([f"p{j + 1:0{width}d}" for j in range(n_pt)], dtype=object)
    meas = pd.DataFrame({"station": ids[si], "point": pids[ri]})
    for k, name in enumerate(geom.axis_names):
        meas[name] = poses_file[pi[ri], k]
    for j, c in enumerate("xyz"):
        meas[f"tool_{c}"] = tools[ti[ri], j]
    meas["length"] = length
    st = pd.DataFrame({"station": ids, "x_mm": S[:, 0], "y_mm": S[:, 1], "z_mm": S[:, 2],
                       "dead_length_mm": dead})
    S0 = S + rng.normal(0.0, start_jitter_mm, S.shape)
    st0 = pd.DataFrame({"station": ids, "x_mm": S0[:, 0], "y_mm": S0[:, 1], "z_mm": S0[:, 2]})
    return Simulation(geom, truth, meas, st, st0, np.sqrt(var), poses_file, tools)


def measurement_arrays(geom: Geometry, meas: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Internal poses (N, n_axes) and tool offsets (N, 3) of a measurement table."""
    q = geom.to_internal(meas[geom.axis_names].to_numpy(float))
    t = meas[["tool_x", "tool_y", "tool_z"]].to_numpy(float)
    return q, t


# ======================================================================================
# comparison modulo the gauge


def field_error_modulo_gauge(pred: np.ndarray, truth: np.ndarray, nominal_points: np.ndarray,
                             *, return_max: bool = False):
    """RMS (over points and components, um) of pred - truth (N, 3) um after removing the
    least-squares small rigid motion a + w x p (p: nominal points (N, 3) mm): the one
    motion between the stations and the machine no multilateration sees."""
    d = (np.asarray(pred, float) - np.asarray(truth, float)).ravel()
    p = np.asarray(nominal_points, float)
    p = p - p.mean(axis=0)
    n = len(p)
    A = np.zeros((3 * n, 6))
    A[0::3, 0] = A[1::3, 1] = A[2::3, 2] = 1.0
    x, y, z = p.T
    # w x p = (wy z - wz y, wz x - wx z, wx y - wy x)
    A[0::3, 4], A[0::3, 5] = z, -y
    A[1::3, 3], A[1::3, 5] = -z, x
    A[2::3, 3], A[2::3, 4] = y, -x
    col = np.linalg.norm(A, axis=0)
    sol = np.linalg.lstsq(A / col, d, rcond=None)[0]
    r = d - (A / col) @ sol
    rms = float(np.sqrt(np.mean(r ** 2)))
    return (rms, float(np.max(np.abs(r)))) if return_max else rms


# ======================================================================================
# the reference figure: a plain least-squares fit, no datum


@dataclass
class ReferenceFit:
    theta: np.ndarray  # error parameters (mm / rad) of the error model passed in
    stations: np.ndarray  # (K, 3) mm
    dead: np.ndarray  # (K,) mm
    residual_rms_um: float
    chi2_per_dof: float
    rank: int
    iterations: int
    method: str


def _linear_model(machine, error_model, q: np.ndarray, t: np.ndarray):
    """Nominal points p0 (N, 3) and G (N, 3, P) with p = p0 + G theta (first order)."""
    p0, _, Je = machine.evaluate(q, t, np.zeros(machine.n_errors))
    G = np.einsum("nik,nkp->nip", Je, error_model.basis(q))
    return p0, G


def reference_field_um(machine, error_model, theta: np.ndarray, q: np.ndarray,
                       tools: np.ndarray) -> np.ndarray:
    """Volumetric error (N, 3) um of the first-order model at parameters theta."""
    t = np.broadcast_to(np.asarray(tools, float), (len(q), 3))
    _, G = _linear_model(machine, error_model, q, t)
    return np.einsum("nip,p->ni", G, theta) * 1e3


def gauge_hold(S: np.ndarray) -> list[tuple[int, int]]:
    """(station, coordinate) pairs to hold so that exactly the rigid motion of the whole
    set of stations is fixed (3-2-1): every coordinate of the first station, the two
    coordinates of the second across the line from the first, the coordinate of the third
    along the normal of the plane of the three."""
    d = S[1] - S[0]
    n = np.cross(d, S[2] - S[0])
    j = int(np.argmax(np.abs(d)))
    return [(0, 0), (0, 1), (0, 2)] + [(1, c) for c in range(3) if c != j] \
        + [(2, int(np.argmax(np.abs(n))))]


def reference_fit(machine, error_model, meas: pd.DataFrame, stations_start: pd.DataFrame,
                  sigma_mm: np.ndarray, *, method: str = "scipy", max_iter: int = 50
                  ) -> ReferenceFit:
    """See :func:`_reference_fit`; one BLAS thread (small dense problems on a shared
    machine: threads only contend)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return _reference_fit(machine, error_model, meas, stations_start, sigma_mm,
                              method=method, max_iter=max_iter)


def _reference_fit(machine, error_model, meas: pd.DataFrame, stations_start: pd.DataFrame,
                   sigma_mm: np.ndarray, *, method: str = "scipy", max_iter: int = 50
                   ) -> ReferenceFit:
    """Fit error parameters, station positions and dead lengths to the readings by plain
    weighted least squares with no datum on the errors: every error parameter, every dead
    length and the stations are free except six station coordinates (:func:`gauge_hold`)
    held at their start values, which fixes the one rigid motion between stations and
    machine that no multilateration sees and nothing else.  (Left free, that motion is a
    curved valley of the first-order model: a solver walks along it and trades the
    model's first-order rotation against the stations' exact one.)  The remaining
    minimisers form an affine set (what the data cannot see is linear in the
    parameters) and all give the same volumetric field.

    The start: errors zero; stations and dead lengths fitted to the nominal points from
    ``stations_start``.

    machine, error_model: volcal's ``Machine`` and ``ErrorModel`` (only ``evaluate``,
    ``basis``, ``n_errors`` and ``spec.axes`` are used).
    method: ``"scipy"`` (``scipy.optimize.least_squares``, trf, x_scale from the
    Jacobian's column norms, exact trust-region steps on the dense Jacobian: its error
    columns are dense anyway), ``"scipy-sparse"`` (the same with a sparse Jacobian and
    LSMR steps: the same solution, 3x slower on the 5-axis cases) or ``"gauss-newton"``
    (minimum-norm steps, ``numpy.linalg.lstsq`` on the column-scaled Jacobian).
    """
    import scipy.sparse as sps

    names = [a.name for a in machine.spec.axes]
    rot = [a.is_rotary for a in machine.spec.axes]
    q = meas[names].to_numpy(float).copy()
    q[:, rot] = np.deg2rad(q[:, rot])
    t = meas[["tool_x", "tool_y", "tool_z"]].to_numpy(float)
    L = meas["length"].to_numpy(float)
    ids = list(stations_start["station"])
    si = np.array([ids.index(s) for s in meas["station"]])
    K = len(ids)
    # one linearisation per distinct (pose, tool)
    key = np.column_stack([q, t])
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    p0u, Gu = _linear_model(machine, error_model, uniq[:, :len(names)], uniq[:, len(names):])
    P = Gu.shape[2]
    n_x = P + 4 * K
    w = 1.0 / np.asarray(sigma_mm, float)
    N = len(L)
    rows = np.arange(N)

    def unpack(x):
        return x[:P], x[P:P + 3 * K].reshape(K, 3), x[P + 3 * K:]

    def fun_full(x):
        theta, S, d = unpack(x)
        v = p0u[inv] + np.einsum("nip,p->ni", Gu[inv], theta) - S[si]
        return (np.linalg.norm(v, axis=1) - d[si] - L) * w

    def jac_full(x):
        theta, S, d = unpack(x)
        v = p0u[inv] + np.einsum("nip,p->ni", Gu[inv], theta) - S[si]
        u = v / np.linalg.norm(v, axis=1)[:, None]
        J = np.zeros((N, n_x))
        J[:, :P] = np.einsum("ni,nip->np", u, Gu[inv]) * w[:, None]
        for j in range(3):
            J[rows, P + 3 * si + j] = -u[:, j] * w
        J[rows, P + 3 * K + si] = -w
        return J

    x_full = np.concatenate([np.zeros(P), stations_start[["x_mm", "y_mm", "z_mm"]]
                             .to_numpy(float).ravel(), np.zeros(K)])
    # start: stations and dead lengths fitted to the nominal points (errors zero)
    for _ in range(30):
        dx = np.linalg.lstsq(jac_full(x_full)[:, P:], -fun_full(x_full), rcond=None)[0]
        x_full[P:] += dx
        if np.max(np.abs(dx)) < 1e-10:
            break
    free = np.ones(n_x, bool)
    for k, c in gauge_hold(unpack(x_full)[1]):
        free[P + 3 * k + c] = False

    def fun(xf):
        x = x_full.copy()
        x[free] = xf
        return fun_full(x)

    def jac(xf):
        x = x_full.copy()
        x[free] = xf
        return jac_full(x)[:, free]

    xf = x_full[free].copy()
    if method in ("scipy", "scipy-sparse"):
        from scipy.optimize import least_squares
        col = np.linalg.norm(jac(xf), axis=0)
        col[col == 0] = 1.0
        if method == "scipy":
            opts = dict(jac=jac, tr_solver="exact")
        else:
            opts = dict(jac=lambda x: sps.csr_matrix(jac(x)), tr_solver="lsmr",
                        tr_options={"atol": 1e-12, "btol": 1e-12})
        sol = least_squares(fun, xf, method="trf", x_scale=1.0 / col, ftol=1e-12,
                            xtol=1e-12, gtol=1e-10, max_nfev=100, **opts)
        xf, its = sol.x, int(sol.nfev)
    elif method == "gauss-newton":
        its = 0
        r = fun(xf)
        for its in range(1, max_iter + 1):  # noqa: B007  (the count is reported)
            J = jac(xf)
            col = np.linalg.norm(J, axis=0)
            col[col == 0] = 1.0
            dx = np.linalg.lstsq(J / col, -r, rcond=None)[0] / col
            xf = xf + dx
            r, before = fun(xf), float(r @ r)
            if before - float(r @ r) <= 1e-12 * before:
                break
    else:
        raise ValueError(f"unknown method {method!r}")
    x = x_full.copy()
    x[free] = xf
    r = fun_full(x)
    J = jac(xf)
    col = np.linalg.norm(J, axis=0)
    col[col == 0] = 1.0
    sv = np.linalg.svd(J / col, compute_uv=False)
    rank = int(np.sum(sv > sv[0] * max(J.shape) * np.finfo(float).eps))
    theta, S, d = unpack(x)
    res_um = r / w * 1e3
    return ReferenceFit(theta, S, d, float(np.sqrt(np.mean(res_um ** 2))),
                        float(np.sum(r ** 2) / (N - rank)), rank, its, method)
