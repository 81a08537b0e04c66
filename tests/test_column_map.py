"""Reading an instrument's export through a column mapping (--columns / columns=)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from volcal.base.exceptions import InputError
from volcal.measurement.tables import load_measurements, parse_column_map

ROOT = Path(__file__).resolve().parents[1]
EXPORT = ROOT / "examples" / "tracker_export" / "export.csv"
MAP = (
    "station=Tracker,point=Target,X=Machine X [mm],Y=Machine Y [mm],Z=Machine Z [mm],"
    "tool_x=Reflector dX,tool_y=Reflector dY,tool_z=Reflector dZ,length=Distance [m],"
    "time=Timestamp [s]"
)


def test_parse_column_map():
    assert parse_column_map("length=L[m], station=Tracker") == {
        "length": ("L", "m"),
        "station": ("Tracker", None),
    }
    with pytest.raises(InputError, match="unknown unit 'furlong'"):
        parse_column_map("length=L[furlong]")
    with pytest.raises(InputError, match="expected VOLCAL_COLUMN=FILE_COLUMN"):
        parse_column_map("length")


def test_mapped_export_reads_like_volcal_columns():
    raw = pd.read_csv(EXPORT)
    direct = pd.DataFrame(
        {
            "station": raw["Tracker"],
            "point": raw["Target"],
            "X": raw["Machine X [mm]"],
            "Y": raw["Machine Y [mm]"],
            "Z": raw["Machine Z [mm]"],
            "tool_x": raw["Reflector dX"],
            "tool_y": raw["Reflector dY"],
            "tool_z": raw["Reflector dZ"],
            "length": raw["Distance [m]"] * 1000.0,
            "time": raw["Timestamp [s]"],
        }
    )
    a = load_measurements(EXPORT, "mcv754_wxyzt", columns=MAP)
    b = load_measurements(direct, "mcv754_wxyzt")
    assert np.allclose(a.length, b.length, rtol=0, atol=1e-9)
    assert np.array_equal(a.q_internal, b.q_internal)
    assert list(a.station_ids) == list(b.station_ids)


def test_mapping_errors_name_the_problem():
    with pytest.raises(InputError, match="no column 'Dist'.*Distance"):
        load_measurements(EXPORT, "mcv754_wxyzt", columns="length=Dist[m]")
    with pytest.raises(InputError, match="volcal has no column 'lenght'.*'length'"):
        load_measurements(EXPORT, "mcv754_wxyzt", columns="lenght=Distance [m]")
    with pytest.raises(InputError, match="cannot be converted"):
        load_measurements(EXPORT, "mcv754_wxyzt", columns="length=Distance [m][deg]")
