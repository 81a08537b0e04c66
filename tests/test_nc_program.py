"""``volcal.outputs.nc_program``: every dialect read back by an independent parser written here.

The parsers know only the dialects' syntax (not the module's templates or helpers): they
turn a program into a list of events (move with its axis words, feed and comment; dwell
with its duration in s; program stop with its operator comment; end) and check the
dialect's framing on the way (``%`` lines, block / line numbers, header codes).  One
checker then compares the events with the plan: the commanded poses in order (to the
printed precision: 3 decimals mm, 4 decimals deg), one dwell of the right length after
every move, a stop exactly where (station, tool) changes, and the point ids in the comments.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from volcal.base.exceptions import InputError
from volcal.outputs.nc_program import NC_DIALECTS, TEMPLATE_DIR, nc_program

AXES5 = [("X", "linear"), ("Y", "linear"), ("Z", "linear"), ("A", "rotary"), ("C", "rotary")]
PRECISION = {"linear": 3, "rotary": 4}


# ---------------------------------------------------------------------------- parsers


@dataclass
class Event:
    kind: str  # "move", "dwell", "stop", "end", "comment"
    pose: dict[str, float] = field(default_factory=dict)  # move: axis -> value, in order
    feed: float = math.nan  # move: mm/min
    seconds: float = math.nan  # dwell
    comment: str = ""


@dataclass
class Program:
    events: list[Event]
    modes: set[str]  # the modal codes / unit word set before the first move


WORD = re.compile(r"([A-Z]+)([+-]?\d+(?:\.\d*)?)")


def _words(body: str) -> list[tuple[str, str]]:
    out = []
    for tok in body.split():
        m = WORD.fullmatch(tok)
        assert m, f"not an address word: {tok!r} in {body!r}"
        out.append((m[1], m[2]))
    return out


def _paren(line: str) -> tuple[str, str | None]:
    """(code, comment) of an ISO / FANUC block: at most one comment, at the end, not nested."""
    m = re.fullmatch(r"([^()]*?)\s*(?:\(([^()]*)\))?", line)
    assert m, f"bad comment in {line!r}"
    return m[1].strip(), m[2]


def _iso_like(body: str, comment: str | None, prog: Program, *, fanuc: bool) -> None:
    ev = prog.events
    words = _words(body)
    if not words:
        ev.append(Event("comment", comment=comment or ""))
        return
    codes = [a + v for a, v in words if a in ("G", "M")]
    if codes[:1] == ["G01"]:
        pose = {a: float(v) for a, v in words[1:] if a != "F"}
        assert words[-1][0] == "F", body
        ev.append(Event("move", pose=pose, feed=float(words[-1][1]), comment=comment or ""))
    elif codes == ["G04"]:
        assert len(words) == 2, body
        addr, val = words[1]
        if fanuc:
            # P without decimal point = ms; with one, a FANUC may read seconds
            assert addr == "P" and "." not in val, body
            ev.append(Event("dwell", seconds=int(val) / 1000.0))
        else:
            assert addr == "X", body
            ev.append(Event("dwell", seconds=float(val)))
    elif codes == ["M00"]:
        ev.append(Event("stop", comment=comment or ""))
    elif codes == ["M30"]:
        ev.append(Event("end", comment=comment or ""))
    else:
        assert all(a == "G" for a, _ in words), body
        assert not any(e.kind == "move" for e in ev), f"modes after the first move: {body}"
        prog.modes |= set(codes)


def parse_iso(text: str) -> Program:
    lines = text.split("\n")
    assert lines[-1] == "", "program must end with a newline"
    lines = lines[:-1]
    assert lines[0] == "%" and lines[-1] == "%"
    assert "%" not in "".join(lines[1:-1])
    prog = Program([], set())
    numbers = []
    for line in lines[1:-1]:
        m = re.fullmatch(r"N(\d+) (.*)", line)
        assert m, f"block without number: {line!r}"
        numbers.append(int(m[1]))
        _iso_like(*_paren(m[2]), prog, fanuc=False)
    assert numbers == list(range(10, 10 * len(numbers) + 1, 10))
    return prog


def parse_fanuc(text: str) -> Program:
    lines = text.split("\n")
    assert lines[-1] == ""
    lines = lines[:-1]
    assert lines[0] == "%" and lines[-1] == "%"
    onum, _ = _paren(lines[1])
    assert re.fullmatch(r"O\d{4}", onum), lines[1]
    prog = Program([], {onum})
    for line in lines[2:-1]:
        code, comment = _paren(line)
        if comment is not None:
            assert comment == comment.upper(), f"FANUC comments are upper case: {line!r}"
        _iso_like(code, comment, prog, fanuc=True)
    return prog


def parse_siemens(text: str) -> Program:
    assert text.endswith("\n")
    prog = Program([], set())
    ev = prog.events
    for line in text.splitlines():
        body, _, comment = line.partition(";")
        words = _words(body)
        comment = comment.strip()
        codes = [a + v for a, v in words if a in ("G", "M")]
        if not words:
            ev.append(Event("comment", comment=comment))
        elif codes[:1] == ["G1"]:
            pose = {a: float(v) for a, v in words[1:] if a != "F"}
            assert words[-1][0] == "F", line
            ev.append(Event("move", pose=pose, feed=float(words[-1][1]), comment=comment))
        elif codes == ["G4"]:
            assert len(words) == 2 and words[1][0] == "F", line
            ev.append(Event("dwell", seconds=float(words[1][1])))
        elif codes == ["M0"]:
            ev.append(Event("stop", comment=comment))
        elif codes == ["M30"]:
            ev.append(Event("end", comment=comment))
        else:
            assert all(a == "G" for a, _ in words), line
            prog.modes |= set(codes)
    return prog


def parse_heidenhain(text: str) -> Program:
    assert text.endswith("\n")
    lines = text.splitlines()
    prog = Program([], set())
    ev = prog.events
    bodies = []
    for i, line in enumerate(lines):
        m = re.fullmatch(r"(\d+) (.*)", line)
        assert m and int(m[1]) == i, f"line {i} numbered wrongly: {line!r}"
        bodies.append(m[2])
    first = re.fullmatch(r"BEGIN PGM (\w+) (MM|INCH)", bodies[0])
    last = re.fullmatch(r"END PGM (\w+) (MM|INCH)", bodies[-1])
    assert first and last and first[1] == last[1] and first[2] == last[2]
    prog.modes.add(first[2])
    i = 1
    while i < len(bodies) - 1:
        b = bodies[i]
        if b.startswith(";"):
            ev.append(Event("comment", comment=b[1:].strip()))
        elif b == "STOP":
            # the operator's instruction is the comment line just before
            prev = ev.pop() if ev and ev[-1].kind == "comment" else Event("comment")
            ev.append(Event("stop", comment=prev.comment))
        elif b == "CYCL DEF 9.0 DWELL TIME":
            i += 1
            m = re.fullmatch(r"CYCL DEF 9\.1 DWELL (\d+(?:\.\d+)?)", bodies[i])
            assert m, bodies[i]
            ev.append(Event("dwell", seconds=float(m[1])))
        elif b.startswith("L "):
            code, _, comment = b[2:].partition(";")
            pose, feed = {}, math.nan
            for tok in code.split():
                if tok.startswith("F"):
                    feed = float(tok[1:])
                    continue
                # Klartext coordinates carry an explicit sign
                m = re.fullmatch(r"([A-Z]+)([+-]\d+\.\d+)", tok)
                assert m, f"coordinate without explicit sign: {tok!r}"
                pose[m[1]] = float(m[2])
            ev.append(Event("move", pose=pose, feed=feed, comment=comment.strip()))
        else:
            raise AssertionError(f"unexpected line {b!r}")
        i += 1
    ev.append(Event("end"))
    return prog


PARSERS = {
    "iso": parse_iso,
    "fanuc": parse_fanuc,
    "siemens": parse_siemens,
    "heidenhain": parse_heidenhain,
}
MODES = {
    "iso": {"G21", "G90"},
    "fanuc": {"G21", "G90", "G17"},
    "siemens": {"G71", "G90"},
    "heidenhain": {"MM"},
}


# ---------------------------------------------------------------------------- checker


def _block_starts(plan: pd.DataFrame) -> list[int]:
    keys = list(zip(plan["station"].astype(str), plan["tool"].astype(int)))
    return [i for i in range(len(keys)) if i == 0 or keys[i] != keys[i - 1]]


def check_program(
    prog: Program,
    plan: pd.DataFrame,
    axes,
    *,
    dialect: str,
    dwell_s: float,
    feed: float,
    safe: dict[str, float] | None = None,
) -> None:
    assert MODES[dialect] <= prog.modes, prog.modes
    ev = prog.events
    assert ev[-1].kind == "end" and sum(e.kind == "end" for e in ev) == 1
    names = [n for n, _ in axes]
    tol = {n: 0.5 * 10.0 ** -PRECISION[k] + 1e-9 for n, k in axes}
    points = plan["point"].to_numpy() if "point" in plan else np.arange(1, len(plan) + 1)

    row, stops_at, safe_moves = 0, [], []
    for j, e in enumerate(ev):
        if e.kind == "stop":
            stops_at.append(row)
            station, tool = plan["station"].iloc[row], int(plan["tool"].iloc[row])
            c = e.comment.lower()
            # the tool offset by its value when the plan has it, else by its number
            if "tool_x_mm" in plan:
                v = plan[["tool_x_mm", "tool_y_mm", "tool_z_mm"]].iloc[row]
                what = "tool offset " + ", ".join(f"{x:g}" for x in v) + " mm"
            else:
                what = f"tool number {tool}"
            assert f"station {str(station).lower()}" in c and what in c, e.comment
        elif e.kind == "move" and e.comment.lower() == "safe pose":
            safe_moves.append((j, e))
        elif e.kind == "move":
            assert row < len(plan), "more moves than plan rows"
            assert list(e.pose) == [n.upper() for n in names], e.pose
            for n in names:
                want = float(plan[n].iloc[row])
                assert abs(e.pose[n.upper()] - want) <= tol[n], (row, n, e.pose, want)
            assert e.feed == pytest.approx(feed, abs=5e-4)
            pid = int(points[row])
            assert re.search(rf"\bpoint {pid}\b", e.comment, re.I), e.comment
            assert ev[j + 1].kind == "dwell", "every move is followed by its dwell"
            row += 1
    assert row == len(plan), "fewer moves than plan rows"
    dwells = [e.seconds for e in ev if e.kind == "dwell"]
    assert len(dwells) == len(plan)
    assert np.allclose(dwells, dwell_s, atol=5e-4)
    assert stops_at == _block_starts(plan)
    if safe is None:
        assert not safe_moves
    else:
        # one retreat before every stop and one before the end
        assert len(safe_moves) == len(stops_at) + 1
        for j, e in safe_moves:
            after = next(f for f in ev[j + 1 :] if f.kind != "comment")
            assert after.kind in ("stop", "end")
            assert e.pose == pytest.approx({k.upper(): v for k, v in safe.items()}, abs=1e-3)


# ---------------------------------------------------------------------------- tests


@pytest.fixture
def plan() -> pd.DataFrame:
    rng = np.random.default_rng(7)
    n = 11
    df = pd.DataFrame(
        {
            "X": rng.uniform(-800, 800, n),
            "Y": rng.uniform(-400, 400, n),
            "Z": rng.uniform(-500, 0, n),
            "A": rng.uniform(-120, 30, n),
            "C": rng.uniform(-360, 360, n),
            # S1 twice with a tool change, then S2, then S1 again (a new block)
            "station": ["S1"] * 3 + ["S1"] * 2 + ["S2"] * 4 + ["S1"] * 2,
            "tool": [0, 0, 0, 1, 1, 1, 1, 1, 1, 1, 1],
            "point": [101, 102, 103, 201, 202, 7, 8, 9, 10, 55, 56],
        },
        index=range(100, 100 + n),
    )
    df.loc[101, "X"] = -0.0001  # rounds to zero: printed without a minus sign
    return df


@pytest.mark.parametrize("dialect", NC_DIALECTS)
def test_round_trip(plan, dialect):
    text = nc_program(plan, AXES5, dialect=dialect, dwell_s=1.5, feed_mm_min=3000.0)
    prog = PARSERS[dialect](text)
    check_program(prog, plan, AXES5, dialect=dialect, dwell_s=1.5, feed=3000.0)
    assert "-0.000" not in text
    assert sum(e.kind == "stop" for e in prog.events) == 4


@pytest.mark.parametrize("dialect", NC_DIALECTS)
def test_tool_offsets_by_value_and_set_up_notes(plan, dialect):
    p = plan.copy()
    values = {0: (0.0, 0.0, -100.0), 1: (80.0, 0.0, -100.5)}
    for j, c in enumerate(("tool_x_mm", "tool_y_mm", "tool_z_mm")):
        p[c] = [values[t][j] for t in p["tool"]]
    notes = {"S1": ["station S1 of 2: tracker at x 1 y 2 z 3 mm"], "S2": ["aim S2 (here)"]}
    text = nc_program(p, AXES5, dialect=dialect, setup_notes=notes)
    prog = PARSERS[dialect](text)
    check_program(prog, p, AXES5, dialect=dialect, dwell_s=2.0, feed=2000.0)
    ev = prog.events
    stops = [j for j, e in enumerate(ev) if e.kind == "stop"]
    # each station's notes once, as comments right before its first stop only
    assert "tool number" not in text.lower()
    assert "station s1 of 2" in ev[stops[0] - 1].comment.lower()
    # ISO and FANUC drop the parentheses a comment cannot hold
    assert "aim s2 here" in ev[stops[2] - 1].comment.lower().replace("(", "").replace(")", "")
    assert ev[stops[1] - 1].kind == "dwell" and ev[stops[3] - 1].kind == "dwell"
    assert sum("station s1 of 2" in e.comment.lower() for e in ev) == 1


@pytest.mark.parametrize("dialect", NC_DIALECTS)
def test_safe_pose_and_header_lines(plan, dialect):
    safe = {"Z": 0.0, "X": -10.0}  # given out of order: written in axis order
    text = nc_program(
        plan,
        AXES5,
        dialect=dialect,
        safe_pose=safe,
        header_lines=["operator: J. Doe (shift 2) 100%"],
    )
    prog = PARSERS[dialect](text)
    check_program(prog, plan, AXES5, dialect=dialect, dwell_s=2.0, feed=2000.0, safe=safe)
    first = next(e for e in prog.events if e.kind == "move")
    assert list(first.pose) == ["X", "Z"]
    assert any("operator: j. doe" in e.comment.lower() for e in prog.events)


def test_without_point_column_rows_are_numbered(plan):
    p = plan.drop(columns="point")
    check_program(parse_iso(nc_program(p, AXES5)), p, AXES5, dialect="iso", dwell_s=2, feed=2000)


def test_dialect_details(plan):
    fanuc = nc_program(plan, AXES5, dialect="fanuc", dwell_s=0.25)
    assert "G04 P250\n" in fanuc
    # the program number is stable (not Python's salted hash) and can be given
    assert fanuc.split("\n")[1] == nc_program(plan, AXES5, dialect="fanuc").split("\n")[1]
    assert nc_program(plan, AXES5, dialect="fanuc", program_name="O42").split("\n")[1] == (
        "O0042 (O42)"
    )
    siemens = nc_program(plan, AXES5, dialect="siemens")
    assert "DC(" in siemens.split("G71")[0]  # the note on modulo rotary axes, at the top
    hh = nc_program(plan, AXES5, dialect="heidenhain", program_name="plan_1").splitlines()
    assert hh[0] == "0 BEGIN PGM PLAN_1 MM" and hh[-1].endswith(" END PGM PLAN_1 MM")


def test_comments_cannot_break_the_syntax(plan):
    p = plan.copy()
    p["station"] = p["station"].replace("S2", "left (2)")
    for dialect in ("iso", "fanuc"):
        text = nc_program(p, AXES5, dialect=dialect, header_lines=["a (b) 5%", "two\nlines"])
        PARSERS[dialect](text)  # would fail on nested parentheses or a stray %
        assert "STATION LEFT 2" in text.upper()


def test_template_files_exist():
    assert sorted(p.stem for p in TEMPLATE_DIR.glob("*.j2")) == sorted(NC_DIALECTS)


def test_unknown_dialect(plan):
    with pytest.raises(InputError, match="unknown NC dialect 'gcode'") as e:
        nc_program(plan, AXES5, dialect="gcode")
    assert all(d in str(e.value) for d in NC_DIALECTS)


def test_missing_axis_column(plan):
    with pytest.raises(InputError, match=r"no axis column 'C'.*present: X, Y, Z, A, station"):
        nc_program(plan.drop(columns="C"), AXES5)
    with pytest.raises(InputError, match="no column 'tool'"):
        nc_program(plan.drop(columns="tool"), AXES5)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_value(plan, bad):
    p = plan.copy()
    p.loc[103, "Y"] = bad  # the 4th row
    with pytest.raises(InputError, match=r"column 'Y'.*non-finite.*row 4 of the plan \(index 103"):
        nc_program(p, AXES5)


def test_empty_plan(plan):
    with pytest.raises(InputError, match="empty"):
        nc_program(plan.iloc[:0], AXES5)


def test_other_bad_inputs(plan):
    p = plan.copy()
    p["tool"] = p["tool"].astype(float)
    p.loc[105, "tool"] = 1.5
    with pytest.raises(InputError, match="column 'tool'.*integer"):
        nc_program(p, AXES5)
    with pytest.raises(InputError, match="kind 'angular'"):
        nc_program(plan, [("X", "linear"), ("A", "angular")])
    with pytest.raises(InputError, match="NC address"):
        nc_program(plan.rename(columns={"X": "F"}), [("F", "linear")])
    with pytest.raises(InputError, match="unknown axes"):
        nc_program(plan, AXES5, safe_pose={"W": 0.0})
    with pytest.raises(InputError, match="dwell_s"):
        nc_program(plan, AXES5, dwell_s=-1.0)
    with pytest.raises(InputError, match="feed_mm_min"):
        nc_program(plan, AXES5, feed_mm_min=0.0)


# ---------------------------------------------------------------------------- property


@st.composite
def plans(draw):
    rotary = draw(st.booleans())
    axes = [("X", "linear"), ("Y", "linear"), ("Z", "linear")] + ([("B", "rotary")] * rotary)
    n = draw(st.integers(1, 12))
    value = st.floats(-5000, 5000, allow_nan=False, allow_infinity=False)
    cols = {name: draw(st.lists(value, min_size=n, max_size=n)) for name, _ in axes}
    cols["station"] = draw(st.lists(st.sampled_from(["S1", "S2", "far"]), min_size=n, max_size=n))
    cols["tool"] = draw(st.lists(st.integers(0, 3), min_size=n, max_size=n))
    cols["point"] = draw(st.lists(st.integers(0, 10**6), min_size=n, max_size=n))
    return pd.DataFrame(cols), axes


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    case=plans(),
    dwell=st.floats(0, 60, allow_nan=False),
    feed=st.floats(1, 20000, allow_nan=False),
)
def test_iso_round_trip_property(case, dwell, feed):
    plan, axes = case
    dwell, feed = round(dwell, 3), round(feed, 3)  # the printed precision of both
    text = nc_program(plan, axes, dialect="iso", dwell_s=dwell, feed_mm_min=feed)
    check_program(parse_iso(text), plan, axes, dialect="iso", dwell_s=dwell, feed=feed)
