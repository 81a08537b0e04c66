"""Sequential multilateration: one laser tracker or LaserTRACER set up at several stations in
turn (paper 002 eq. 5-6; paper 000's L_k).

Per station its position (x, y, z) in the workpiece frame and a dead length d (mm):
``reading = ||P - Q|| - d``.  Globally a small rigid motion of the whole station set (first
order): redundant with the stations while they are free (the identification then holds
it), but it lets a two-phase or points-only solve absorb the frame mismatch once the
stations are fixed.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from volcal.base.exceptions import SolverError
from volcal.measurement.instruments.base import Instrument


@dataclass(frozen=True, repr=False)
class SequentialMultilateration(Instrument):
    """One tracker at several stations: per station ``x, y, z`` and a dead length (mm)."""

    name: str = "tracker"
    station_param_names: tuple[str, ...] = ("x_mm", "y_mm", "z_mm", "dead_length_mm")
    global_param_names: tuple[str, ...] = (
        "frame_tx_mm",
        "frame_ty_mm",
        "frame_tz_mm",
        "frame_rx_rad",
        "frame_ry_rad",
        "frame_rz_rad",
    )

    def reading(self, point: ca.SX, station: ca.SX, glob: ca.SX) -> ca.SX:
        q = station[:3] + glob[:3] + ca.cross(glob[3:6], station[:3])
        return ca.sqrt(ca.sumsqr(point - q)) - station[3]

    def start_values(
        self,
        station_ids: list[str],
        station_index: np.ndarray,
        points: np.ndarray,
        readings: np.ndarray,
    ) -> np.ndarray:
        """Paper 002's linear solution refined by the sqrt residual (paper 000 Case A)."""
        from volcal.measurement.multilateration import calibrate_stations

        ids = np.asarray(station_ids, dtype=object)[np.asarray(station_index, int)]
        cal = calibrate_stations(ids, points, readings, method="sqrt")
        est = np.full((len(station_ids), 4), np.nan)
        for sid, pos, d, ok, st in zip(
            cal.stations, cal.positions, cal.dead_lengths, cal.converged, cal.status
        ):
            if not ok:
                raise SolverError(
                    f"could not locate station {sid} from the nominal points", status=str(st)
                )
            k = list(station_ids).index(str(sid))
            est[k, :3], est[k, 3] = pos, d
        return est

    def start_note(self) -> str:
        return (
            "station start values: paper 002 linear solution refined by the sqrt "
            "residual (paper 000 Case A) on nominal points"
        )
