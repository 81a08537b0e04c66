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
        format (``axis, target_mm, cycle, direction, deviation_um``) is recognised and read
        by :meth:`read_iso230_2`."""
        from volcal.measurement.tables import read_columns

        if _is_iso230_2(source):
            return self.read_iso230_2(source, spec)
        axes = [(f"{a.name}_{'deg' if a.is_rotary else 'mm'}", True, "float") for a in spec.axes]
        cols = [("setup", True, "id"), ("point", False, "id"), *axes]
        cols += [(f"tool_{c}_mm", False, "float") for c in "xyz"]
        cols += [
            ("displacement_mm", False, "float"),
            ("displacement_um", False, "float"),
            ("sigma_mm", False, "optfloat"),
            ("sigma_um", False, "optfloat"),
        ]
        v, rows, label = read_columns(source, cols, what="interferometer table")
        out = {"station": v["setup"], "point": v.get("point", np.array([f"r{r}" for r in rows]))}
        for n, _, _ in axes:
            out[n] = v[n]
        for c in "xyz":
            out[f"tool_{c}_mm"] = v.get(f"tool_{c}_mm", np.zeros(len(rows)))
        out["length_mm"] = _one_of(v, "displacement", label, required=True)
        sig = _one_of(v, "sigma", label, required=False)
        if sig is not None:
            out["sigma_mm"] = sig
        return pd.DataFrame(out)

    def read_iso230_2(
        self,
        source: str | Path | pd.DataFrame,
        spec,
        *,
        line: dict[str, float] | None = None,
        tool: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> pd.DataFrame:
        """An ISO 230-2 data file (:func:`volcal.iso230_2.data.load_readings`) as
        interferometer readings: one set-up per axis, every (target, cycle, direction)
        a reading of the actual position target + deviation (mm).  The other axes stand
        at ``line`` ({axis: position, mm or deg}), else at their reference positions;
        ``tool``: the tool offset of the reflector (mm).  Linear axes only."""
        from volcal.iso230_2.data import load_readings

        readings = load_readings(source)
        line = dict(line or {})
        unknown = [a for a in line if a not in spec.axis_names]
        if unknown:
            raise InputError(
                f"the line position names axes {unknown} the model does not have "
                f"(axes: {', '.join(spec.axis_names)})",
                source="line",
            )
        rows = []
        for r in readings:
            if r.units.kind != "linear" or r.axis not in spec.axis_names:
                raise InputError(
                    f"axis {r.axis}: an interferometer reads linear axes of the model "
                    f"({', '.join(a.name for a in spec.axes if not a.is_rotary)})",
                    source=r.source,
                    column="axis",
                )
            for way, dev in (("+", r.up), ("-", r.down)):
                for i, target in enumerate(r.targets):
                    for j in range(r.n):
                        row = {"station": f"{r.axis}-line", "point": f"{r.axis}{i}c{j + 1}{way}"}
                        for a in spec.axes:
                            unit = "deg" if a.is_rotary else "mm"
                            pos = target if a.name == r.axis else line.get(a.name, a.reference)
                            row[f"{a.name}_{unit}"] = float(pos)
                        row.update(zip(("tool_x_mm", "tool_y_mm", "tool_z_mm"), tool))
                        row["length_mm"] = float(target + dev[i, j])
                        rows.append(row)
        return pd.DataFrame(rows)


def _is_iso230_2(source) -> bool:
    """Does the table have the ISO 230-2 columns (``target_mm`` and ``cycle``)?"""
    if isinstance(source, pd.DataFrame):
        names = [str(c).strip().lower() for c in source.columns]
    else:
        try:
            with open(source, encoding="utf-8-sig") as f:
                names = [c.strip().lower() for c in f.readline().split(",")]
        except OSError:
            return False
    return "target_mm" in names and "cycle" in names


def _one_of(v: dict, base: str, label: str, *, required: bool) -> np.ndarray | None:
    """The ``base_mm`` or ``base_um`` column in mm (exactly one of them; None if neither
    and not required)."""
    mm, um = v.get(f"{base}_mm"), v.get(f"{base}_um")
    if mm is not None and um is not None:
        raise InputError(
            f"columns '{base}_mm' and '{base}_um' are the same quantity; keep one",
            source=label,
            row=1,
            column=f"{base}_um",
        )
    if mm is None and um is None:
        if required:
            raise InputError(
                f"missing required column '{base}_mm' (or '{base}_um')", source=label, row=1
            )
        return None
    return mm if mm is not None else um * 1e-3
