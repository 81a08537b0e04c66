"""A laser interferometer: the displacement of the tool relative to the table along a beam.

Station = set-up (one nominal line, e.g. the X axis at fixed Y, Z).  Per set-up the unit
direction of the nominal line (``ux, uy, uz``; from the set-up's nominal points, held), two
misalignment angles of the beam against that line (``misalign_a_rad`` towards ``e1``,
``misalign_b_rad`` towards ``e2``, the two directions normal to it; held at their start
value, 0 unless a stations table gives them: at the nominal line the reading depends on
them at second order only, the cosine error, so the data cannot determine them) and the
dead-path offset (``offset_mm``: the reading at the workpiece origin, which absorbs where
the reading was zeroed and the dead path):

    reading = v . point - offset,   v = cos b (cos a u + sin a e1) + sin b e2  (mm)

Optics on the table or on the spindle: both read the displacement of tool and table
relative to each other along the beam; the spindle-side element (reflector or
interferometer optics) sits at the tool offset, and the sign of the beam direction is taken
from the readings (a reading that decreases along the travel flips u).

Tables: a plain CSV (:meth:`LaserInterferometer.read_table`: ``setup``, the machine's axis
columns, optional ``tool_x_mm``.., ``displacement_mm`` or ``displacement_um``, optional
``sigma_mm`` / ``sigma_um`` and ``point``), or the ISO 230-2 data files ``volcal
iso230-2`` reads (:meth:`LaserInterferometer.read_iso230_2`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np
import pandas as pd

from volcal.base.exceptions import InputError, SolverError
from volcal.measurement.instruments.base import Instrument


def beam_direction(u, a, b):
    """The beam direction (CasADi): ``u`` (3,) turned by the angle a (rad) towards e1, then
    by b towards e2 (a unit vector).  e1 = h x u / |h x u| with h the machine z axis (the x axis
    for a line within 26 deg of z), e2 = u x e1: for a line along x, e1 = y, e2 = z."""
    u = u / ca.norm_2(u)
    h = ca.if_else(ca.fabs(u[2]) < 0.9, ca.DM([0.0, 0.0, 1.0]), ca.DM([1.0, 0.0, 0.0]))
    e1 = ca.cross(h, u)
    e1 = e1 / ca.norm_2(e1)
    e2 = ca.cross(u, e1)
    return ca.cos(b) * (ca.cos(a) * u + ca.sin(a) * e1) + ca.sin(b) * e2


@dataclass(frozen=True, repr=False)
class LaserInterferometer(Instrument):
    """A laser interferometer along nominal lines (see the module docstring)."""

    name: str = "interferometer"
    station_param_names: tuple[str, ...] = (
        "ux",
        "uy",
        "uz",
        "misalign_a_rad",
        "misalign_b_rad",
        "offset_mm",
    )
    global_param_names: tuple[str, ...] = ()
    positive_readings: bool = False  # displacements are signed

    def reading(self, point: ca.SX, station: ca.SX, glob: ca.SX) -> ca.SX:
        return ca.dot(beam_direction(station[:3], station[3], station[4]), point) - station[5]

    def held_station_params(self, station_id: str) -> tuple[str, ...]:
        return ("ux", "uy", "uz", "misalign_a_rad", "misalign_b_rad")

    def start_values(
        self,
        station_ids: list[str],
        station_index: np.ndarray,
        points: np.ndarray,
        readings: np.ndarray,
    ) -> np.ndarray:
        """Per set-up: the principal direction of its nominal points (signed so that the
        readings grow along it), no misalignment, and the offset matching the readings."""
        out = np.zeros((len(station_ids), 6))
        idx = np.asarray(station_index, int)
        for k, sid in enumerate(station_ids):
            P, m = points[idx == k], readings[idx == k]
            c = P - P.mean(axis=0)
            s = np.linalg.svd(c, full_matrices=False)[1:] if len(P) > 1 else None
            if s is None or s[0][0] < 1e-6 or s[0][1:].max(initial=0.0) > 1e-3 * s[0][0]:
                raise SolverError(
                    f"interferometer set-up {sid}: its nominal points do not lie on one line "
                    "(an interferometer reads along a line between at least two positions)"
                )
            u = s[1][0]
            if np.dot(c @ u, m - m.mean()) < 0:
                u = -u
            out[k, :3] = u
            out[k, 5] = float(np.mean(P @ u - m))
        return out

    def start_note(self) -> str:
        return (
            "interferometer start values: line directions from the nominal points, no "
            "misalignment, offsets from the readings"
        )

    # ---- tables ---------------------------------------------------------------------
    def read_table(self, source: str | Path | pd.DataFrame, spec) -> pd.DataFrame:
        """The plain interferometer CSV as volcal's measurement table (station = set-up,
        length_mm = displacement in mm).  Columns: ``setup`` (id), one column per machine
        axis (``X_mm``, ``C_deg``, ...), optional ``tool_x_mm``, ``tool_y_mm``,
        ``tool_z_mm``, ``displacement_mm`` or ``displacement_um``, optional ``sigma_mm`` or
        ``sigma_um``, optional ``point`` (id; default: the row number).  The ISO 230-2
        format (``axis``, ``target_mm`` or ``target_deg``, ``cycle``, ``direction``, ...) is
        recognised and read by :meth:`read_iso230_2`."""
        from volcal.measurement.iso230_2_files import is_iso230_2_table
        from volcal.measurement.tables import mm_or_um, mm_or_um_columns, read_columns

        if is_iso230_2_table(source):
            return self.read_iso230_2(source, spec)
        axes = [(f"{a.name}_{'deg' if a.is_rotary else 'mm'}", True, "float") for a in spec.axes]
        cols = [("setup", True, "id"), ("point", False, "id"), *axes]
        cols += [(f"tool_{c}_mm", False, "float") for c in "xyz"]
        cols += mm_or_um_columns("displacement") + mm_or_um_columns("sigma", "optfloat")
        v, rows, label = read_columns(source, cols, what="interferometer table")
        out: dict[str, np.ndarray] = {"station": v["setup"]}
        out["point"] = v.get("point", np.array([f"r{r}" for r in rows], dtype=object))
        for n, _, _ in axes:
            out[n] = v[n]
        for c in "xyz":
            out[f"tool_{c}_mm"] = v.get(f"tool_{c}_mm", np.zeros(len(rows)))
        out["length_mm"] = mm_or_um(v, "displacement", label, required=True)
        sig = mm_or_um(v, "sigma", label, required=False)
        if sig is not None:
            out["sigma_mm"] = sig
        return pd.DataFrame(out)

    def read_iso230_2(self, source: str | Path | pd.DataFrame, spec) -> pd.DataFrame:
        """An ISO 230-2 data file (the format ``volcal iso230-2`` reads, read and validated by
        the same reader, :func:`volcal.measurement.iso230_2_files.read_iso230_2_file`: a file
        is accepted or refused by both alike) as interferometer readings: one set-up per
        axis (``<axis>-line``), every row a reading of the actual position (target +
        deviation, mm).  The other axes stand where the optional columns ``Y_mm``, ...
        (the model's axis names) say, else at their reference positions; the reflector at
        the optional ``tool_x_mm``, ``tool_y_mm``, ``tool_z_mm`` (default 0); optional
        ``sigma_um`` or ``sigma_mm``.  Linear axes of the model only."""
        from volcal.measurement.iso230_2_files import LINEAR, read_iso230_2_file
        from volcal.measurement.tables import mm_or_um

        f = read_iso230_2_file(source)
        label = f.source
        linear = {a.name: a for a in spec.axes if not a.is_rotary}
        if f.units is not LINEAR:
            raise InputError(
                f"an interferometer reads a linear axis of the model ({', '.join(linear)}); "
                "this file gives target_deg (a rotary axis)",
                source=label,
                row=1,
                column=f.columns["target_deg"],
            )
        n = len(f.row)
        out: dict[str, np.ndarray] = {}
        out["station"] = np.empty(n, dtype=object)
        out["point"] = np.array(
            [
                f"{a}-c{c}{'+' if d == 'up' else '-'}-r{r}"
                for a, c, d, r in zip(f.axis, f.cycle, f.direction, f.row)
            ],
            dtype=object,
        )
        for a in spec.axes:
            unit = "deg" if a.is_rotary else "mm"
            pos = f.number_column(f"{a.name}_{unit}", f"the position of axis {a.name} in {unit}")
            out[f"{a.name}_{unit}"] = np.full(n, float(a.reference)) if pos is None else pos
        for r in range(n):
            name = str(f.axis[r]).upper()
            if name not in linear:
                raise InputError(
                    f"axis {f.axis[r]!r}: an interferometer reads a linear axis of the "
                    f"model ({', '.join(linear)})",
                    source=label,
                    row=int(f.row[r]),
                    column=f.columns["axis"],
                )
            out["station"][r] = f"{name}-line"
            out[f"{name}_mm"][r] = f.target[r]
        for c in "xyz":
            tool = f.number_column(f"tool_{c}_mm", "the tool offset in mm")
            out[f"tool_{c}_mm"] = np.zeros(n) if tool is None else tool
        out["length_mm"] = f.target + f.deviation  # the actual position, mm
        sigma = {
            k: x
            for k in ("sigma_mm", "sigma_um")
            if (x := f.number_column(k, f"a standard deviation in {k[6:]}", optional=True))
            is not None
        }
        sig = mm_or_um(sigma, "sigma", label, required=False)
        if sig is not None:
            out["sigma_mm"] = sig
        return pd.DataFrame(out)
