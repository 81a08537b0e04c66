"""A telescoping ballbar (ISO 230-4): the radius deviation of a circle.

Station = set-up (one circle).  Per set-up the centre of the table-side ball (``x_mm,
y_mm, z_mm`` in the workpiece frame) and the radius the deviations are read against
(``radius_mm``: the nominal length of the bar, free, so a calibration error of the bar is
absorbed):

    reading = |point - centre| - radius  (mm)

The reading depends on the centre's coordinate normal to the circle's plane at second
order only, so that coordinate is held at its start value (:meth:`Ballbar.held_from_points`).

Table (:meth:`Ballbar.read_table`): a CSV of ``setup`` (id), ``plane`` (the two axes the
circle is run on, e.g. ``XY``; the angle turns from the first towards the second),
``centre_<AXIS>_mm`` / ``_deg`` for every machine axis (the axis positions at the circle's
centre), ``radius_mm`` (nominal radius), ``angle_deg``, ``deviation_um`` or
``deviation_mm``, optional ``tool_x_mm``.., ``sigma_um`` / ``sigma_mm`` and ``point``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np
import pandas as pd

from volcal.base.exceptions import InputError, SolverError
from volcal.measurement.instruments.base import Instrument


@dataclass(frozen=True, repr=False)
class Ballbar(Instrument):
    """A ballbar run on circles (see the module docstring)."""

    name: str = "ballbar"
    station_param_names: tuple[str, ...] = ("x_mm", "y_mm", "z_mm", "radius_mm")
    global_param_names: tuple[str, ...] = ()
    positive_readings: bool = False  # deviations are signed

    def reading(self, point: ca.SX, station: ca.SX, glob: ca.SX) -> ca.SX:
        return ca.norm_2(point - station[:3]) - station[3]

    @staticmethod
    def _plane(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(mean point, two in-plane unit vectors (2, 3), unit normal) of points (n, 3)."""
        c = P.mean(axis=0)
        vt = np.linalg.svd(P - c, full_matrices=False)[2]
        return c, vt[:2], vt[2]

    def start_values(
        self,
        station_ids: list[str],
        station_index: np.ndarray,
        points: np.ndarray,
        readings: np.ndarray,
    ) -> np.ndarray:
        """Per set-up: the centre of the least-squares circle through its nominal points
        (Kasa's algebraic fit in their plane) and the radius matching the readings."""
        out = np.zeros((len(station_ids), 4))
        idx = np.asarray(station_index, int)
        for k, sid in enumerate(station_ids):
            P, m = points[idx == k], readings[idx == k]
            if len(P) < 3:
                raise SolverError(f"ballbar set-up {sid}: a circle needs at least 3 readings")
            c0, E, _ = self._plane(P)
            uv = (P - c0) @ E.T
            A = np.column_stack([2 * uv, np.ones(len(uv))])
            sol, *_ = np.linalg.lstsq(A, (uv**2).sum(axis=1), rcond=None)
            centre = c0 + sol[:2] @ E
            # the reading at radius 0 is each point's distance from the centre
            rad, _ = self.evaluate(P, np.tile(np.r_[centre, 0.0], (len(P), 1)))
            if not np.all(np.isfinite(rad)) or rad.min() < 1e-3:
                raise SolverError(f"ballbar set-up {sid}: its nominal points are not on a circle")
            out[k, :3] = centre
            out[k, 3] = float(np.mean(rad - m))
        return out

    def held_from_points(
        self, station_ids: list[str], station_index: np.ndarray, points: np.ndarray
    ) -> dict[str, tuple[str, ...]]:
        """Per set-up, the centre coordinate closest to the normal of its circle's plane."""
        idx = np.asarray(station_index, int)
        out: dict[str, tuple[str, ...]] = {}
        for k, sid in enumerate(station_ids):
            n = self._plane(points[idx == k])[2]
            out[str(sid)] = (("x_mm", "y_mm", "z_mm")[int(np.argmax(np.abs(n)))],)
        return out

    def start_note(self) -> str:
        return "ballbar start values: circle centres and radii from the nominal points"

    # ---- tables ---------------------------------------------------------------------
    def read_table(self, source: str | Path | pd.DataFrame, spec) -> pd.DataFrame:
        """The ballbar CSV (module docstring) as volcal's measurement table: the axis
        positions of every reading on its circle, length_mm = the deviation in mm."""
        from volcal.measurement.tables import mm_or_um, mm_or_um_columns, read_columns

        units = {a.name: ("deg" if a.is_rotary else "mm") for a in spec.axes}
        centre = [(f"centre_{a}_{u}", True, "float") for a, u in units.items()]
        cols = [("setup", True, "id"), ("point", False, "id"), ("plane", True, "id"), *centre]
        cols += [("radius_mm", True, "float"), ("angle_deg", True, "float")]
        cols += [(f"tool_{c}_mm", False, "float") for c in "xyz"]
        cols += mm_or_um_columns("deviation") + mm_or_um_columns("sigma", "optfloat")
        v, rows, label = read_columns(source, cols, what="ballbar table")
        n = len(rows)
        linear = [a.name for a in spec.axes if not a.is_rotary]
        q = {a: v[f"centre_{a}_{u}"].copy() for a, u in units.items()}
        ang = np.deg2rad(v["angle_deg"])
        for r in range(n):
            plane = str(v["plane"][r]).strip().upper()
            pair = _split_plane(plane, linear)
            if pair is None:
                raise InputError(
                    f"expected the plane as two linear axes of the model (e.g. "
                    f"{''.join(linear[:2])}), got {plane!r}",
                    source=label,
                    row=int(rows[r]),
                    column="plane",
                )
            if not v["radius_mm"][r] > 0:
                raise InputError(
                    f"expected a positive radius in mm, got {v['radius_mm'][r]:g}",
                    source=label,
                    row=int(rows[r]),
                    column="radius_mm",
                )
            a1, a2 = pair
            q[a1][r] += v["radius_mm"][r] * np.cos(ang[r])
            q[a2][r] += v["radius_mm"][r] * np.sin(ang[r])
        out: dict[str, np.ndarray] = {"station": v["setup"]}
        out["point"] = v.get("point", np.array([f"r{r}" for r in rows], dtype=object))
        for a, u in units.items():
            out[f"{a}_{u}"] = q[a]
        for c in "xyz":
            out[f"tool_{c}_mm"] = v.get(f"tool_{c}_mm", np.zeros(n))
        out["length_mm"] = mm_or_um(v, "deviation", label, required=True)
        sig = mm_or_um(v, "sigma", label, required=False)
        if sig is not None:
            out["sigma_mm"] = sig
        return pd.DataFrame(out)


def _split_plane(plane: str, linear: list[str]) -> tuple[str, str] | None:
    """``"XY"`` -> ("X", "Y") for axis names of any length (None if not two distinct
    linear axes)."""
    for k in range(1, len(plane)):
        a, b = plane[:k], plane[k:]
        if a in linear and b in linear and a != b:
            return a, b
    return None
