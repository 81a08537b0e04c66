"""Loading and validation of measurement and stations tables (volcal.measurement.tables)."""
from __future__ import annotations

import re
import warnings

import numpy as np
import pandas as pd
import pytest

from volcal.base.exceptions import InputError
from volcal.measurement.tables import (
    MAX_LENGTH_MM,
    DataWarning,
    Measurements,
    load_measurements,
    load_stations,
)
from volcal.model.spec import resolve_model

STATIONS = {"S1": (-300.0, -200.0, -400.0), "S2": (1000.0, -200.0, -350.0),
            "S3": (1000.0, 700.0, -450.0), "S4": (-300.0, 700.0, -300.0)}


@pytest.fixture(scope="module")
def spec3():
    return resolve_model("mcv754_wxyzt")  # X [0, 754], Y [0, 500], Z [-550, 0]


@pytest.fixture(scope="module")
def spec5():
    return resolve_model("head_bc")  # X Y Z C B, C [-180, 180], B [-100, 100] deg


def make_table(n_points: int = 12, stations=("S1", "S2", "S3", "S4"), seed: int = 0,
               tool: bool = True) -> pd.DataFrame:
    """A valid 3-axis table: every station sees the same spatial, non-coplanar points."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(0, 754, n_points)
    Y = rng.uniform(0, 500, n_points)
    Z = rng.uniform(-550, 0, n_points)
    tz = np.where(np.arange(n_points) % 2 == 0, 0.0, 100.0)
    rows = []
    for s in stations:
        sx, sy, sz = STATIONS[s]
        for i in range(n_points):
            p = np.array([X[i], Y[i], Z[i] + tz[i]])
            row = {"station": s, "point": f"P{i + 1}", "X": X[i], "Y": Y[i], "Z": Z[i]}
            if tool:
                row["tool_z"] = tz[i]
            row["length"] = float(np.linalg.norm(p - (sx, sy, sz)))
            rows.append(row)
    return pd.DataFrame(rows)


def write(tmp_path, df: pd.DataFrame, name: str = "meas.csv"):
    path = tmp_path / name
    df.to_csv(path, index=False)
    return path


def quiet_load(*args, **kwargs) -> Measurements:
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataWarning)
        return load_measurements(*args, **kwargs)


def error_of(*args, **kwargs) -> InputError:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)
        with pytest.raises(InputError) as info:
            load_measurements(*args, **kwargs)
    return info.value


def assert_where(err: InputError, source: str, row: int | None, column: str | None) -> str:
    msg = str(err)
    assert source in msg
    if row is not None:
        assert err.row == row and f"row {row}" in msg
    if column is not None:
        assert err.column == column and f"column '{column}'" in msg
    return msg


# ---------------------------------------------------------------------------------------
# valid input


def test_valid_table_gives_solver_arrays(spec3):
    df = make_table()
    m = quiet_load(df, spec3)
    assert len(m) == m.n == 48
    assert m.axis_names == ("X", "Y", "Z")
    assert m.station_ids == ["S1", "S2", "S3", "S4"]
    assert m.point_ids == [f"P{i}" for i in range(1, 13)]
    np.testing.assert_array_equal(m.station_index, np.repeat(np.arange(4), 12))
    np.testing.assert_array_equal(m.point_index, np.tile(np.arange(12), 4))
    np.testing.assert_allclose(m.q_internal, df[["X", "Y", "Z"]].to_numpy())
    np.testing.assert_allclose(m.tool[:, 2], df["tool_z"])
    assert np.all(m.tool[:, :2] == 0.0)
    np.testing.assert_allclose(m.length, df["length"])
    assert np.all(np.isnan(m.sigma)) and np.all(np.isnan(m.time))
    assert not m.has_sigma and not m.has_time
    np.testing.assert_array_equal(m.rows, np.arange(48) + 2)
    assert list(m.table.columns) == ["station", "point", "X", "Y", "Z", "tool_x", "tool_y",
                                     "tool_z", "length", "time", "sigma"]
    assert m.source == "<DataFrame>"
    assert m.given_columns == ("station", "point", "X", "Y", "Z", "tool_z", "length")
    with pytest.raises(ValueError):
        m.length[0] = 1.0  # read-only arrays


def test_csv_ids_are_text_and_match_dataframe(tmp_path, spec3):
    df = make_table()
    df["station"] = df["station"].map({"S1": "01", "S2": "02", "S3": "03", "S4": "4"})
    path = write(tmp_path, df)
    m = quiet_load(path, spec3)
    assert m.station_ids == ["01", "02", "03", "4"]
    assert m.source == str(path)
    m_df = quiet_load(df, spec3)
    np.testing.assert_array_equal(m.q_internal, m_df.q_internal)
    np.testing.assert_array_equal(m.length, m_df.length)
    # integer ids in a DataFrame become text too
    df2 = make_table()
    df2["point"] = np.tile(np.arange(1, 13), 4)
    assert quiet_load(df2, spec3).point_ids[:3] == ["1", "2", "3"]


def test_rotary_axes_in_degrees_become_radians(spec5):
    rng = np.random.default_rng(3)
    n = 12
    pose = pd.DataFrame({"X": rng.uniform(0, 1000, n), "Y": rng.uniform(0, 800, n),
                         "Z": rng.uniform(-600, 0, n), "C": rng.uniform(-180, 180, n),
                         "B": rng.uniform(-100, 100, n), "tool_z": np.tile([0.0, 80.0], 6)})
    df = pd.concat([pose.assign(station=s, point=[f"P{i}" for i in range(n)],
                                length=rng.uniform(500, 1500, n)) for s in "ABCD"],
                   ignore_index=True)
    m = quiet_load(df, spec5)
    assert m.axis_names == ("X", "Y", "Z", "C", "B")
    np.testing.assert_allclose(m.q_internal[:, 3], np.deg2rad(df["C"]))
    np.testing.assert_allclose(m.q_internal[:, 4], np.deg2rad(df["B"]))
    np.testing.assert_allclose(m.table["B"], df["B"])  # the table keeps file units (deg)
    # unit-suffixed synonyms of the axis columns
    m2 = quiet_load(df.rename(columns={"X": "X_mm", "B": "B_deg"}), spec5)
    np.testing.assert_array_equal(m2.q_internal, m.q_internal)


def test_unit_suffixed_synonyms(spec3):
    df = make_table()
    df["time"] = np.arange(len(df), dtype=float)[::-1]  # time order is not required
    df["sigma"] = 0.001
    df.loc[3, "sigma"] = np.nan  # per-row absent sigma is allowed
    ren = df.rename(columns={"length": "length_mm", "tool_z": "tool_z_mm", "time": "time_s",
                             "sigma": "sigma_mm"})
    m = quiet_load(ren, spec3)
    np.testing.assert_allclose(m.length, df["length"])
    np.testing.assert_allclose(m.time, df["time"])
    assert np.isnan(m.sigma[3]) and m.sigma[0] == 0.001 and m.has_sigma
    assert list(m.table.columns)[-3:] == ["length", "time", "sigma"]


def test_input_dataframe_is_not_modified(spec3):
    df = make_table()
    df["station"] = df["station"].astype(object)
    df.loc[0, "station"] = "  S1 "
    before = df.copy(deep=True)
    m = quiet_load(df, spec3)
    pd.testing.assert_frame_equal(df, before)
    assert m.table is not df
    m.table.loc[0, "X"] = -1.0
    pd.testing.assert_frame_equal(df, before)


def test_csv_file_is_not_modified_and_blank_lines_keep_row_numbers(tmp_path, spec3):
    path = write(tmp_path, make_table())
    text = path.read_text()
    lines = text.splitlines()
    lines.insert(3, "")  # a blank line becomes file row 4
    path.write_text("\n".join(lines) + "\n\n")
    before = path.read_bytes()
    m = quiet_load(path, spec3)
    assert path.read_bytes() == before
    assert m.rows[:4].tolist() == [2, 3, 5, 6]


# ---------------------------------------------------------------------------------------
# column errors


def test_misnamed_column_suggests_closest(tmp_path, spec3):
    path = write(tmp_path, make_table().rename(columns={"length": "lenght"}))
    err = error_of(path, spec3)
    msg = assert_where(err, "meas.csv", 1, "length")
    assert "missing required column 'length'" in msg
    assert "'lenght' meant to be 'length'" in msg


def test_unknown_extra_column_is_an_error_listing_allowed_names(tmp_path, spec3):
    path = write(tmp_path, make_table().assign(temperature=20.0))
    err = error_of(path, spec3)
    msg = assert_where(err, "meas.csv", 1, "temperature")
    assert "unknown column 'temperature'" in msg
    assert "allowed columns: station, point, X (X_mm)" in msg


def test_misspelled_axis_is_not_ignored(tmp_path, spec3):
    df = make_table()
    df["x"] = df["X"]  # a lower-case duplicate of an axis column
    err = error_of(write(tmp_path, df), spec3)
    msg = assert_where(err, "meas.csv", 1, "x")
    assert "did you mean 'X'" in msg


def test_axis_columns_not_matching_model(tmp_path, spec5):
    df = make_table()  # X Y Z only; the head_bc model also has C and B
    err = error_of(write(tmp_path, df), spec5)
    msg = assert_where(err, "meas.csv", 1, "C")
    assert "model 'head_bc'" in msg and "missing column(s) for C, B" in msg
    df = df.assign(A=0.0, C=0.0)  # A is no axis of the model
    msg = str(error_of(write(tmp_path, df), spec5))
    assert "missing column(s) for B" in msg and "column(s) A that the model has no axis" in msg


def test_both_forms_of_one_column(tmp_path, spec3):
    df = make_table()
    df["length_mm"] = df["length"]
    err = error_of(write(tmp_path, df), spec3)
    msg = assert_where(err, "meas.csv", 1, "length_mm")
    assert "'length' and 'length_mm' are the same quantity" in msg


def test_duplicate_header(tmp_path, spec3):
    path = tmp_path / "dup.csv"
    path.write_text("station,point,X,Y,Z,length,X\n" + "S1,P1,1,1,-1,100,1\n" * 4)
    err = error_of(path, spec3)
    msg = assert_where(err, "dup.csv", 1, "X")
    assert "appears twice (columns 3 and 7)" in msg


def test_semicolon_separated_file(tmp_path, spec3):
    path = tmp_path / "semi.csv"
    make_table().to_csv(path, index=False, sep=";")
    err = error_of(path, spec3)
    assert_where(err, "semi.csv", 1, None)
    assert "comma-separated" in str(err)


def test_empty_and_header_only_files(tmp_path, spec3):
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    assert "empty" in str(error_of(empty, spec3))
    header = tmp_path / "header.csv"
    header.write_text("station,point,X,Y,Z,length\n")
    err = error_of(header, spec3)
    assert "no data rows" in str(err) and "header.csv" in str(err)
    assert "no such" in str(error_of(tmp_path / "missing.csv", spec3))


# ---------------------------------------------------------------------------------------
# value errors


def test_non_numeric_value(tmp_path, spec3):
    df = make_table().astype({"Y": object})
    df.loc[6, "Y"] = "12,5"
    err = error_of(write(tmp_path, df), spec3)
    msg = assert_where(err, "meas.csv", 8, "Y")
    assert "expected a number (mm), got '12,5'" in msg


def test_missing_and_nan_values(tmp_path, spec3):
    df = make_table()
    df.loc[9, "length"] = np.nan
    err = error_of(write(tmp_path, df), spec3)
    msg = assert_where(err, "meas.csv", 11, "length")
    assert "missing value" in msg
    err = error_of(df, spec3, name="frame")  # NaN in a DataFrame
    assert_where(err, "frame", 11, "length")


def test_missing_id(tmp_path, spec3):
    df = make_table()
    df.loc[4, "point"] = ""
    err = error_of(write(tmp_path, df), spec3)
    msg = assert_where(err, "meas.csv", 6, "point")
    assert "missing id" in msg


def test_infinite_value(spec3):
    df = make_table()
    df.loc[2, "X"] = np.inf
    assert_where(error_of(df, spec3), "<DataFrame>", 4, "X")


def test_non_positive_length(tmp_path, spec3):
    df = make_table()
    df.loc[5, "length"] = 0.0
    err = error_of(write(tmp_path, df), spec3)
    msg = assert_where(err, "meas.csv", 7, "length")
    assert "expected a positive length in mm, got 0" in msg


def test_relative_lengths_may_be_negative(spec3):
    df = make_table()
    df["length"] = df["length"] - 1000.0
    assert np.any(df["length"] <= 0)
    m = quiet_load(df, spec3, relative_lengths=True)
    np.testing.assert_allclose(m.length, df["length"])


def test_absurd_length(tmp_path, spec3):
    df = make_table()
    df.loc[13, "length"] = 2.5e5
    err = error_of(write(tmp_path, df), spec3)
    msg = assert_where(err, "meas.csv", 15, "length")
    assert f"{MAX_LENGTH_MM:g} mm (100 m)" in msg


def test_position_outside_travel(tmp_path, spec3):
    df = make_table()
    df.loc[20, "X"] = 760.0  # travel [0, 754]
    err = error_of(write(tmp_path, df), spec3)
    msg = assert_where(err, "meas.csv", 22, "X")
    assert "outside the travel [0, 754] mm of axis X" in msg
    assert "tolerance 0.000754 mm" in msg
    # within the tolerance (1e-6 of the travel range) is accepted
    ok = make_table()
    ok.loc[ok["point"] == "P1", "Z"] = 0.0005  # Z travel [-550, 0], tolerance 0.00055
    quiet_load(ok, spec3)


def test_non_positive_sigma(tmp_path, spec3):
    df = make_table().assign(sigma=0.0005)
    df.loc[30, "sigma"] = -0.001
    err = error_of(write(tmp_path, df), spec3)
    msg = assert_where(err, "meas.csv", 32, "sigma")
    assert "expected a positive standard uncertainty" in msg


def test_several_problems_in_one_message(tmp_path, spec3):
    df = make_table().astype({"Y": object})
    df.loc[9, "length"] = -5.0
    df.loc[2, "Y"] = "abc"
    df.loc[15, "Z"] = 10.0
    err = error_of(write(tmp_path, df), spec3)
    msg = assert_where(err, "meas.csv", 4, "Y")  # the first problem in file order
    assert "2 further problem(s)" in msg
    assert "row 11, column 'length'" in msg and "row 17, column 'Z'" in msg


# ---------------------------------------------------------------------------------------
# table-level errors


def test_duplicate_rows_name_both(tmp_path, spec3):
    df = make_table()
    dup = df.iloc[[4]].assign(length=df.loc[4, "length"] + 0.001)
    df = pd.concat([df, dup], ignore_index=True)
    err = error_of(write(tmp_path, df), spec3)
    msg = assert_where(err, "meas.csv", 50, "point")
    assert "rows 6 and 50" in msg and "station 'S1', point 'P5'" in msg


def test_station_with_too_few_readings(tmp_path, spec3):
    df = make_table()
    df = pd.concat([df, make_table(n_points=3, stations=("S3",), seed=5)
                    .assign(station="S5")], ignore_index=True)
    err = error_of(write(tmp_path, df), spec3)
    msg = assert_where(err, "meas.csv", 50, "station")
    assert "station 'S5' has 3 reading(s) (row(s) 50, 51, 52)" in msg
    assert "at least 4" in msg


def test_fixed_station_needs_fewer_readings(spec3):
    df = pd.concat([make_table(), make_table(n_points=2, stations=("S3",), seed=5)
                    .assign(station="S5")], ignore_index=True)
    st = pd.DataFrame({"station": ["S5"], "x": [0.0], "y": [0.0], "z": [0.0], "fixed": [True]})
    with pytest.warns(DataWarning):
        m = load_measurements(df, spec3, stations=st)
    assert m.station_ids[-1] == "S5"


def test_stations_not_described_when_required(tmp_path, spec3):
    df = make_table()
    st_path = tmp_path / "stations.csv"
    pd.DataFrame({"station": ["S1", "S2", "S4"], "x_mm": [0.0, 1.0, 2.0], "y_mm": 0.0,
                  "z_mm": 0.0}).to_csv(st_path, index=False)
    err = error_of(write(tmp_path, df), spec3, stations=st_path, require_station_positions=True)
    msg = assert_where(err, "meas.csv", 26, "station")
    assert "station 'S3'" in msg and "describes: S1, S2, S4" in msg
    # not required: the same tables load, with warnings naming the ids that do not match
    with pytest.warns(DataWarning) as rec:
        m = load_measurements(df, spec3, stations=st_path)
    text = " | ".join(str(w.message) for w in rec)
    assert "'S3'" in text and "not described in the stations table" in text
    assert list(m.stations["station"]) == ["S1", "S2", "S4"]
    # required but no table at all
    err = error_of(df, spec3, require_station_positions=True)
    assert err.column == "station" and "no stations table" in str(err)


# ---------------------------------------------------------------------------------------
# warnings


def test_warn_coplanar_station(spec3):
    df = make_table()
    df.loc[df["station"] == "S2", "Z"] = -100.0
    df.loc[df["station"] == "S2", "tool_z"] = 0.0
    # S2 now visits other poses: give them their own point ids
    df.loc[df["station"] == "S2", "point"] = [f"Q{i}" for i in range(12)]
    with pytest.warns(DataWarning, match=r"station 'S2' .* lie in one plane"):
        load_measurements(df, spec3)


def test_warn_few_readings(spec3):
    df = make_table(n_points=6)
    with pytest.warns(DataWarning) as record:
        load_measurements(df, spec3)
    texts = [str(w.message) for w in record]
    for s in ("S1", "S2", "S3", "S4"):
        assert any(f"station '{s}' has only 6 readings (fewer than 10)" in t for t in texts)


def test_warn_constant_tool_offset(spec3):
    df = make_table(tool=False)
    with pytest.warns(DataWarning, match=r"tool offset is the same in every row .* last axis "
                                         r"of the chain \(Z: EAZ, EBZ, ECZ, and what they mix "
                                         r"with\) cannot be separated"):
        load_measurements(df, spec3)


def test_warn_point_id_with_different_poses(spec3):
    df = make_table()
    df.loc[df["station"] == "S3", "X"] += 1.0
    with pytest.warns(DataWarning, match=r"point 'P1' has different axis positions"):
        load_measurements(df, spec3)


def test_no_warning_for_good_data(spec3):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_measurements(make_table(), spec3)


# ---------------------------------------------------------------------------------------
# stations table


def test_load_stations_synonyms_and_defaults(tmp_path):
    path = tmp_path / "st.csv"
    path.write_text("station,x,y,z,dead_length,fixed\n"
                    "01,1,2,3,250.5,TRUE\n"
                    "S2,4,5,6,,no\n"
                    "S3,7,8,9,0,\n")
    st = load_stations(path)
    assert list(st.columns) == ["station", "x_mm", "y_mm", "z_mm", "dead_length_mm",
                                "dead_length_given", "fixed"]
    assert list(st["station"]) == ["01", "S2", "S3"]
    np.testing.assert_allclose(st["dead_length_mm"], [250.5, 0.0, 0.0])
    assert list(st["dead_length_given"]) == [True, False, True]
    assert list(st["fixed"]) == [True, False, False]
    # preferred unit-suffixed names, no optional columns
    st2 = load_stations(pd.DataFrame({"station": ["A"], "x_mm": [1.0], "y_mm": [2.0],
                                      "z_mm": [3.0]}))
    assert not st2["fixed"].any() and not st2["dead_length_given"].any()
    # the output is a valid input (idempotent)
    pd.testing.assert_frame_equal(load_stations(st), st)


def test_load_stations_errors(tmp_path):
    path = tmp_path / "st.csv"
    path.write_text("station,x,x_mm,y,z\nS1,1,1,2,3\n")
    err = pytest.raises(InputError, load_stations, path).value
    assert_where(err, "st.csv", 1, "x_mm")
    path.write_text("station,x,y,z\nS1,1,2,3\nS1,4,5,6\n")
    err = pytest.raises(InputError, load_stations, path).value
    msg = assert_where(err, "st.csv", 3, "station")
    assert "described twice (rows 2 and 3)" in msg
    path.write_text("station,x,y,z,fixed\nS1,1,2,3,maybe\n")
    err = pytest.raises(InputError, load_stations, path).value
    assert_where(err, "st.csv", 2, "fixed")
    path.write_text("station,x,y\nS1,1,2\n")
    err = pytest.raises(InputError, load_stations, path).value
    msg = assert_where(err, "st.csv", 1, "z_mm")
    assert "'z'" in msg  # the accepted synonym is named
    err = pytest.raises(InputError, load_stations,
                        pd.DataFrame({"station": ["S1"], "x": ["a"], "y": [0], "z": [0]}),
                        name="st").value
    assert_where(err, "st", 2, "x")
    assert re.search(r"expected a number \(mm\), got 'a'", str(err))
