"""Paper 001's simultaneous three-laser telescopic instrument (HPTI) as an observation model.

Station = laser.  Per laser its origin ``x, y, z`` in the instrument frame (mm) and its
length offset (mm); global ``instrument_T_machine`` (tx, ty, tz mm; rx, ry, rz rad, exact
rotation R = Rz Ry Rx):  ``reading = ||R P + t - Q|| - offset``.  The instrument's own frame
convention (ICRS, paper sec. 3) holds laser1.x/y/z, laser2.y/z and laser3.z at 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from volcal.measurement.instruments.base import Instrument

FRAME_NAMES = (
    "frame_tx_mm",
    "frame_ty_mm",
    "frame_tz_mm",
    "frame_rx_rad",
    "frame_ry_rad",
    "frame_rz_rad",
)


def rotation_sx(r):
    """R = Rz(rz) Ry(ry) Rx(rx) for CasADi symbols r = (rx, ry, rz) rad."""
    cx, sx, cy, sy, cz, sz = (
        ca.cos(r[0]),
        ca.sin(r[0]),
        ca.cos(r[1]),
        ca.sin(r[1]),
        ca.cos(r[2]),
        ca.sin(r[2]),
    )
    Rx = ca.blockcat([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = ca.blockcat([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = ca.blockcat([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return ca.mtimes([Rz, Ry, Rx])


@dataclass(frozen=True, repr=False)
class MultiLaserInstrument(Instrument):
    """The HPTI: three lasers read every point simultaneously (see the module docstring)."""

    name: str = "multilaser"
    station_param_names: tuple[str, ...] = ("x_mm", "y_mm", "z_mm", "offset_mm")
    global_param_names: tuple[str, ...] = FRAME_NAMES

    @staticmethod
    def to_instrument(point, glob):
        """Machine point (3,) -> instrument frame (CasADi)."""
        return ca.mtimes(rotation_sx(glob[3:6]), point) + glob[0:3]

    def reading(self, point, station, glob):
        diff = self.to_instrument(point, glob) - station[0:3]
        return ca.sqrt(ca.sumsqr(diff)) - station[3]

    @staticmethod
    def icrs_fixed() -> dict[str, tuple[str, ...]]:
        """Station parameters the ICRS convention fixes at 0 (per laser)."""
        return {"laser1": ("x_mm", "y_mm", "z_mm"), "laser2": ("y_mm", "z_mm"), "laser3": ("z_mm",)}

    def held_station_params(self, station_id: str) -> tuple[str, ...]:
        return self.icrs_fixed().get(station_id, ())

    @staticmethod
    def _frame(Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) with the ICRS of three laser origins Q (machine frame, (>= 3, 3)):
        laser 1 at the origin, laser 2 on x, laser 3 in the xy plane; P_I = R P_M + t."""
        ex = Q[1] - Q[0]
        ex /= np.linalg.norm(ex)
        ez = np.cross(ex, Q[2] - Q[0])
        ez /= np.linalg.norm(ez)
        R = np.vstack([ex, np.cross(ez, ex), ez])
        return R, -R @ Q[0]

    def start(self, station_ids, station_index, points, readings):
        """Laser origins in the ICRS from a tracker-style calibration of each laser on the
        nominal points, expressed in the frame the first three origins span (laser 1 at
        the origin, laser 2 on x, laser 3 in the xy plane), offsets from that fit; and the
        machine-to-ICRS frame motion (tx, ty, tz mm; rx, ry, rz rad, R = Rz Ry Rx) that
        goes with them."""
        from volcal.measurement.instruments.tracker import SequentialMultilateration

        est = SequentialMultilateration().start_values(station_ids, station_index, points, readings)
        if len(est) < 3:
            return est, np.zeros(6)
        R, t = self._frame(est[:, :3])
        est[:, :3] = est[:, :3] @ R.T + t
        # R = Rz(rz) Ry(ry) Rx(rx): ry = -asin(R[2, 0]), rx = atan2(R[2, 1], R[2, 2]),
        # rz = atan2(R[1, 0], R[0, 0])
        ry = -np.arcsin(np.clip(R[2, 0], -1.0, 1.0))
        rx = np.arctan2(R[2, 1], R[2, 2])
        rz = np.arctan2(R[1, 0], R[0, 0])
        return est, np.array([t[0], t[1], t[2], rx, ry, rz])

    def start_values(self, station_ids, station_index, points, readings) -> np.ndarray:
        """The laser origins of :meth:`start` (ICRS, mm) and their offsets (mm)."""
        return self.start(station_ids, station_index, points, readings)[0]
