"""Planning settings from a TOML file (data only: parsing never executes code).

Keys (every one optional except ``model`` and at least one region; command-line flags
override them)::

    model = "mcv754_wxyzt"          # bundled model name or model file (relative to the file)
    stations = 4                    # tracker set-ups
    tools = [[0, 0, 0], [0, 0, -100]]   # available tool offsets, mm
    readings = 960                  # or: minutes = 60 and seconds_per_reading = 4
    budget = "paper002"
    criterion = "I"                 # I, A, D, E
    optimizer = "gradient"          # gradient, ga, none
    poses = "exchange"              # exchange, spread
    grid = 6                        # candidate positions per linear axis
    seed = 0
    degree = 3
    margin_deg = 5                  # kept off the acceptance half-angle, deg
    margin_mm = 20                  # kept inside regions, on distances and obstacles, mm
    start_stations = "S.csv"        # start or given stations (relative to the file)
    [instruments]                   # interferometer lines / ballbar circles to add
    add = ["interferometer", "ballbar"]
    minutes = 60                    # their time budget, on top of the tracker plan
    interferometer_setup_min = 15   # and the other costs of InstrumentCosts
    [travel]                        # the travel to cover, mm / deg
    X = [0, 754]
    [constraints]                   # see volcal.analysis.planning.geometry
    ...
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

from volcal.analysis.planning.additions import instruments_from_dict
from volcal.analysis.planning.evaluator import CRITERIA
from volcal.analysis.planning.geometry import constraints_from_dict
from volcal.analysis.planning.plan import OPTIMIZERS
from volcal.base.exceptions import InputError

__all__ = ["load_setting", "check_setting", "bundled_settings", "SETTING_KEYS"]

SETTING_KEYS = {
    "model": str,
    "stations": int,
    "tools": list,
    "readings": int,
    "minutes": float,
    "seconds_per_reading": float,
    "budget": str,
    "criterion": str,
    "optimizer": str,
    "poses": str,
    "grid": int,
    "seed": int,
    "degree": int,
    "starts": int,
    "population": int,
    "generations": int,
    "rounds": int,
    "margin_deg": float,
    "margin_mm": float,
    "start_stations": str,
    "travel": dict,
    "constraints": dict,
    "instruments": dict,
}


# lower limits of the counts (what the search needs to run at all)
_AT_LEAST = {
    "stations": 3,
    "readings": 1,
    "grid": 2,
    "seed": 0,
    "degree": 0,
    "starts": 1,
    "population": 2,
    "generations": 1,
    "rounds": 1,
}
_CHOICES = {
    "criterion": CRITERIA,
    "optimizer": OPTIMIZERS,
    "poses": ("exchange", "spread"),
}
_TYPE_WORDS = {
    int: "an integer",
    float: "a number",
    str: "a string",
    list: "an array",
    dict: "a table",
}


def _what(v: Any) -> str:
    """A TOML value's kind and value, for messages."""
    kind = {
        bool: "boolean",
        int: "integer",
        float: "number",
        str: "string",
        list: "array",
        dict: "table",
    }.get(type(v), type(v).__name__)
    text = repr(v)
    return f"{kind} {text if len(text) <= 60 else text[:57] + '...'}"


def check_setting(doc: Mapping[str, Any], source: str) -> dict[str, Any]:
    """The checked values of a parsed planning setting (a TOML document), before any
    model is built or search run: keys, types, ranges and choices, the tool offsets, the
    travel to cover and every constraint (:func:`constraints_from_dict`).  Raises
    :class:`InputError` naming ``source`` and the key."""
    unknown = sorted(set(doc) - set(SETTING_KEYS))
    if unknown:
        raise InputError(
            f"unknown key(s) {', '.join(unknown)}; expected some of {', '.join(SETTING_KEYS)}",
            source=source,
        )
    out: dict[str, Any] = {}
    for k, v in doc.items():
        want = SETTING_KEYS[k]
        ok = isinstance(v, want) or (want is float and isinstance(v, int))
        if isinstance(v, bool) or not ok:
            raise InputError(f"'{k}' must be {_TYPE_WORDS[want]}, got {_what(v)}", source=source)
        if want is float and k.startswith("margin_") and not (math.isfinite(v) and v >= 0):
            raise InputError(f"'{k}' must be a finite number >= 0, got {v!r}", source=source)
        if want is float and not k.startswith("margin_") and not (math.isfinite(v) and v > 0):
            raise InputError(f"'{k}' must be a finite number > 0, got {v!r}", source=source)
        if k in _AT_LEAST and v < _AT_LEAST[k]:
            raise InputError(f"'{k}' must be at least {_AT_LEAST[k]}, got {v}", source=source)
        if k in _CHOICES and v not in _CHOICES[k]:
            raise InputError(
                f"'{k}' must be one of {', '.join(_CHOICES[k])}, got {v!r}", source=source
            )
        out[k] = float(v) if want is float else v
    if "readings" in out and "minutes" in out:
        raise InputError("give the budget as 'readings' or as 'minutes', not both", source=source)
    if "tools" in out:
        t = out["tools"]
        if not t or not all(
            isinstance(r, list)
            and len(r) == 3
            and all(isinstance(a, (int, float)) and not isinstance(a, bool) for a in r)
            and all(math.isfinite(a) for a in r)
            for r in t
        ):
            raise InputError(
                "'tools' must be a list of tool offsets [x, y, z] of finite numbers (mm), "
                f"got {_what(t)}",
                source=source,
            )
    for axis, v in out.get("travel", {}).items():
        if not (
            isinstance(v, list)
            and len(v) == 2
            and all(isinstance(a, (int, float)) and not isinstance(a, bool) for a in v)
            and all(math.isfinite(a) for a in v)
            and v[0] < v[1]
        ):
            raise InputError(
                f"[travel] '{axis}' must be [lo, hi] with lo < hi (mm or deg), got {_what(v)}",
                source=source,
            )
    if "constraints" in out:
        constraints_from_dict(out["constraints"], where=f"{source}: [constraints]")
    if "instruments" in out:
        instruments_from_dict(out["instruments"], source)
    return out


def bundled_settings() -> dict[str, Path]:
    """{example name: setting file} of the bundled planning settings (``plan_<name>.toml``)."""
    root = Path(str(resources.files("volcal").joinpath("data")))
    return {p.stem.removeprefix("plan_"): p for p in sorted(root.glob("plan_*.toml"))}


def load_setting(source: str | Path) -> dict[str, Any]:
    """Read a planning setting (a TOML file or the name of a bundled one) into a dict of
    checked values; paths inside are made absolute relative to the file."""
    bundled = bundled_settings()
    path = bundled[str(source)] if str(source) in bundled else Path(source)
    try:
        with open(path, "rb") as fh:
            doc = tomllib.load(fh)
    except FileNotFoundError:
        raise InputError(
            f"no planning setting file {str(path)!r} (bundled: {', '.join(bundled)})",
            source=str(path),
        ) from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML: {exc}", source=str(path)) from None
    out = check_setting(doc, str(path))
    for k in ("start_stations",):
        if k in out:
            out[k] = str((path.parent / out[k]).resolve())
    if "model" in out and (out["model"].endswith(".toml") or "/" in out["model"]):
        out["model"] = str((path.parent / out["model"]).resolve())
    out["_source"] = str(path)
    return out
