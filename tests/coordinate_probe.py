"""A new instrument in one file, to show that adding one touches no identification code: a
probe (or a CMM-like coordinate sensor) that reads one coordinate of the tool point per
reading.

Station = measuring direction.  Per station a unit direction (ux, uy, uz; dimensionless,
known, held by the instrument's convention) and a zero offset (mm):
``reading = u . point - offset``.  Three stations "X", "Y", "Z" read the three coordinates
of every point.
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from volcal.measurement.instruments import Instrument, register

AXES = {"X": (1.0, 0.0, 0.0), "Y": (0.0, 1.0, 0.0), "Z": (0.0, 0.0, 1.0)}


@register
@dataclass(frozen=True, repr=False)
class CoordinateProbe(Instrument):
    name: str = "coordinate-probe"
    station_param_names: tuple[str, ...] = ("ux", "uy", "uz", "offset_mm")
    global_param_names: tuple[str, ...] = ()
    positive_readings: bool = False  # coordinates are signed

    def reading(self, point, station, glob):
        return ca.dot(station[:3], point) - station[3]

    def held_station_params(self, station_id):
        return ("ux", "uy", "uz")

    def start_values(self, station_ids, station_index, points, readings):
        out = np.zeros((len(station_ids), 4))
        for k, sid in enumerate(station_ids):
            u = np.array(AXES[str(sid)[-1].upper()])
            sel = np.asarray(station_index) == k
            out[k, :3] = u
            out[k, 3] = float(np.mean(points[sel] @ u - readings[sel]))
        return out
