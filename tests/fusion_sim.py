"""Interferometer lines and ballbar circles simulated on tests/indep_sim.py's machine.

The readings are written from the physics with numpy on the simulator's true tool points
(exact transforms, a truth outside volcal's basis), not from volcal's instruments:
interferometer ``reading = b . P - offset`` along a beam b turned slightly away from the
line (true misalignment, a cosine error of 1e-9 relative), ballbar ``reading = |P - C| -
R`` with the table ball C off the nominal centre and a bar length R off the nominal.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

import indep_sim as ind

LINE_SIGMA_MM = 0.05e-3  # interferometer: 0.05 um per reading
CIRCLE_SIGMA_MM = 0.5e-3  # ballbar: 0.5 um per reading


def tracker_readings(geom, truth, tools, rng, n_stations: int) -> pd.DataFrame:
    """The tracker's table beside the other instruments: indep_sim's multilateration over
    a 4 x 4 x 4 grid of the linear axes with tool offsets ``tools`` (K, 3) mm from
    ``n_stations`` stations (random numbers from ``rng``), with the readings' standard
    uncertainty as its ``sigma`` column (mm)."""
    poses = ind.grid(geom, {"X": 4, "Y": 4, "Z": 4})
    sim = ind.simulate(geom, truth, poses, tools, rng, n_stations=n_stations)
    trk = sim.measurements.copy()
    trk["sigma"] = sim.sigma_mm
    return trk


def interferometer_lines(
    geom: ind.Geometry,
    truth: ind.Truth,
    lines: list[tuple[str, dict[str, float]]],
    rng: np.random.Generator,
    *,
    n_targets: int = 11,
    tool=(0.0, 0.0, 100.0),
    noise: bool = True,
    sigma_mm: float = LINE_SIGMA_MM,
) -> pd.DataFrame:
    """One set-up per (axis, {other axis: position}): targets over the axis' travel, the
    reflector at ``tool``; volcal's interferometer CSV (setup, axes, tool, displacement)."""
    frames = []
    t = np.asarray(tool, float)
    for k, (axis, fixed) in enumerate(lines):
        j = geom.axis_names.index(axis)
        q = np.zeros((n_targets, len(geom.axes)))
        for i, a in enumerate(geom.axes):
            q[:, i] = fixed.get(a.name, 0.0)
        q[:, j] = ind.linspace_travel(geom.axes[j], n_targets)
        qi = geom.to_internal(q)
        P = ind.tool_points(geom, qi, np.tile(t, (n_targets, 1)), truth)
        P0 = ind.tool_points(geom, qi, np.tile(t, (n_targets, 1)))
        u = P0[-1] - P0[0]
        u /= np.linalg.norm(u)
        # a misaligned beam: 50 urad off the line
        off = np.cross(u, [0.3, 0.5, 0.8])
        b = u + 50e-6 * off / np.linalg.norm(off)
        b /= np.linalg.norm(b)
        m = P @ b - rng.uniform(-50, 50)
        if noise:
            m = m + rng.normal(0, sigma_mm, n_targets)
        df = pd.DataFrame(
            {"setup": f"L{k + 1}{axis}", "point": [f"t{i}" for i in range(n_targets)]}
        )
        for i, a in enumerate(geom.axes):
            df[f"{a.name}_{'deg' if a.rotary else 'mm'}"] = q[:, i]
        for c, v in zip("xyz", t):
            df[f"tool_{c}_mm"] = v
        df["displacement_mm"] = m
        df["sigma_um"] = sigma_mm * 1e3
        frames.append(df)
    return pd.concat(frames, ignore_index=True)


def ballbar_circles(
    geom: ind.Geometry,
    truth: ind.Truth,
    circles: list[tuple[str, dict[str, float], float]],
    rng: np.random.Generator,
    *,
    n_angles: int = 24,
    tool=(0.0, 0.0, 100.0),
    noise: bool = True,
    sigma_mm: float = CIRCLE_SIGMA_MM,
) -> pd.DataFrame:
    """One set-up per (plane, centre {axis: position}, radius mm): volcal's ballbar CSV."""
    frames = []
    t = np.asarray(tool, float)
    ang = np.arange(n_angles) * 360.0 / n_angles
    for k, (plane, centre, radius) in enumerate(circles):
        a1, a2 = geom.axis_names.index(plane[0]), geom.axis_names.index(plane[1])
        qc = np.array([centre.get(a.name, 0.0) for a in geom.axes], float)
        q = np.tile(qc, (n_angles, 1))
        q[:, a1] += radius * np.cos(np.deg2rad(ang))
        q[:, a2] += radius * np.sin(np.deg2rad(ang))
        qi = geom.to_internal(q)
        P = ind.tool_points(geom, qi, np.tile(t, (n_angles, 1)), truth)
        C = ind.tool_points(geom, geom.to_internal(qc[None]), t[None])[0]
        C = C + rng.normal(0, 0.02, 3)  # the table ball set 20 um off the nominal centre
        R = radius + rng.uniform(-5e-3, 5e-3)  # the bar's length 5 um off nominal
        m = np.linalg.norm(P - C, axis=1) - radius
        m = m - (R - radius)
        if noise:
            m = m + rng.normal(0, sigma_mm, n_angles)
        df = pd.DataFrame(
            {"setup": f"B{k + 1}{plane}", "point": [f"a{i}" for i in range(n_angles)]}
        )
        df["plane"] = plane
        for i, a in enumerate(geom.axes):
            df[f"centre_{a.name}_{'deg' if a.rotary else 'mm'}"] = qc[i]
        df["radius_mm"] = radius
        df["angle_deg"] = ang
        for c, v in zip("xyz", t):
            df[f"tool_{c}_mm"] = v
        df["deviation_um"] = m * 1e3
        df["sigma_um"] = sigma_mm * 1e3
        frames.append(df)
    return pd.concat(frames, ignore_index=True)
