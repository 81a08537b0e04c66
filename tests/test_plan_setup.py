"""The plan as a set-up sheet (``volcal plan`` output read by a person and by the next
command).

Truths the planner did not produce:
* the aim the operator is told (the NC program's comments: the point the reflector's axis
  is aimed from and its direction) is checked against the constraint geometry computed
  here: nominal reflector points from the independent rigid-body simulator
  (tests/indep_sim.py), the angle between the stated aim and every station-to-reflector
  line;
* the margins: every station moved by 1 mm (many random directions) with the stated aim
  kept, re-checked against the declared limits with independent geometry (region boxes,
  distances, angles, beams sampled against the obstacles); a plan made without margins
  breaks under the same test;
* the hand-over plan -> simulate -> identify is in
  tests/test_planning.py::test_cli_plan_writes_a_plan_identify_can_read (one plan run).
"""

from __future__ import annotations

import json
import re

import numpy as np
import pandas as pd
import pytest

import indep_sim as ind
from test_planning import OBSTACLES, _cylinder_hit, _inside_box, _setting, _smoke_plan
from volcal.analysis.planning import plan
from volcal.outputs.plan_files import write_plan

NUM = r"(-?\d+(?:\.\d+)?)"


def _angles_deg(aim: np.ndarray, stations: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Angle between the aim (n, 3) and each point -> station line, deg."""
    beam = stations - points
    beam /= np.linalg.norm(beam, axis=1, keepdims=True)
    a = aim / np.linalg.norm(aim, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.sum(beam * a, axis=1), -1, 1)))


def _planned_points(model: str, mp: pd.DataFrame) -> np.ndarray:
    """Nominal reflector points of the plan's rows from the independent simulator."""
    geom = ind.load_geometry(model)
    q = geom.to_internal(mp[geom.axis_names].to_numpy(float))
    t = mp[["tool_x_mm", "tool_y_mm", "tool_z_mm"]].to_numpy(float)
    return ind.tool_points(geom, q, t)


def _sheet_from_program(text: str) -> dict[str, dict[str, np.ndarray]]:
    """What the NC program tells the operator per station: tracker position, the point
    the reflector's axis is aimed from and its direction (parsed from the comments)."""
    out: dict[str, dict[str, np.ndarray]] = {}
    station = None
    for line in text.splitlines():
        m = re.search(rf"station (S\d+) of \d+: tracker at x {NUM} y {NUM} z {NUM} mm", line)
        if m:
            station = m[1]
            out[station] = {"at": np.array([float(v) for v in m.groups()[1:]])}
        m = re.search(rf"aimed from the workspace centre x {NUM} y {NUM} z {NUM} mm", line)
        if m:
            out[station]["from"] = np.array([float(v) for v in m.groups()])
        m = re.search(rf"aim direction {NUM}, {NUM}, {NUM}:", line)
        if m:
            out[station]["dir"] = np.array([float(v) for v in m.groups()])
    return out


def test_the_stated_aim_keeps_every_beam_inside_the_acceptance_angle(tmp_path):
    res = _smoke_plan(obstacles=True)
    cfg, cons = _setting(**OBSTACLES)
    write_plan(res, tmp_path / "p", dialects=("iso", "fanuc"), plots=False)
    mp = pd.read_csv(tmp_path / "p" / "measurement_plan.csv")
    P = _planned_points(cfg["model"], mp)
    half = cons["reflector"]["half_angle_deg"]
    margin_deg = res.margins[0]
    for dialect in ("iso", "fanuc"):
        text = (tmp_path / "p" / f"program_{dialect}.nc").read_text()
        if dialect == "fanuc":  # upper case, as the control shows it
            text = text.lower().replace("station s", "station S")
        sheet = _sheet_from_program(text)
        assert sorted(sheet) == sorted(mp["station"].unique())
        for sid, s in sheet.items():
            rows = (mp["station"] == sid).to_numpy()
            # the stated direction points from the stated point at the stated tracker
            to_tracker = s["at"] - s["from"]
            assert _angles_deg(s["dir"][None], s["at"][None], s["from"][None])[0] < 0.1
            assert np.allclose(s["dir"], to_tracker / np.linalg.norm(to_tracker), atol=2e-3)
            n = int(rows.sum())
            ang = _angles_deg(np.tile(s["dir"], (n, 1)), np.tile(s["at"], (n, 1)), P[rows])
            # printed to 3 decimals (direction) and 0.1 mm: 0.2 deg of rounding at most
            assert ang.max() <= half - margin_deg + 0.2, (sid, ang.max())
    # the report states the same sheet and the tool offsets by value at every stop
    report = (tmp_path / "p" / "report.md").read_text()
    assert "## Set-up sheet" in report and "aimed from the workspace centre" in report
    iso = (tmp_path / "p" / "program_iso.nc").read_text()
    stops = re.findall(
        r"M00 \(set up the tracker at station (S\d+), mount the reflector at "
        rf"tool offset {NUM}, {NUM}, {NUM} mm",
        iso,
    )
    blocks = mp.groupby(["station", "tool_x_mm", "tool_y_mm", "tool_z_mm"], sort=False).size()
    assert [(s, float(x), float(y), float(z)) for s, x, y, z in stops] == list(blocks.index)
    summary = json.loads((tmp_path / "p" / "summary.json").read_text())
    assert summary["margins"] == {"deg": 5.0, "mm": 20.0}
    # the slack the summary states against the slack computed here from the sheet, the
    # independent points and the declared limits (no planner code)
    slack = {r["constraint"]: r["slack"] for r in summary["slack"]}
    sheet_iso = _sheet_from_program((tmp_path / "p" / "program_iso.nc").read_text())
    mine = _independent_slack(sheet_iso, mp, P, cons)
    assert set(slack) == set(mine)
    # the sheet is printed to 0.1 mm and 3 decimals of direction; the beams are sampled
    for k, tol in (("angle", 0.2), ("distance", 0.1), ("range", 0.1), ("region", 0.1),
                   ("sight", 1.0)):
        assert slack[k] == pytest.approx(mine[k], abs=tol), (k, slack[k], mine[k])
    assert mine["angle"] >= 5.0 - 0.2 and mine["region"] >= 20.0 - 0.1
    assert mine["distance"] >= 20.0 - 0.1 and mine["sight"] >= 20.0 - 1.0
    assert sorted(sheet_iso) == sorted(mp["station"].unique())


def _box_distance(p: np.ndarray, lo, hi) -> np.ndarray:
    """Distance of points p (..., 3) to a box, 0 inside (independent of the planner)."""
    return np.linalg.norm(p - np.clip(p, np.asarray(lo, float), np.asarray(hi, float)), axis=-1)


def _independent_slack(sheet, mp: pd.DataFrame, P: np.ndarray, cons: dict) -> dict[str, float]:
    """Slack per declared limit: the half-angle minus the largest angle between the
    stated aim and a beam; the smallest beam length minus the minimum distance; the
    smallest distance of a station to a face of its region box; the smallest distance of
    400 points along every beam to an obstacle (the box's distance, the cylinder's axis
    distance minus its radius; a beam that crosses one counts as 0)."""
    S = np.array([sheet[s]["at"] for s in mp["station"]])
    aim = np.array([sheet[s]["dir"] for s in mp["station"]])
    out = {}
    out["angle"] = cons["reflector"]["half_angle_deg"] - _angles_deg(aim, S, P).max()
    out["distance"] = np.linalg.norm(S - P, axis=1).min() - cons["min_distance_mm"]
    out["range"] = cons["max_range_mm"] - np.linalg.norm(S - P, axis=1).max()
    depth = []
    for st in sheet.values():
        x = st["at"]
        depth.append(max(
            min(np.min(x - np.asarray(r["box"][0])), np.min(np.asarray(r["box"][1]) - x))
            for r in cons["region"]
        ))
    out["region"] = min(depth)
    t = np.linspace(0.0, 1.0, 400)[None, :, None]
    beams = P[:, None, :] + t * (S - P)[:, None, :]  # (N, 400, 3)
    clear = np.inf
    for ob in cons["obstacle"]:
        shift = P[:, None, :] if ob.get("moves_with") == "tool" else 0.0
        if "box" in ob:
            d = _box_distance(beams - shift, *ob["box"])
        else:
            a, b = (np.asarray(v, float) for v in ob["cylinder"])
            ab = b - a
            rel = beams - shift - a
            u = np.clip(np.sum(rel * ab, -1) / np.sum(ab * ab), 0, 1)
            d = np.linalg.norm(rel - u[..., None] * ab, axis=-1) - ob["radius"]
        clear = min(clear, float(np.maximum(d, 0.0).min()))
    out["sight"] = clear
    return out


def test_box_obstacle_slack_is_the_beam_clearance():
    """A box obstacle's slack: the smallest distance of the beams to the box (sampled
    here), negative when a beam crosses it; the violation list agrees."""
    from volcal.analysis.planning.geometry import (
        Constraints,
        Obstacle,
        constraint_slack,
        reading_violations,
    )

    rng = np.random.default_rng(2)
    P = rng.uniform([-100, -100, 0], [100, 100, 50], (30, 3))
    S = np.array([[0.0, 800.0, 300.0]])
    box = Obstacle("box", lo=(-300.0, 400.0, -100.0), hi=(300.0, 450.0, 80.0), name="beam")
    cons = Constraints(obstacles=(box,))
    st = np.zeros(len(P), int)
    t = np.linspace(0.0, 1.0, 20001)[None, :, None]
    beams = P[:, None, :] + t * (S[st] - P)[:, None, :]
    expect = _box_distance(beams, box.lo, box.hi).min()
    sl = constraint_slack(P, np.zeros_like(P), st, S, cons, np.zeros(3)).set_index("constraint")
    assert expect > 1.0  # the beams pass above the box
    assert sl.loc["sight", "slack"] == pytest.approx(expect, abs=0.05)
    assert reading_violations(P, np.zeros_like(P), st, S, cons, np.zeros(3)).empty
    # raise the box into the beams: broken, negative slack, and the reading is listed
    high = Obstacle("box", lo=(-300.0, 400.0, -100.0), hi=(300.0, 450.0, 400.0), name="wall")
    cons = Constraints(obstacles=(high,))
    sl = constraint_slack(P, np.zeros_like(P), st, S, cons, np.zeros(3)).set_index("constraint")
    assert sl.loc["sight", "slack"] < 0
    bad = reading_violations(P, np.zeros_like(P), st, S, cons, np.zeros(3))
    assert int(sl.loc["sight", "reading"]) in set(bad["reading"])


def _broken_after_moving(res, cons, n_draws: int = 20, step_mm: float = 1.0) -> int:
    """Readings that break a declared limit when every station is moved by ``step_mm`` in
    random directions (the reflector keeps the aim stated for the planned position),
    counted over ``n_draws`` draws with independent geometry."""
    cfg, _ = _setting()
    mp = res.measurement_plan()
    P = _planned_points(cfg["model"], mp)
    st = mp["station"].str[1:].astype(int).to_numpy() - 1
    aim = res.aim()[["dir_x", "dir_y", "dir_z"]].to_numpy(float)[st]
    rng = np.random.default_rng(11)
    broken = 0
    for _ in range(n_draws):
        d = rng.normal(size=res.stations_mm.shape)
        S_all = res.stations_mm + step_mm * d / np.linalg.norm(d, axis=1, keepdims=True)
        S = S_all[st]
        bad = _angles_deg(aim, S, P) > cons["reflector"]["half_angle_deg"]
        dist = np.linalg.norm(S - P, axis=1)
        bad |= (dist < cons["min_distance_mm"]) | (dist > cons["max_range_mm"])
        inside = np.zeros(len(S_all), bool)
        for r in cons["region"]:
            lo, hi = np.array(r["box"], float)
            inside |= np.all((S_all >= lo) & (S_all <= hi), axis=1)
        bad |= ~inside[st]
        for ob in cons.get("obstacle", []):
            s = np.linspace(0, 1, 120)[None, :, None]
            beam = P[:, None, :] + s * (S - P)[:, None, :]
            if "box" in ob:
                bad |= _inside_box(beam, *ob["box"]).any(axis=1)
            else:
                a = P[:, None, :] + np.array(ob["cylinder"][0], float)
                b = P[:, None, :] + np.array(ob["cylinder"][1], float)
                bad |= _cylinder_hit(beam[:, 1:], a, b, ob["radius"]).any(axis=1)
        broken += int(bad.sum())
    return broken


def test_margins_hold_when_the_tracker_stands_1_mm_off_its_spot():
    res = _smoke_plan(obstacles=True)
    _, cons = _setting(**OBSTACLES)
    assert _broken_after_moving(res, cons) == 0
    # the same plan without margins sits on its limits: 1 mm off breaks readings
    cfg, cons0 = _setting()
    bare = plan(
        cfg["model"],
        n_stations=4,
        tools=np.array(cfg["tools"], float),
        readings=240,
        constraints=cons0,
        grid=4,
        starts=1,
        rounds=1,
        seed=3,
        margin_deg=0.0,
        margin_mm=0.0,
    )
    assert bare.violations().empty
    assert bare.slack()["slack"].min() < 0.01  # some declared limit is reached
    assert _broken_after_moving(bare, cons0) > 0


def test_margins_in_the_setting_file_and_too_large_ones(tmp_path):
    from volcal.analysis.planning.setting import load_setting
    from volcal.base.exceptions import InputError

    f = tmp_path / "s.toml"
    f.write_text('model = "mcv754_wxyzt"\nmargin_deg = 2.5\nmargin_mm = 7\n')
    cfg = load_setting(f)
    assert cfg["margin_deg"] == 2.5 and cfg["margin_mm"] == 7.0
    _, cons = _setting()
    with pytest.raises(InputError, match="left of the machine.*margin"):
        plan(cfg["model"], readings=240, constraints=cons, grid=4, margin_mm=300.0)
    with pytest.raises(InputError, match="half-angle"):
        plan(cfg["model"], readings=240, constraints=cons, grid=4, margin_deg=60.0)
