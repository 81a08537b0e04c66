"""NC programs that drive a machine tool through a measurement plan.

A measurement plan is the sequence of machine poses at which a laser tracker reads the
distance to a reflector on the spindle.  :func:`nc_program` writes it as a program for the
machine's control, in one of :data:`NC_DIALECTS`:

* ``"iso"``: ISO 6983 (``%`` ... ``%``, block numbers ``N10, N20, ...``, ``G01``,
  ``G04 X<s>``, ``M00``, ``M30``, comments in parentheses);
* ``"fanuc"``: FANUC (``O<number>``, ``G04 P<ms>``, upper-case comments);
* ``"siemens"``: SINUMERIK 840D (``G71 G90``, ``G4 F<s>``, ``M0``, ``;`` comments);
* ``"heidenhain"``: HEIDENHAIN Klartext (``BEGIN PGM`` / ``END PGM``, ``L X+... F...``,
  ``CYCL DEF 9`` dwell, ``STOP``).

The program holds, in order: a header (name, units, absolute coordinates, comments), and
for every block of consecutive plan rows with the same (station, tool) the station's
set-up notes (``setup_notes``, comment lines before its first block: where the tracker
stands, where the reflector points) and a program stop with the operator's instruction
(set up the tracker at the station, mount the reflector at the tool offset, given by its
value in mm when the plan has ``tool_x_mm, tool_y_mm, tool_z_mm``), then for every row a
linear move to the pose at the feed ``feed_mm_min`` (mm/min), a dwell of ``dwell_s``
seconds during which the tracker reads, and a comment naming the point, station and tool
offset on the move's line; last the program end.

Units: linear axes in mm (3 decimals), rotary axes in deg (4 decimals).  The values are
the plan's axis positions as given, in the control's active work coordinate system: the
operator sets that so that its zero is the model's axis zero.  No tool length or radius
compensation is commanded.  The moves are straight lines (G01 / L) from pose to pose: the
plan must be free of collisions along them.

The syntax of each dialect lives in a Jinja2 template ``templates/nc/<dialect>.j2`` next to
this module; the templates receive the poses and comments already formatted and checked
(see :func:`_render`), and a counter ``nr()`` for block / line numbers.
"""

from __future__ import annotations

import math
import re
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from itertools import count
from pathlib import Path
from typing import Any

import jinja2
import numpy as np
import pandas as pd

from volcal.base.exceptions import InputError

NC_DIALECTS = ("iso", "fanuc", "siemens", "heidenhain")
"""The dialects :func:`nc_program` writes (the names of the templates in ``templates/nc``)."""

TEMPLATE_DIR = Path(__file__).parent / "templates" / "nc"

AXIS_KINDS = ("linear", "rotary")
# decimals printed per axis kind: 1 um on linear axes, 0.0001 deg (about 0.5 urad, far below
# what the tracker resolves at the spindle) on rotary axes
DECIMALS = {"linear": 3, "rotary": 4}

# address letters that mean something else in at least one dialect (feed, G/M codes, block
# number, program number, dwell, spindle, tool, radius, ...): an axis of that name would
# be read as that word
_RESERVED_ADDRESSES = frozenset("DFGHLMNOPRST")
_AXIS_NAME = re.compile(r"[A-Za-z][A-Za-z0-9]*")
# FANUC accepts only a small character set in comments; everything else becomes a space
_FANUC_COMMENT_DROP = re.compile(r"[^A-Z0-9 .,:_+\-=/#*]")


@dataclass(frozen=True)
class _Word:
    """One axis word of a move, formatted: ``text`` plain (``-20.000``), ``signed`` with an
    explicit sign (``-20.000`` / ``+100.000``, HEIDENHAIN)."""

    name: str
    text: str
    signed: str


@dataclass(frozen=True)
class _Row:
    words: list[_Word]
    comment: str


@dataclass(frozen=True)
class _Block:
    station: str
    tool: int
    stop_comment: str
    rows: list[_Row]
    notes: list[str]


def nc_program(
    plan: pd.DataFrame,
    axes: Sequence[tuple[str, str]],
    *,
    dialect: str = "iso",
    dwell_s: float = 2.0,
    feed_mm_min: float = 2000.0,
    program_name: str = "VOLCAL",
    safe_pose: Mapping[str, float] | None = None,
    header_lines: Sequence[str] = (),
    setup_notes: Mapping[str, Sequence[str]] | None = None,
) -> str:
    """The NC program that visits the poses of ``plan`` in order, as text.

    Parameters
    ----------
    plan
        One row per reading in measuring order: one column per axis named as the axis
        (linear axes in mm, rotary axes in deg), ``station`` (str, the tracker set-up the
        row belongs to), ``tool`` (int, the number of the reflector / tool offset: it
        groups the rows), optionally ``tool_x_mm, tool_y_mm, tool_z_mm`` (the tool
        offset's value, mm, printed in the comments instead of the number) and
        optionally ``point`` (int, the id printed in the comment; without it the rows are
        numbered 1, 2, ...).  Consecutive rows with the same (station, tool) form one block,
        which starts with a program stop for the operator.  The index is not used.
    axes
        The machine's axes in model order as ``(name, kind)``, kind ``"linear"`` (mm) or
        ``"rotary"`` (deg), e.g. ``[("X", "linear"), ("Y", "linear"), ("Z", "linear"),
        ("A", "rotary"), ("C", "rotary")]``.  Every move commands every axis, in this order.
    dialect
        One of :data:`NC_DIALECTS`.
    dwell_s
        Dwell at each pose, s (>= 0), the time the tracker has to read.  FANUC programs it
        in whole ms.
    feed_mm_min
        Feed of the moves, mm/min (> 0); how the control applies it to moves that include
        rotary axes is the control's setting.
    program_name
        Program name (letters, digits, ``_``; other characters are dropped, and HEIDENHAIN
        and FANUC names are upper case).  FANUC needs a program number: ``"O1234"`` or
        ``"1234"`` gives O1234, any other name a stable number in 1000-7999 from its CRC-32
        (8000-9999 are often edit-protected).
    safe_pose
        Axis positions (mm / deg) of a pose where the operator can work at the machine, for
        any subset of the axes: when given, the machine moves there (linear move, same
        feed) before each program stop and before the program end.  The other axes keep
        their position.
    header_lines
        Extra comment lines written after the program's own header comments.
    setup_notes
        {station: comment lines}, written before the first program stop of that station
        (the set-up sheet: where the tracker stands, where the reflector points).

    Returns
    -------
    str
        The program, lines separated by ``\\n``, ending with a newline.

    Raises
    ------
    InputError
        Unknown dialect, bad axes, an empty plan, a missing column, a non-finite value or
        non-integer tool / point, a bad ``dwell_s``, ``feed_mm_min``, ``program_name`` or
        ``safe_pose``.
    """
    if dialect not in NC_DIALECTS:
        raise InputError(
            f"unknown NC dialect {dialect!r}; known dialects: {', '.join(NC_DIALECTS)}"
        )
    axis_list = _check_axes(axes)
    if not (math.isfinite(dwell_s) and dwell_s >= 0):
        raise InputError(f"dwell_s must be a finite number of seconds >= 0, got {dwell_s!r}")
    if not (math.isfinite(feed_mm_min) and feed_mm_min > 0):
        raise InputError(f"feed_mm_min must be a finite feed > 0 (mm/min), got {feed_mm_min!r}")
    blocks, n_rows = _blocks(plan, axis_list, dialect, setup_notes or {})
    safe = _safe_words(safe_pose, axis_list)
    name = _program_name(program_name, dialect)

    def note(text: str) -> str:
        return _comment(text, dialect)

    stations = {b.station for b in blocks}
    # short lines without parentheses or apostrophes, so that they read the same in every
    # dialect (FANUC drops both) and stay within the controls' comment lengths
    header = [
        f"volcal measurement plan: poses {n_rows}, set-ups {len(blocks)}, "
        f"tracker stations {len(stations)}",
        "axis positions in the active work coordinate system",
        "its zero must be the axis zero of the model",
        "linear axes mm, rotary axes deg, no tool compensation",
        f"feed {_short(feed_mm_min)} mm/min, dwell {_short(dwell_s)} s per pose",
        *header_lines,
    ]
    mapping: dict[str, Any] = {
        "name": name,
        "program_number": _fanuc_number(program_name) if dialect == "fanuc" else 0,
        "header": [note(h) for h in header],
        "blocks": blocks,
        "safe": safe,
        "safe_comment": note("safe pose"),
        "end_comment": note("end of measurement plan"),
        "feed": _short(feed_mm_min),
        "dwell_s": f"{dwell_s:.3f}",
        # FANUC reads P without a decimal point as ms (with one, some controls read s)
        "dwell_ms": str(int(round(dwell_s * 1000.0))),
        "rotary": [n.upper() for n, k in axis_list if k == "rotary"],
    }
    return _render(dialect, mapping)


def _render(dialect: str, mapping: dict[str, Any]) -> str:
    """``templates/nc/<dialect>.j2`` rendered with ``mapping`` and ``nr()``: block numbers
    10, 20, ... (ISO) or line numbers 0, 1, ... (HEIDENHAIN); a fresh counter per program,
    so the numbers are consecutive however the template nests its loops."""
    step: Callable[[], int] = count(10, 10).__next__ if dialect == "iso" else count(0).__next__
    return _environment().get_template(f"{dialect}.j2").render(mapping, nr=step)


@lru_cache(maxsize=1)
def _environment() -> jinja2.Environment:
    # the same settings as the compensation templates: an undefined variable is an error,
    # nothing is escaped (the output is not HTML), block tags leave no blank lines
    return jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(TEMPLATE_DIR)),
        undefined=jinja2.StrictUndefined,
        autoescape=False,
        keep_trailing_newline=True,
        trim_blocks=True,
        lstrip_blocks=True,
    )


def _check_axes(axes: Sequence[tuple[str, str]]) -> list[tuple[str, str]]:
    out: list[tuple[str, str]] = []
    seen: set[str] = set()
    for item in axes:
        try:
            name, kind = item
        except (TypeError, ValueError):
            raise InputError(f"an axis is (name, kind), got {item!r}") from None
        if not isinstance(name, str) or not _AXIS_NAME.fullmatch(name):
            raise InputError(f"axis name {name!r}: expected a letter followed by letters/digits")
        if name.upper() in _RESERVED_ADDRESSES:
            raise InputError(
                f"axis name {name!r} is an NC address ({', '.join(sorted(_RESERVED_ADDRESSES))}"
                " are reserved)"
            )
        if name.upper() in seen:
            raise InputError(f"axis {name!r} is given twice")
        if kind not in AXIS_KINDS:
            raise InputError(f"axis {name!r}: kind {kind!r}, expected 'linear' or 'rotary'")
        seen.add(name.upper())
        out.append((name, kind))
    if not out:
        raise InputError("no axes given")
    return out


def _tool_text(values: np.ndarray | None, tool: int) -> str:
    """The tool offset as the operator mounts it: its value (``tool offset 0, 0, -100 mm``)
    when known, else its number in the plan."""
    if values is None:
        return f"tool number {tool}"
    # rounded first and + 0.0 so that -0.0 prints as 0
    return "tool offset " + ", ".join(_short(round(float(v), 3) + 0.0) for v in values) + " mm"


def _blocks(
    plan: pd.DataFrame,
    axes: list[tuple[str, str]],
    dialect: str,
    setup_notes: Mapping[str, Sequence[str]],
) -> tuple[list[_Block], int]:
    """The plan's rows grouped into blocks of consecutive rows with the same (station, tool),
    formatted for ``dialect``; and the number of rows."""
    if not isinstance(plan, pd.DataFrame):
        raise InputError(f"the plan must be a pandas DataFrame, got {type(plan).__name__}")
    if len(plan) == 0:
        raise InputError("the plan is empty: it needs at least one row (pose)")
    present = ", ".join(map(str, plan.columns)) or "none"
    for col in [n for n, _ in axes] + ["station", "tool"]:
        if col not in plan.columns:
            what = "axis column" if col not in ("station", "tool") else "column"
            raise InputError(
                f"the plan has no {what} {col!r}; columns present: {present}", source="plan"
            )
    values = {n: _finite_column(plan, n) for n, _ in axes}
    tools = _integer_column(plan, "tool")
    points = (
        _integer_column(plan, "point")
        if "point" in plan.columns
        else np.arange(1, len(plan) + 1, dtype=np.int64)
    )
    stations = [_station(s, i, plan) for i, s in enumerate(plan["station"].to_list())]
    tcols = ["tool_x_mm", "tool_y_mm", "tool_z_mm"]
    tvals = (
        np.column_stack([_finite_column(plan, c) for c in tcols])
        if all(c in plan.columns for c in tcols)
        else None
    )

    blocks: list[_Block] = []
    key: tuple[str, int] | None = None
    noted: set[str] = set()
    for i in range(len(plan)):
        station, tool = stations[i], int(tools[i])
        what = _tool_text(None if tvals is None else tvals[i], tool)
        if (station, tool) != key:
            key = (station, tool)
            stop = (
                f"set up the tracker at station {station}, mount the reflector at {what}, "
                "then cycle start"
            )
            notes = [] if station in noted else list(setup_notes.get(station, ()))
            noted.add(station)
            lines = [_comment(n, dialect) for n in notes]
            blocks.append(_Block(station, tool, _comment(stop, dialect), [], lines))
        words = [_word(n, k, float(values[n][i])) for n, k in axes]
        comment = _comment(f"point {int(points[i])} station {station} {what}", dialect)
        blocks[-1].rows.append(_Row(words, comment))
    return blocks, len(plan)


def _where(plan: pd.DataFrame, i: int) -> str:
    return f"row {i + 1} of the plan (index {plan.index[i]!r})"


def _finite_column(plan: pd.DataFrame, col: str) -> np.ndarray:
    try:
        v = pd.to_numeric(plan[col], errors="coerce").to_numpy(dtype=float, na_value=np.nan)
    except (TypeError, ValueError):
        raise InputError("expected numbers", source="plan", column=col) from None
    bad = np.flatnonzero(~np.isfinite(v))
    if bad.size:
        i = int(bad[0])
        raise InputError(
            f"non-finite or non-numeric value {plan[col].iloc[i]!r} in {_where(plan, i)}: "
            "expected a finite number",
            source="plan",
            column=col,
        )
    return v


def _integer_column(plan: pd.DataFrame, col: str) -> np.ndarray:
    v = _finite_column(plan, col)
    bad = np.flatnonzero(v != np.round(v))
    if bad.size:
        i = int(bad[0])
        raise InputError(
            f"expected an integer, got {plan[col].iloc[i]!r} in {_where(plan, i)}",
            source="plan",
            column=col,
        )
    return v.astype(np.int64)


def _station(s: object, i: int, plan: pd.DataFrame) -> str:
    # None, NaN and pd.NA all mean a missing station (pd.isna is elementwise on arrays)
    if s is None or (pd.api.types.is_scalar(s) and pd.isna(s)) or str(s).strip() == "":
        raise InputError(f"no station in {_where(plan, i)}", source="plan", column="station")
    return str(s).strip()


def _word(name: str, kind: str, value: float) -> _Word:
    d = DECIMALS[kind]
    # round first and add 0.0 so that -0.0004 prints as 0.000, not -0.000
    v = round(value, d) + 0.0
    return _Word(name.upper(), f"{v:.{d}f}", f"{v:+.{d}f}")


def _safe_words(
    safe_pose: Mapping[str, float] | None, axes: list[tuple[str, str]]
) -> list[_Word] | None:
    if safe_pose is None:
        return None
    kinds = dict(axes)
    unknown = [k for k in safe_pose if k not in kinds]
    if unknown:
        raise InputError(f"safe_pose names unknown axes {unknown}; the axes are {', '.join(kinds)}")
    if not safe_pose:
        raise InputError("safe_pose is empty: give at least one axis position or None")
    words = []
    # in model axis order, whatever the mapping's order
    for n, k in axes:
        if n in safe_pose:
            v = float(safe_pose[n])
            if not math.isfinite(v):
                raise InputError(f"safe_pose: non-finite value {v!r} for axis {n!r}")
            words.append(_word(n, k, v))
    return words


def _comment(text: str, dialect: str) -> str:
    """``text`` made safe for a comment of ``dialect``: one line; without the characters that
    would end a parenthesised comment early (``(``, ``)``) or end the tape (``%``) in ISO and
    FANUC; upper case and FANUC's character set for FANUC."""
    t = " ".join(str(text).split())
    if dialect in ("iso", "fanuc"):
        t = t.replace("(", "").replace(")", "").replace("%", "")
    if dialect == "fanuc":
        t = _FANUC_COMMENT_DROP.sub(" ", t.upper())
    return " ".join(t.split())


def _program_name(name: str, dialect: str) -> str:
    clean = re.sub(r"[^A-Za-z0-9_]", "", str(name))
    if not clean:
        raise InputError(
            f"program_name {name!r} has no letters or digits; give e.g. 'VOLCAL' or 'O1234'"
        )
    return clean.upper() if dialect in ("heidenhain", "fanuc") else clean


def _fanuc_number(name: str) -> int:
    """The FANUC program number: given as ``O1234`` / ``1234`` (1-9999), else from the CRC-32
    of the name (stable across runs and machines, unlike ``hash``) in 1000-7999."""
    m = re.fullmatch(r"[Oo]?(\d{1,4})", name.strip())
    if m and int(m.group(1)) > 0:
        return int(m.group(1))
    return 1000 + zlib.crc32(name.encode("utf-8")) % 7000


def _short(x: float) -> str:
    """``x`` with up to 3 decimals and no trailing zeros (``2000``, ``2.5``)."""
    return f"{x:.3f}".rstrip("0").rstrip(".")
