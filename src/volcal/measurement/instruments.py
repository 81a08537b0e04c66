"""Observation models: what an instrument reads for a given actual tool point.

An instrument has parameters per station (or per laser) and global parameters, and one
CasADi SX expression for a single reading.  The identification replicates that expression
over all readings with ``Function.map``; nothing here knows about the data.

* :class:`SequentialMultilateration`: one laser tracker or LaserTRACER set up at several
  stations in turn.  Per station its position (x, y, z) in the workpiece frame and a dead
  length d (paper 002 eq. 5-6; paper 000's L_k): reading = ||P - Q|| - d.
* :class:`MultiLaserInstrument`: paper 001's simultaneous telescopic instrument; see
  :mod:`volcal.analysis.multilaser`.
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca


class InstrumentBase:
    """What every observation model offers the NLP: its parameter names (per station or
    laser, and global), their units, and ``reading(point, station, glob)``."""

    station_param_names: tuple[str, ...] = ()
    global_param_names: tuple[str, ...] = ()

    @property
    def global_param_units(self) -> tuple[str, ...]:
        return tuple("rad" if n.endswith("_rad") else "mm" for n in self.global_param_names)

    @property
    def n_station_params(self) -> int:
        return len(self.station_param_names)

    @property
    def n_global_params(self) -> int:
        return len(self.global_param_names)


@dataclass(frozen=True)
class SequentialMultilateration(InstrumentBase):
    """Sequential multilateration with one tracker: per station ``x, y, z`` (mm) and a dead
    length (mm); no global parameters."""

    name: str = "sequential"
    station_param_names: tuple[str, ...] = ("x_mm", "y_mm", "z_mm", "dead_length_mm")
    # A rigid motion of the whole station set (first order): redundant with the stations
    # while they are free (the identification then fixes it), but it is what lets a
    # two-phase or points-only solve absorb the frame mismatch once stations are fixed.
    global_param_names: tuple[str, ...] = ("frame_tx_mm", "frame_ty_mm", "frame_tz_mm",
                                           "frame_rx_rad", "frame_ry_rad", "frame_rz_rad")

    def reading(self, point: ca.SX, station: ca.SX, glob: ca.SX) -> ca.SX:
        """Model of one reading (mm) for the actual tool point ``point`` (3, mm)."""
        q = station[:3] + glob[:3] + ca.cross(glob[3:6], station[:3])
        diff = point - q
        return ca.sqrt(ca.sumsqr(diff)) - station[3]



Instrument = SequentialMultilateration
