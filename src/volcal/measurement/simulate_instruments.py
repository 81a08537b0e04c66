"""Interferometer lines and ballbar circles simulated on the same true machine as
:func:`volcal.measurement.simulate.simulate`, written in the instruments' own table formats
(:mod:`volcal.measurement.instruments.interferometer`, ``.ballbar``).

Actual tool points from the exact model (``Machine.evaluate(..., exact=True)``) with the
error motions at the commanded poses; readings from the instrument's reading function
at set-up parameters drawn from the seed: an interferometer beam misaligned by up to
50 urad and a dead-path offset, a ballbar's table ball up to 20 um off the nominal centre
and a bar length up to 5 um off the nominal radius.  Noise: normal with the standard
uncertainty written in ``sigma_um`` (``noise=False``: exact readings, the same column).
:func:`planned_table` fills in a planned table (``volcal plan``'s ``added_*.csv``) instead
of the fixed lines and circles.
"""

from __future__ import annotations

from pathlib import Path
from typing import cast

import numpy as np
import pandas as pd

from volcal.measurement.instruments import Ballbar, LaserInterferometer
from volcal.model.errors import ErrorModel
from volcal.model.machine import Machine

#: standard uncertainty of an interferometer reading (um)
INTERFEROMETER_SIGMA_UM = 0.1
#: standard uncertainty of a ballbar reading (um)
BALLBAR_SIGMA_UM = 0.5


def _middle(machine: Machine) -> np.ndarray:
    """Axis positions (file units: mm, deg) at the middle of every travel."""
    return np.array([0.5 * (a.travel[0] + a.travel[1]) for a in machine.spec.axes])


def _columns(machine: Machine, prefix: str = "") -> list[str]:
    return [f"{prefix}{a.name}_{'deg' if a.is_rotary else 'mm'}" for a in machine.spec.axes]


def _actual_points(machine, em, theta, q_file, tool) -> tuple[np.ndarray, np.ndarray]:
    """(nominal, actual) tool points (N, 3) mm at poses in file units."""
    from volcal.measurement.simulate import _error_values

    q = machine.axis_to_internal(np.asarray(q_file, float))
    t = np.tile(np.asarray(tool, float), (len(q), 1))
    P, _, _ = machine.evaluate(q, t, _error_values(em, q, theta), exact=True)
    return machine.nominal_points(q, t), np.asarray(P, float)


def _read(ins, P: np.ndarray, station: np.ndarray, sigma_um: float, noise: bool, rng):
    """The instrument's readings (mm) of actual points P (N, 3) at one set-up, with normal
    noise of standard deviation sigma_um (um) when ``noise``."""
    m, _ = ins.evaluate(P, np.tile(station, (len(P), 1)))
    return m + rng.normal(0.0, sigma_um * 1e-3, len(P)) if noise else m


def _table(
    setup: str,
    points: list[str],
    columns: dict[str, object],
    tool: tuple[float, float, float],
    reading: tuple[str, np.ndarray],
    sigma_um: float,
) -> pd.DataFrame:
    """One set-up in an instrument's CSV layout: ``setup``, ``point``, the instrument's own
    ``columns`` (in order), ``tool_*_mm``, the reading column and ``sigma_um``."""
    df = pd.DataFrame({"setup": setup, "point": points})
    for c, v in columns.items():
        df[c] = v
    for c, v in zip("xyz", tool):
        df[f"tool_{c}_mm"] = v
    df[reading[0]] = reading[1]
    df["sigma_um"] = sigma_um
    return df


def interferometer_table(
    machine: Machine,
    em: ErrorModel,
    theta: np.ndarray,
    rng: np.random.Generator,
    *,
    n_targets: int = 11,
    tool: tuple[float, float, float] = (0.0, 0.0, 0.0),
    noise: bool = True,
) -> pd.DataFrame:
    """One line along every linear axis through the middle of the travel (``n_targets``
    targets over the axis' travel), as the interferometer's CSV."""
    ins = LaserInterferometer()
    mid = _middle(machine)
    frames = []
    for j, a in enumerate(machine.spec.axes):
        if a.is_rotary:
            continue
        q = np.tile(mid, (n_targets, 1))
        q[:, j] = np.linspace(a.travel[0], a.travel[1], n_targets)
        P0, P = _actual_points(machine, em, theta, q, tool)
        u = (P0[-1] - P0[0]) / np.linalg.norm(P0[-1] - P0[0])
        st = np.r_[u, rng.uniform(-50e-6, 50e-6, 2), rng.uniform(-100.0, 100.0)]
        m = _read(ins, P, st, INTERFEROMETER_SIGMA_UM, noise, rng)
        points = [f"t{i}" for i in range(n_targets)]
        columns = dict(zip(_columns(machine), q.T))
        reading = ("displacement_mm", m)
        frames.append(
            _table(f"{a.name}-line", points, columns, tool, reading, INTERFEROMETER_SIGMA_UM)
        )
    return pd.concat(frames, ignore_index=True)


def ballbar_table(
    machine: Machine,
    em: ErrorModel,
    theta: np.ndarray,
    rng: np.random.Generator,
    *,
    n_angles: int = 36,
    tool: tuple[float, float, float] = (0.0, 0.0, 0.0),
    noise: bool = True,
) -> pd.DataFrame:
    """One circle in every plane of two linear axes (XY, YZ, ZX order of the model),
    centred in the travel, radius 40 % of the smaller half-travel, as the ballbar's CSV."""
    ins = Ballbar()
    mid = _middle(machine)
    lin = [j for j, a in enumerate(machine.spec.axes) if not a.is_rotary]
    pairs = [(lin[i], lin[(i + 1) % len(lin)]) for i in range(len(lin))] if len(lin) > 2 else []
    if len(lin) == 2:
        pairs = [(lin[0], lin[1])]
    ang = np.arange(n_angles) * 360.0 / n_angles
    frames = []
    axes = machine.spec.axes
    for j1, j2 in pairs:
        half = min(np.ptp(axes[j1].travel), np.ptp(axes[j2].travel)) / 2
        radius = round(0.8 * half, -1) or 0.8 * half
        q = np.tile(mid, (n_angles, 1))
        q[:, j1] += radius * np.cos(np.deg2rad(ang))
        q[:, j2] += radius * np.sin(np.deg2rad(ang))
        _, P = _actual_points(machine, em, theta, q, tool)
        C = _actual_points(machine, em, np.zeros_like(theta), mid[None], tool)[0][0]
        st = np.r_[C + rng.uniform(-0.02, 0.02, 3), radius + rng.uniform(-5e-3, 5e-3)]
        m = _read(ins, P, st, BALLBAR_SIGMA_UM, noise, rng)
        plane = axes[j1].name + axes[j2].name
        points = [f"a{i}" for i in range(n_angles)]
        columns: dict[str, object] = {"plane": plane}
        columns.update(zip(_columns(machine, "centre_"), mid))
        columns.update(radius_mm=radius, angle_deg=ang)
        reading = ("deviation_um", m * 1e3)
        frames.append(_table(f"{plane}-circle", points, columns, tool, reading, BALLBAR_SIGMA_UM))
    return pd.concat(frames, ignore_index=True)


#: the reading column of each instrument's table (without the unit suffix)
_READING = {"interferometer": "displacement", "ballbar": "deviation"}


def planned_table(
    machine: Machine,
    em: ErrorModel,
    theta: np.ndarray,
    rng: np.random.Generator,
    instrument: str,
    source: str | Path | pd.DataFrame,
    *,
    noise: bool = True,
) -> pd.DataFrame:
    """The readings of a planned table of ``instrument`` (``interferometer`` or
    ``ballbar``): a CSV in the instrument's own format whose reading column
    (``displacement_um`` / ``_mm``, ``deviation_um`` / ``_mm``) may be empty or absent,
    e.g. ``added_interferometer.csv`` of ``volcal plan --add-minutes``.  The table is read
    (and checked, errors naming the file, row and column) by the instrument's reader, its
    reading column filled in from the same true machine, set-up by set-up (set-up
    parameters drawn as in :func:`interferometer_table` and :func:`ballbar_table`), with
    noise of the table's ``sigma_um`` / ``sigma_mm`` (default
    :data:`INTERFEROMETER_SIGMA_UM`, :data:`BALLBAR_SIGMA_UM`); every other column is
    kept as it is."""
    from volcal.base.exceptions import InputError

    ins = {"interferometer": LaserInterferometer(), "ballbar": Ballbar()}[instrument]
    label = str(source) if isinstance(source, (str, Path)) else "<DataFrame>"
    if isinstance(source, pd.DataFrame):
        df = source.copy()
    else:
        if not Path(source).is_file():
            raise InputError(f"no such {instrument} table file", source=label)
        df = pd.read_csv(source, skipinitialspace=True)
    base = _READING[instrument]
    col = next((c for c in (f"{base}_um", f"{base}_mm") if c in df.columns), f"{base}_um")
    probe = df.copy()
    probe[col] = 0.0  # the geometry only: the readings are what is simulated
    try:
        t = cast(pd.DataFrame, ins.read_table(probe, machine.spec))
    except InputError as exc:  # name the file, not the DataFrame it was read into
        text = str(exc)
        msg = text.split(": ", 1)[1] if text.startswith("<") and ": " in text else text
        raise InputError(msg, source=label, row=exc.row, column=exc.column) from None
    q_file = t[_columns(machine)].to_numpy(float)
    tool = t[["tool_x_mm", "tool_y_mm", "tool_z_mm"]].to_numpy(float)
    q = machine.axis_to_internal(q_file)
    from volcal.measurement.simulate import _error_values

    P, _, _ = machine.evaluate(q, tool, _error_values(em, q, theta), exact=True)
    P = np.asarray(P, float)
    P0 = machine.nominal_points(q, tool)
    default = INTERFEROMETER_SIGMA_UM if instrument == "interferometer" else BALLBAR_SIGMA_UM
    sigma_mm = np.full(len(t), default * 1e-3)
    if "sigma_mm" in t.columns:
        given = t["sigma_mm"].to_numpy(float)
        sigma_mm = np.where(np.isfinite(given), given, sigma_mm)
    m = np.zeros(len(t))
    station = t["station"].astype(str).to_numpy()
    for sid in pd.unique(station):
        rows = np.flatnonzero(station == sid)
        if instrument == "interferometer":
            u = P0[rows[-1]] - P0[rows[0]]
            if not np.linalg.norm(u) > 0:
                raise InputError(
                    f"set-up {sid}: its targets do not span a line", source=label, column="setup"
                )
            u = u / np.linalg.norm(u)
            st = np.r_[u, rng.uniform(-50e-6, 50e-6, 2), rng.uniform(-100.0, 100.0)]
        else:
            first = int(rows[0])
            qc = machine.axis_to_internal(
                df.loc[first, _columns(machine, "centre_")].to_numpy(float)[None]
            )
            C = machine.nominal_points(qc, tool[first][None])[0]
            R = float(df.loc[first, "radius_mm"])
            st = np.r_[C + rng.uniform(-0.02, 0.02, 3), R + rng.uniform(-5e-3, 5e-3)]
        m[rows], _ = ins.evaluate(P[rows], np.tile(st, (len(rows), 1)))
    if noise:
        m = m + rng.normal(0.0, 1.0, len(m)) * sigma_mm
    out = df.copy()
    out[col] = m * (1e3 if col.endswith("_um") else 1.0)
    if "sigma_um" not in out.columns and "sigma_mm" not in out.columns:
        out["sigma_um"] = sigma_mm * 1e3
    return out
