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
    [travel]                        # the travel to cover, mm / deg
    X = [0, 754]
    [constraints]                   # see volcal.analysis.planning.geometry
    ...
"""

from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from volcal.base.exceptions import InputError

__all__ = ["load_setting", "bundled_settings", "SETTING_KEYS"]

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
}


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
    unknown = sorted(set(doc) - set(SETTING_KEYS))
    if unknown:
        raise InputError(
            f"unknown key(s) {', '.join(unknown)}; expected some of {', '.join(SETTING_KEYS)}",
            source=str(path),
        )
    out: dict[str, Any] = {}
    for k, v in doc.items():
        want = SETTING_KEYS[k]
        ok = isinstance(v, want) or (want is float and isinstance(v, int))
        if isinstance(v, bool) or not ok:
            raise InputError(f"'{k}' must be a {want.__name__}, got {v!r}", source=str(path))
        out[k] = float(v) if want is float else v
    for k in ("start_stations",):
        if k in out:
            out[k] = str((path.parent / out[k]).resolve())
    if "model" in out and (out["model"].endswith(".toml") or "/" in out["model"]):
        out["model"] = str((path.parent / out["model"]).resolve())
    out["_source"] = str(path)
    return out
