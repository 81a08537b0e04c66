"""Where a tracker may stand and what it can see: regions, obstacles, the reflector.

All coordinates are in the machine's workpiece frame, in mm; angles in degrees in the
declarations, radians inside.

* :class:`Region`: a convex polygon in the plane normal to ``up`` (the floor or the table)
  with height limits along ``up``; a box is a four-corner polygon.  Several regions give
  a union; each station stands in one of them.
* :class:`Obstacle`: an axis-aligned box or a cylinder that the beam must not cross; fixed
  in the machine frame, or moving with the tool point (a spindle head: its coordinates are
  then relative to the nominal tool point of the reading).  Cylinders are checked as
  capsules (round end caps), which can only be stricter than the cylinder.
* :class:`Reflector`: the acceptance half-angle of the reflector about its mounting axis.
  The axis is fixed in the tool frame (turned with the rotary axes), or, as in paper 004,
  re-aimed at every station set-up: then it points from the workspace centre to the
  station and every beam of that station must lie within the half-angle of it.
* :class:`Constraints`: all of the above plus the minimum station-to-point distance and the
  tracker's maximum range.  :meth:`Constraints.with_margins` gives the stricter set a plan
  is searched in (``margin_deg`` off the acceptance angle, ``margin_mm`` inside every
  region, added to the minimum distance and the obstacles, off the range), so that a
  tracker set up a little off its planned spot, or a reflector aimed a little off, still
  keeps the declared limits.

:func:`reading_violations` lists every reading that breaks a constraint (the check every
plan passes before it is written), :func:`station_feasible` says whether a station
position is allowed at all.  Both are plain numpy, independent of the optimisers.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from volcal.base.exceptions import InputError

__all__ = [
    "Region",
    "Obstacle",
    "Reflector",
    "Constraints",
    "reading_violations",
    "station_feasible",
    "beam_blocked",
    "stations_ok",
    "aim_axes",
    "beam_angles_deg",
    "segment_box_clearance",
    "constraints_from_dict",
    "constraint_slack",
]

_AXES = {"x": 0, "y": 1, "z": 2}


def _plane_axes(up: str) -> tuple[int, int, int]:
    u = _AXES[up]
    a, b = [i for i in range(3) if i != u]
    return a, b, u


@dataclass(frozen=True)
class Region:
    """A convex polygon (vertices (n, 2) mm, in the two coordinates other than ``up``, in
    their natural order: for up = z, (x, y)) extruded between heights ``low`` and
    ``high`` (mm along ``up``)."""

    vertices: np.ndarray
    low: float
    high: float
    up: str = "z"
    name: str = "region"

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, float)
        if v.ndim != 2 or v.shape[1] != 2 or len(v) < 3:
            raise InputError(f"region {self.name!r}: expected at least 3 vertices (x, y) in mm")
        if self.up not in _AXES:
            raise InputError(f"region {self.name!r}: 'up' must be x, y or z, got {self.up!r}")
        if not self.high >= self.low:
            raise InputError(f"region {self.name!r}: height limits {self.low} > {self.high}")
        # counter-clockwise, and convex (the optimisers use its edges as linear constraints)
        area2 = float(np.sum(v[:, 0] * np.roll(v[:, 1], -1) - np.roll(v[:, 0], -1) * v[:, 1]))
        if area2 < 0:
            v = v[::-1]
        e = np.roll(v, -1, axis=0) - v
        cross = e[:, 0] * np.roll(e, -1, axis=0)[:, 1] - e[:, 1] * np.roll(e, -1, axis=0)[:, 0]
        if area2 == 0 or (cross < -1e-9 * np.abs(area2)).any():
            raise InputError(
                f"region {self.name!r}: the polygon must be convex with a non-zero area "
                "(split a concave region into several convex ones)"
            )
        object.__setattr__(self, "vertices", v)

    @classmethod
    def box(cls, lo: Sequence[float], hi: Sequence[float], name: str = "box") -> Region:
        """An axis-aligned box from corners lo, hi (x, y, z mm), up = z."""
        a, b = np.asarray(lo, float), np.asarray(hi, float)
        v = np.array([[a[0], a[1]], [b[0], a[1]], [b[0], b[1]], [a[0], b[1]]])
        return cls(v, float(a[2]), float(b[2]), "z", name)

    def halfspaces(self) -> tuple[np.ndarray, np.ndarray]:
        """(A (m, 3), b (m,)) with A s <= b exactly inside (edges and height limits)."""
        a, b_, u = _plane_axes(self.up)
        v = self.vertices
        e = np.roll(v, -1, axis=0) - v
        n2 = np.column_stack([e[:, 1], -e[:, 0]])  # outward normals of a CCW polygon
        A = np.zeros((len(v) + 2, 3))
        A[: len(v), a], A[: len(v), b_] = n2[:, 0], n2[:, 1]
        bb = np.empty(len(v) + 2)
        bb[: len(v)] = np.sum(n2 * v, axis=1)
        A[len(v), u], bb[len(v)] = 1.0, self.high
        A[len(v) + 1, u], bb[len(v) + 1] = -1.0, -self.low
        return A, bb

    def corners(self) -> np.ndarray:
        """(2 n, 3) mm: the polygon's vertices at the low and at the high height."""
        a, b_, u = _plane_axes(self.up)
        n = len(self.vertices)
        out = np.empty((2 * n, 3))
        out[:, a] = np.tile(self.vertices[:, 0], 2)
        out[:, b_] = np.tile(self.vertices[:, 1], 2)
        out[:, u] = np.repeat([self.low, self.high], n)
        return out

    def contains(self, s: np.ndarray, tol: float = 1e-6) -> np.ndarray:
        A, b = self.halfspaces()
        s = np.atleast_2d(np.asarray(s, float))
        return np.all(s @ A.T <= b + tol, axis=1)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """n uniform points inside (rejection from the bounding box)."""
        a, b_, u = _plane_axes(self.up)
        lo, hi = self.vertices.min(0), self.vertices.max(0)
        out = np.empty((0, 3))
        while len(out) < n:
            m = max(2 * (n - len(out)), 8)
            s = np.empty((m, 3))
            s[:, a] = rng.uniform(lo[0], hi[0], m)
            s[:, b_] = rng.uniform(lo[1], hi[1], m)
            s[:, u] = rng.uniform(self.low, self.high, m)
            out = np.vstack([out, s[self.contains(s)]])
        return out[:n]

    @property
    def volume(self) -> float:
        v = self.vertices
        area = 0.5 * abs(np.sum(v[:, 0] * np.roll(v[:, 1], -1) - np.roll(v[:, 0], -1) * v[:, 1]))
        return float(area * max(self.high - self.low, 1e-9))

    def inset(self, margin_mm: float) -> Region:
        """The region shrunk by ``margin_mm`` (mm) on every face (edges and height limits);
        :class:`InputError` when nothing is left."""
        m = float(margin_mm)
        if m == 0:
            return self
        v = self.vertices
        e = np.roll(v, -1, axis=0) - v
        n = np.column_stack([e[:, 1], -e[:, 0]])
        length = np.linalg.norm(n, axis=1, keepdims=True)
        if np.any(length == 0):
            raise InputError(f"region {self.name!r}: a vertex is listed twice in a row")
        n /= length  # outward unit normals (CCW polygon)
        c = np.sum(n * v, axis=1) - m  # edge k: n_k . x = c_k
        # vertex k of the inset polygon: where edges k - 1 and k meet
        out = np.empty_like(v)
        for k in range(len(v)):
            A = np.array([n[k - 1], n[k]])
            if abs(np.linalg.det(A)) < 1e-12:  # a straight or repeated vertex
                raise InputError(
                    f"region {self.name!r}: vertex {k + 1} lies on a straight line with its "
                    "neighbours (or repeats one); list only the corners of the polygon"
                )
            out[k] = np.linalg.solve(A, np.array([c[k - 1], c[k]]))
        x, y = out[:, 0], out[:, 1]
        area2 = float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
        inside = np.all(out @ n.T <= c + 1e-6 * max(1.0, np.abs(c).max()), axis=1)
        if area2 <= 0 or not inside.all() or self.high - self.low < 2 * m:
            raise InputError(
                f"region {self.name!r}: a margin of {m:g} mm on every face leaves no room "
                "for the tracker; enlarge the region or lower the margin (margin_mm)"
            )
        return Region(out, self.low + m, self.high - m, self.up, self.name)

    def clearance(self, s: np.ndarray) -> np.ndarray:
        """(M,) mm: how far each point (M, 3) lies inside the region, i.e. its distance to
        the nearest face (negative outside)."""
        A, b = self.halfspaces()
        nrm = np.linalg.norm(A, axis=1)
        s = np.atleast_2d(np.asarray(s, float))
        return np.min((b - s @ A.T) / nrm, axis=1)


@dataclass(frozen=True)
class Obstacle:
    """A box (``lo``, ``hi`` corners) or a cylinder (axis from ``p0`` to ``p1``, ``radius``),
    mm; ``moves_with`` "frame" (fixed) or "tool" (coordinates relative to the nominal tool
    point of each reading)."""

    kind: str
    lo: tuple[float, float, float] = (0.0, 0.0, 0.0)
    hi: tuple[float, float, float] = (0.0, 0.0, 0.0)
    p0: tuple[float, float, float] = (0.0, 0.0, 0.0)
    p1: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius: float = 0.0
    moves_with: str = "frame"
    name: str = "obstacle"

    def __post_init__(self) -> None:
        if self.kind not in ("box", "cylinder"):
            raise InputError(f"obstacle {self.name!r}: kind must be box or cylinder")
        if self.moves_with not in ("frame", "tool"):
            raise InputError(f"obstacle {self.name!r}: moves_with must be frame or tool")
        if self.kind == "box" and not np.all(np.asarray(self.hi) >= np.asarray(self.lo)):
            raise InputError(f"obstacle {self.name!r}: every 'hi' must be >= 'lo'")
        if self.kind == "cylinder" and not self.radius > 0:
            raise InputError(f"obstacle {self.name!r}: the radius must be > 0 mm")


@dataclass(frozen=True)
class Reflector:
    """Acceptance half-angle (deg) about the mounting axis; ``axis`` a unit vector in the
    tool frame, or None: re-aimed at every station (paper 004)."""

    half_angle_deg: float = 180.0
    axis: tuple[float, float, float] | None = None

    @property
    def limited(self) -> bool:
        return self.half_angle_deg < 180.0


@dataclass(frozen=True)
class Constraints:
    """Everything that restricts a station position or a reading (see the module doc)."""

    regions: tuple[Region, ...] = ()
    obstacles: tuple[Obstacle, ...] = ()
    reflector: Reflector = field(default_factory=Reflector)
    min_distance_mm: float = 0.0
    max_range_mm: float = np.inf

    def with_margins(self, margin_deg: float = 0.0, margin_mm: float = 0.0) -> Constraints:
        """The stricter constraints a plan is searched in: the acceptance half-angle less
        ``margin_deg`` (deg), every region shrunk by ``margin_mm`` (mm) on every face, the
        minimum distance plus and the range less ``margin_mm``, every obstacle grown by
        ``margin_mm``.  :class:`InputError` when a margin is negative or leaves nothing."""
        md, mm = float(margin_deg), float(margin_mm)
        if not (np.isfinite(md) and md >= 0 and np.isfinite(mm) and mm >= 0):
            raise InputError(
                f"margins must be finite and >= 0, got {md:g} deg and {mm:g} mm "
                "(margin_deg, margin_mm)"
            )
        ref = self.reflector
        if ref.limited:
            if not ref.half_angle_deg - md > 0:
                raise InputError(
                    f"a margin of {md:g} deg leaves nothing of the reflector's acceptance "
                    f"half-angle {ref.half_angle_deg:g} deg (margin_deg)"
                )
            ref = Reflector(ref.half_angle_deg - md, ref.axis)
        if self.max_range_mm - mm <= self.min_distance_mm + mm:
            raise InputError(
                f"a margin of {mm:g} mm leaves no distance between the minimum distance "
                f"{self.min_distance_mm:g} mm and the range {self.max_range_mm:g} mm (margin_mm)"
            )
        obstacles = []
        for ob in self.obstacles:
            if ob.kind == "box":
                lo = tuple(float(v) - mm for v in ob.lo)
                hi = tuple(float(v) + mm for v in ob.hi)
                obstacles.append(
                    Obstacle("box", lo=lo, hi=hi, moves_with=ob.moves_with, name=ob.name)  # type: ignore[arg-type]
                )
            else:
                obstacles.append(
                    Obstacle(
                        "cylinder",
                        p0=ob.p0,
                        p1=ob.p1,
                        radius=ob.radius + mm,
                        moves_with=ob.moves_with,
                        name=ob.name,
                    )
                )
        return Constraints(
            tuple(r.inset(mm) for r in self.regions),
            tuple(obstacles),
            ref,
            self.min_distance_mm + mm,
            self.max_range_mm - mm,
        )


def _segment_box(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Whether segments a[i] -> b[i] (N, 3) cross the open box (lo, hi) (slab method)."""
    d = b - a
    t0, t1 = np.zeros(len(a)), np.ones(len(a))
    for k in range(3):
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (lo[..., k] - a[:, k]) / d[:, k]
            tb = (hi[..., k] - a[:, k]) / d[:, k]
        par = np.abs(d[:, k]) < 1e-300
        inside = (a[:, k] > lo[..., k]) & (a[:, k] < hi[..., k])
        lo_t = np.where(par, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb))
        hi_t = np.where(par, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb))
        t0, t1 = np.maximum(t0, lo_t), np.minimum(t1, hi_t)
    return t0 < t1 - 1e-12


def _segment_segment_distance(
    a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray
) -> np.ndarray:
    """Distance between segments a0->a1 (N, 3) and b0->b1 (N, 3) or (3,)."""
    u, v, w = a1 - a0, b1 - b0, a0 - b0
    a = np.sum(u * u, -1)
    b = np.sum(u * v, -1)
    c = np.sum(v * v, -1)
    d = np.sum(u * w, -1)
    e = np.sum(v * w, -1)
    den = a * c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(den > 1e-12 * a * c, np.clip((b * e - c * d) / den, 0, 1), 0.0)
        t = np.where(c > 0, (b * s + e) / c, 0.0)
    t = np.clip(t, 0, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(a > 0, np.clip((b * t - d) / a, 0, 1), 0.0)
    diff = w + s[:, None] * u - t[:, None] * v
    return np.linalg.norm(diff, axis=-1)


def beam_blocked(points: np.ndarray, stations: np.ndarray, obstacles: Sequence[Obstacle]):
    """(N,) bool: the beam from points[i] to stations[i] (mm) crosses an obstacle."""
    points, stations = np.asarray(points, float), np.asarray(stations, float)
    out = np.zeros(len(points), bool)
    for ob in obstacles:
        shift = points if ob.moves_with == "tool" else np.zeros((1, 3))
        if ob.kind == "box":
            lo, hi = np.asarray(ob.lo) + shift, np.asarray(ob.hi) + shift
            lo, hi = np.broadcast_to(lo, points.shape), np.broadcast_to(hi, points.shape)
            out |= _segment_box(points, stations, lo, hi)
        else:
            p0 = np.broadcast_to(np.asarray(ob.p0) + shift, points.shape)
            p1 = np.broadcast_to(np.asarray(ob.p1) + shift, points.shape)
            out |= _segment_segment_distance(points, stations, p0, p1) < ob.radius
    return out


def aim_axes(
    points: np.ndarray,
    tool_axes: np.ndarray,
    stations: np.ndarray,
    reflector: Reflector,
    centre: np.ndarray,
) -> np.ndarray:
    """The reflector's mounting axis (N, 3) for every reading: turned with the tool
    (``tool_axes``, the tool-frame axis in the machine frame per reading) or re-aimed from
    the workspace ``centre`` at the reading's station."""
    if reflector.axis is not None:
        return np.asarray(tool_axes, float)
    d = np.asarray(stations, float) - np.asarray(centre, float)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def beam_angles_deg(
    points: np.ndarray,
    tool_axes: np.ndarray,
    stations: np.ndarray,
    reflector: Reflector,
    centre: np.ndarray,
) -> np.ndarray:
    """(N,) deg: the angle between the reflector's mounting axis (:func:`aim_axes`) and
    the beam from each reflector point (N, 3) mm to its station (N, 3) mm.  The one
    computation of the acceptance angle (violations, slack and the set-up sheet)."""
    P, S = np.asarray(points, float), np.asarray(stations, float)
    beam = S - P
    beam = beam / np.linalg.norm(beam, axis=1, keepdims=True)
    ax = aim_axes(P, tool_axes, S, reflector, centre)
    return np.degrees(np.arccos(np.clip(np.sum(beam * ax, axis=1), -1.0, 1.0)))


def _box_sdf(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Signed distance (mm) of points p (N, 3) to boxes (lo, hi) (N, 3): positive
    outside, minus the depth inside."""
    c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    q = np.abs(p - c) - h
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def segment_box_clearance(
    a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray, iterations: int = 80
) -> np.ndarray:
    """(N,) mm: the smallest signed distance of the segments a[i] -> b[i] (N, 3) to the
    boxes (lo, hi) (N, 3 or 3,): the clearance of a beam to a box obstacle, negative (the
    depth) when it crosses it.  The signed distance of a convex set is convex along a
    line, so a golden-section search over the segment finds its minimum."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    lo, hi = np.broadcast_to(lo, a.shape), np.broadcast_to(hi, a.shape)
    d = b - a
    g = (np.sqrt(5.0) - 1.0) / 2.0
    x0, x1 = np.zeros(len(a)), np.ones(len(a))
    for _ in range(iterations):
        m0, m1 = x1 - g * (x1 - x0), x0 + g * (x1 - x0)
        f0 = _box_sdf(a + m0[:, None] * d, lo, hi)
        f1 = _box_sdf(a + m1[:, None] * d, lo, hi)
        left = f0 <= f1
        x1 = np.where(left, m1, x1)
        x0 = np.where(left, x0, m0)
    t = 0.5 * (x0 + x1)
    ends = np.minimum(_box_sdf(a, lo, hi), _box_sdf(b, lo, hi))
    return np.minimum(_box_sdf(a + t[:, None] * d, lo, hi), ends)


def reading_violations(
    points: np.ndarray,
    tool_axes: np.ndarray,
    station_of: np.ndarray,
    stations: np.ndarray,
    constraints: Constraints,
    centre: np.ndarray,
) -> pd.DataFrame:
    """Every (reading, constraint) broken: points (N, 3) mm the reflector positions,
    tool_axes (N, 3) the reflector axis turned with the tool (unit, machine frame),
    station_of (N,) the station index of each reading, stations (K, 3) mm.  Columns:
    ``reading``, ``station``, ``constraint`` (region, distance, range, angle, sight),
    ``value`` (mm or deg) and ``limit``."""
    S = np.asarray(stations, float)[np.asarray(station_of, int)]
    P = np.asarray(points, float)
    rows: list[dict[str, Any]] = []

    def add(mask, kind, value, limit):
        for i in np.flatnonzero(mask):
            rows.append(
                {
                    "reading": int(i),
                    "station": int(station_of[i]),
                    "constraint": kind,
                    "value": float(value[i]),
                    "limit": float(limit),
                }
            )

    if constraints.regions:
        ok = station_feasible(np.asarray(stations, float), constraints, check_sight=False)
        add(~ok[station_of], "region", np.zeros(len(P)), 0.0)
    dist = np.linalg.norm(S - P, axis=1)
    add(dist < constraints.min_distance_mm, "distance", dist, constraints.min_distance_mm)
    add(dist > constraints.max_range_mm, "range", dist, constraints.max_range_mm)
    ref = constraints.reflector
    if ref.limited:
        ang = beam_angles_deg(P, tool_axes, S, ref, centre)
        add(ang > ref.half_angle_deg + 1e-9, "angle", ang, ref.half_angle_deg)
    if constraints.obstacles:
        add(beam_blocked(P, S, constraints.obstacles), "sight", np.ones(len(P)), 0.0)
    return pd.DataFrame(rows, columns=["reading", "station", "constraint", "value", "limit"])


def constraint_slack(
    points: np.ndarray,
    tool_axes: np.ndarray,
    station_of: np.ndarray,
    stations: np.ndarray,
    constraints: Constraints,
    centre: np.ndarray,
) -> pd.DataFrame:
    """How far the readings stay from each declared limit, worst case per kind (arguments
    as :func:`reading_violations`).  One row per limit that applies: ``constraint``
    (angle, distance, range, region, sight), ``worst`` (the value closest to the limit:
    largest beam angle to the reflector axis in deg, smallest or largest station-to-point
    distance in mm, smallest distance of a station to a face of its region in mm, smallest
    clearance of a beam to an obstacle, box or cylinder, in mm), ``limit``, ``slack`` (how much room
    is left, deg or mm; negative: broken), ``unit``, ``station`` (0-based index) and
    ``reading`` (the reading's row, -1 for a station-only limit)."""
    station_of = np.asarray(station_of, int)
    St = np.asarray(stations, float)
    S = St[station_of]
    P = np.asarray(points, float)
    rows: list[dict[str, Any]] = []

    def add(kind: str, worst: float, limit: float, slack: float, unit: str, st: int, r: int):
        rows.append(
            {
                "constraint": kind,
                "worst": float(worst),
                "limit": float(limit),
                "slack": float(slack),
                "unit": unit,
                "station": int(st),
                "reading": int(r),
            }
        )

    if len(P):
        dist = np.linalg.norm(S - P, axis=1)
        ref = constraints.reflector
        if ref.limited:
            ang = beam_angles_deg(P, tool_axes, S, ref, centre)
            i = int(np.argmax(ang))
            h = ref.half_angle_deg
            add("angle", ang[i], h, h - ang[i], "deg", station_of[i], i)
        if constraints.min_distance_mm > 0:
            i = int(np.argmin(dist))
            lim = constraints.min_distance_mm
            add("distance", dist[i], lim, dist[i] - lim, "mm", station_of[i], i)
        if np.isfinite(constraints.max_range_mm):
            i = int(np.argmax(dist))
            lim = constraints.max_range_mm
            add("range", dist[i], lim, lim - dist[i], "mm", station_of[i], i)
        if constraints.obstacles:
            clear = np.full(len(P), np.inf)
            for ob in constraints.obstacles:
                shift = P if ob.moves_with == "tool" else np.zeros((1, 3))
                if ob.kind == "box":
                    lo = np.broadcast_to(np.asarray(ob.lo) + shift, P.shape)
                    hi = np.broadcast_to(np.asarray(ob.hi) + shift, P.shape)
                    c = segment_box_clearance(P, S, lo, hi)
                else:
                    p0 = np.broadcast_to(np.asarray(ob.p0) + shift, P.shape)
                    p1 = np.broadcast_to(np.asarray(ob.p1) + shift, P.shape)
                    c = _segment_segment_distance(P, S, p0, p1) - ob.radius
                clear = np.minimum(clear, c)
            i = int(np.argmin(clear))
            add("sight", clear[i], 0.0, clear[i], "mm", station_of[i], i)
    if constraints.regions:
        depth = np.max([r.clearance(St) for r in constraints.regions], axis=0)
        k = int(np.argmin(depth))
        add("region", depth[k], 0.0, depth[k], "mm", k, -1)
    return pd.DataFrame(
        rows, columns=["constraint", "worst", "limit", "slack", "unit", "station", "reading"]
    )


def station_feasible(
    stations: np.ndarray, constraints: Constraints, *, check_sight: bool = False
) -> np.ndarray:
    """(K,) bool: the station positions (K, 3) mm lie in a region (any, when regions are
    declared) and outside every fixed obstacle."""
    s = np.atleast_2d(np.asarray(stations, float))
    ok = np.ones(len(s), bool)
    if constraints.regions:
        ok &= np.any([r.contains(s) for r in constraints.regions], axis=0)
    for ob in constraints.obstacles:
        if ob.moves_with != "frame":
            continue
        if ob.kind == "box":
            ok &= ~np.all((s > np.asarray(ob.lo)) & (s < np.asarray(ob.hi)), axis=1)
        else:
            p0 = np.broadcast_to(np.asarray(ob.p0, float), s.shape)
            p1 = np.broadcast_to(np.asarray(ob.p1, float), s.shape)
            ok &= _segment_segment_distance(s, s, p0, p1) >= ob.radius
    return ok


# ---- declarations (TOML tables / dicts: data, never code) ---------------------------------


def _is_num(a: Any) -> bool:
    return isinstance(a, (int, float, np.integer, np.floating)) and not isinstance(a, bool)


def _vec(d: Mapping[str, Any], key: str, where: str, n: int = 3) -> tuple[float, ...]:
    v = d.get(key)
    if not isinstance(v, (list, tuple, np.ndarray)) or not all(_is_num(a) for a in v):
        raise InputError(f"{where}: '{key}' must be a list of {n} numbers (mm), got {v!r}")
    out = tuple(float(a) for a in v)
    if len(out) != n or not np.all(np.isfinite(out)):
        raise InputError(f"{where}: '{key}' must be a list of {n} finite numbers (mm), got {v!r}")
    return out


def _pair(v: Any, where: str, key: str) -> tuple[Any, Any]:
    """Two corners or end points, ``[[x, y, z], [x, y, z]]`` (mm)."""
    if not isinstance(v, (list, tuple)) or len(v) != 2:
        raise InputError(f"{where}: '{key}' must be two points [[x, y, z], [x, y, z]] in mm")
    return v[0], v[1]


def _num(
    d: Mapping[str, Any],
    key: str,
    where: str,
    default: float | None = None,
    *,
    infinite: bool = False,
) -> float:
    if key not in d:
        if default is None:
            raise InputError(f"{where}: missing '{key}'")
        return default
    v = d[key]
    if not _is_num(v) or np.isnan(v) or (np.isinf(v) and not infinite):
        raise InputError(f"{where}: '{key}' must be a finite number, got {v!r}")
    return float(v)


def _table(v: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(v, Mapping):
        raise InputError(f"{where}: expected a table of keys, got {v!r}")
    return v


def _keys(d: Mapping[str, Any], known: set[str], where: str) -> None:
    unknown = sorted(map(str, set(d) - known))
    if unknown:
        raise InputError(f"{where}: unknown key(s) {', '.join(unknown)}; expected {sorted(known)}")


def _tables(doc: Mapping[str, Any], key: str, where: str) -> list[Mapping[str, Any]]:
    """``[[where.key]]``: an array of tables (a single table is taken as one)."""
    v = doc.get(key, [])
    if isinstance(v, Mapping):
        v = [v]
    if not isinstance(v, list):
        raise InputError(f"{where}: '{key}' must be an array of tables [[{key}]], got {v!r}")
    return [_table(t, f"{where}.{key}[{k}]") for k, t in enumerate(v)]


def _name(d: Mapping[str, Any], where: str, default: str) -> str:
    v = d.get("name", default)
    if not isinstance(v, str):
        raise InputError(f"{where}: 'name' must be a string, got {v!r}")
    return v


_REGION_KEYS = {"box": {"name", "box"}, "polygon": {"name", "polygon", "low", "high", "up"}}
_OBSTACLE_KEYS = {
    "box": {"name", "box", "moves_with"},
    "cylinder": {"name", "cylinder", "radius", "moves_with"},
}


def constraints_from_dict(doc: Mapping[str, Any], where: str = "constraints") -> Constraints:
    """Constraints from a mapping (a TOML table)::

    min_distance_mm = 150
    max_range_mm = 10000
    [reflector]
    half_angle_deg = 60        # acceptance about the mounting axis, 0 < angle <= 90;
    #                            omit it for a reflector without a limit
    axis = [0, 0, -1]          # in the tool frame; omit: re-aimed at each station
    [[region]]
    name = "left"
    box = [[-500, -200, -700], [-100, 800, -300]]   # or: polygon = [[x, y], ...],
    #                                                 low = .., high = .., up = "z"
    [[obstacle]]
    name = "spindle head"
    cylinder = [[0, 0, 50], [0, 0, 600]]           # axis end points
    radius = 120
    moves_with = "tool"
    [[obstacle]]
    box = [[..], [..]]

    Every key is checked (unknown keys, types, ranges, inverted boxes) and an error names
    ``where`` (the file and table) and the key: raises :class:`InputError`.
    """
    doc = _table(doc, where)
    _keys(doc, {"min_distance_mm", "max_range_mm", "reflector", "region", "obstacle"}, where)
    regions = []
    for k, r in enumerate(_tables(doc, "region", where)):
        w = f"{where}.region[{k}]"
        name = _name(r, w, f"region{k + 1}")
        kind = next((kd for kd in ("box", "polygon") if kd in r), None)
        if kind is None or ("box" in r and "polygon" in r):
            raise InputError(f"{w}: expected either 'box' or 'polygon'")
        _keys(r, _REGION_KEYS[kind], w)
        if kind == "box":
            lo, hi = _pair(r["box"], w, "box")
            lo, hi = _vec({"box": lo}, "box", w), _vec({"box": hi}, "box", w)
            bad = [f"{c}: {a:g} > {b:g}" for c, a, b in zip("xyz", lo, hi, strict=True) if a > b]
            if bad:
                raise InputError(
                    f"{w}: 'box' must be [[x_lo, y_lo, z_lo], [x_hi, y_hi, z_hi]] (mm) with "
                    f"lo <= hi, got {'; '.join(bad)}"
                )
            v = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
            low, high, up = lo[2], hi[2], "z"
        else:
            poly = r["polygon"]
            if not (
                isinstance(poly, list)
                and all(isinstance(v, list) and len(v) == 2 for v in poly)
                and all(_is_num(a) and np.isfinite(a) for v in poly for a in v)
            ):
                raise InputError(
                    f"{w}: 'polygon' must be a list of [x, y] pairs of finite numbers (mm)"
                )
            up = r.get("up", "z")
            if up not in ("x", "y", "z"):
                raise InputError(f'{w}: \'up\' must be "x", "y" or "z", got {up!r}')
            low, high = _num(r, "low", w), _num(r, "high", w)
            if low > high:
                raise InputError(f"{w}: 'low' {low:g} > 'high' {high:g} (mm)")
            v = np.asarray(poly, float)
        try:
            regions.append(Region(v, low, high, up, name))
        except InputError as exc:  # the region's own checks (convex, ...), with the place
            raise InputError(f"{w}: {exc}") from None
    obstacles = []
    for k, o in enumerate(_tables(doc, "obstacle", where)):
        w = f"{where}.obstacle[{k}]"
        name = _name(o, w, f"obstacle{k + 1}")
        mw = o.get("moves_with", "frame")
        if mw not in ("frame", "tool"):
            raise InputError(f'{w}: \'moves_with\' must be "frame" or "tool", got {mw!r}')
        kind = next((kd for kd in ("box", "cylinder") if kd in o), None)
        if kind is None or ("box" in o and "cylinder" in o):
            raise InputError(f"{w}: expected either 'box' or 'cylinder'")
        _keys(o, _OBSTACLE_KEYS[kind], w)
        a, b = _pair(o[kind], w, kind)
        a, b = _vec({kind: a}, kind, w), _vec({kind: b}, kind, w)
        if kind == "box":
            bad = [f"{c}: {x:g} > {y:g}" for c, x, y in zip("xyz", a, b, strict=True) if x > y]
            if bad:
                raise InputError(
                    f"{w}: 'box' must be [[x_lo, y_lo, z_lo], [x_hi, y_hi, z_hi]] (mm) with "
                    f"lo <= hi, got {'; '.join(bad)}"
                )
            ob = Obstacle("box", lo=a, hi=b, moves_with=mw, name=name)  # type: ignore[arg-type]
        else:
            radius = _num(o, "radius", w)
            if not radius > 0:
                raise InputError(f"{w}: 'radius' must be > 0 mm, got {radius:g}")
            ob = Obstacle("cylinder", p0=a, p1=b, radius=radius, moves_with=mw, name=name)  # type: ignore[arg-type]
        obstacles.append(ob)
    wr = f"{where}.reflector"
    rd = _table(doc.get("reflector", {}), wr)
    _keys(rd, {"half_angle_deg", "axis"}, wr)
    axis = None
    if "axis" in rd:
        a = np.asarray(_vec(rd, "axis", wr))
        if np.linalg.norm(a) == 0:
            raise InputError(f"{wr}: 'axis' must not be zero")
        axis = tuple(float(v) for v in a / np.linalg.norm(a))
    half = 180.0  # no acceptance limit
    if "half_angle_deg" in rd:
        half = _num(rd, "half_angle_deg", wr)
        if not 0 < half <= 90:
            raise InputError(
                f"{wr}: 'half_angle_deg' must be > 0 and <= 90 deg (the acceptance half-angle "
                f"about the reflector's axis), got {half:g}; omit it for a reflector without "
                "a limit"
            )
    ref = Reflector(half, axis)  # type: ignore[arg-type]
    min_d = _num(doc, "min_distance_mm", where, 0.0)
    if min_d < 0:
        raise InputError(f"{where}: 'min_distance_mm' must be >= 0, got {min_d:g}")
    max_r = _num(doc, "max_range_mm", where, float("inf"), infinite=True)
    if not max_r > min_d:
        raise InputError(
            f"{where}: 'max_range_mm' ({max_r:g}) must be larger than 'min_distance_mm' ({min_d:g})"
        )
    return Constraints(tuple(regions), tuple(obstacles), ref, min_d, max_r)


def stations_ok(
    candidates: np.ndarray,
    points: np.ndarray,
    tool_axes: np.ndarray,
    constraints: Constraints,
    centre: np.ndarray,
) -> np.ndarray:
    """(M,) bool: each candidate station position (M, 3) mm may read every point (n, 3)
    (the reflector axis turned with the tool ``tool_axes`` (n, 3)): it lies in a region,
    outside fixed obstacles, and every beam keeps the distance, range, acceptance-angle and
    line-of-sight constraints.  Stations are independent of each other, so a plan is
    feasible exactly when each of its stations is."""
    C = np.atleast_2d(np.asarray(candidates, float))
    P = np.asarray(points, float)
    ok = station_feasible(C, constraints)
    if not len(P):
        return ok
    D = C[:, None, :] - P[None, :, :]  # (M, n, 3) beam point -> station
    dist = np.linalg.norm(D, axis=2)
    ok &= np.all(dist >= constraints.min_distance_mm, axis=1)
    ok &= np.all(dist <= constraints.max_range_mm, axis=1)
    ref = constraints.reflector
    if ref.limited:
        if ref.axis is not None:
            ax = np.broadcast_to(np.asarray(tool_axes, float)[None], D.shape)
        else:
            a = C - np.asarray(centre, float)
            ax = np.broadcast_to(
                (a / np.linalg.norm(a, axis=1, keepdims=True))[:, None, :], D.shape
            )
        cosang = np.sum(D * ax, axis=2) / dist
        ok &= np.all(cosang >= np.cos(np.radians(ref.half_angle_deg)) - 1e-12, axis=1)
    if constraints.obstacles:
        for m in np.flatnonzero(ok):
            if beam_blocked(P, np.broadcast_to(C[m], P.shape), constraints.obstacles).any():
                ok[m] = False
    return ok
