"""Validation of ISO 230-2 readings: clear errors naming file, row and column."""
import math

import numpy as np
import pandas as pd
import pytest

from volcal.base.exceptions import InputError
from volcal.iso230_2 import evaluate, example_path, load_readings


@pytest.fixture(scope="module")
def example_lines():
    return example_path().read_text(encoding="utf-8").splitlines()


def write(tmp_path, lines, name="data.csv"):
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def error_of(path_or_df):
    with pytest.raises(InputError) as info:
        load_readings(path_or_df)
    return info.value


def test_example_loads_as_documented(example_lines):
    (ax,) = load_readings(example_path())
    assert ax.axis == "X" and ax.units.kind == "linear"
    assert ax.m == 11 and ax.n == 5
    assert ax.targets[0] == 0.0 and ax.targets[-1] == 750.0
    # row 2 of the file: X, 0.000, cycle 1, +, 2.9 um  -> internal mm
    assert example_lines[1] == "X,0.000,1,+,2.9"
    assert ax.up[0, 0] == pytest.approx(2.9e-3)


def test_missing_cycle(tmp_path, example_lines):
    lines = [example_lines[0]] + [ln for ln in example_lines[1:] if ln.split(",")[2] != "3"]
    err = error_of(write(tmp_path, lines))
    assert "missing cycle(s) 3" in str(err) and err.column == "cycle"
    assert str(tmp_path / "data.csv") in str(err)


def test_unequal_cycle_counts(tmp_path, example_lines):
    lines = [example_lines[0]] + [ln for ln in example_lines[1:]
                                  if not (ln.split(",")[2] == "5" and ln.split(",")[3] == "-")]
    err = error_of(write(tmp_path, lines))
    assert "unequal cycle counts" in str(err)
    assert "'+' has 5 cycles" in str(err) and "'-' has 4" in str(err)


def test_targets_out_of_order_names_the_row(tmp_path, example_lines):
    lines = list(example_lines)
    lines[3], lines[4] = lines[4], lines[3]       # rows 4 and 5: 150.893 and 225.274 swapped
    err = error_of(write(tmp_path, lines))
    assert "targets out of order" in str(err)
    assert err.row == 5 and err.column == "target_mm"
    assert "row 5" in str(err) and "column 'target_mm'" in str(err)


@pytest.mark.parametrize("extra, header_of_extra", [
    ("actual_mm", "actual_mm"), ("target_deg", "target_deg")])
def test_mixed_units_two_forms(tmp_path, example_lines, extra, header_of_extra):
    lines = [example_lines[0] + f",{extra}"] + [ln + ",1.0" for ln in example_lines[1:]]
    err = error_of(write(tmp_path, lines))
    assert "mixed units" in str(err) and err.row == 1
    assert header_of_extra in str(err)


def test_mixed_units_linear_target_with_rotary_value(tmp_path, example_lines):
    lines = [example_lines[0].replace("deviation_um", "deviation_arcsec")] + example_lines[1:]
    err = error_of(write(tmp_path, lines))
    assert "mixed units" in str(err) and err.column == "deviation_arcsec"


@pytest.mark.parametrize("cell, column, expect", [
    (4, "deviation_um", "'abc' is not a number"),
    (4, "", "empty cell"),
    (3, "left", "'left' is not a direction"),
    (2, "2.5", "not a cycle number"),
])
def test_bad_cell_names_row_and_column(tmp_path, example_lines, cell, column, expect):
    lines = list(example_lines)
    fields = lines[6].split(",")                  # row 7 of the file
    fields[cell] = {"deviation_um": "abc"}.get(column, column)
    lines[6] = ",".join(fields)
    err = error_of(write(tmp_path, lines))
    assert expect in str(err)
    assert err.row == 7
    assert err.column == ["axis", "target_mm", "cycle", "direction", "deviation_um"][cell]


def test_missing_reading_names_target_and_run(tmp_path, example_lines):
    lines = list(example_lines)
    del lines[36]                                 # row 37: a '-' reading of cycle 2
    removed = example_lines[36].split(",")
    assert removed[2:4] == ["2", "-"]
    err = error_of(write(tmp_path, lines))
    assert f"no reading at target {float(removed[1]):g} mm" in str(err)
    assert "cycle 2 '-'" in str(err)


def test_duplicate_reading_names_second_row(tmp_path, example_lines):
    lines = example_lines[:4] + [example_lines[3]] + example_lines[4:]
    err = error_of(write(tmp_path, lines))
    assert "second reading" in str(err) and err.row == 5 and "first at row 4" in str(err)


def test_typo_target_points_at_its_row(tmp_path, example_lines):
    lines = list(example_lines)
    lines[5] = lines[5].replace("300.681", "300.861")       # row 6, cycle 1 '+'
    err = error_of(write(tmp_path, lines))
    assert "300.861" in str(err) and err.row == 6 and err.column == "target_mm"


def test_missing_and_unitless_columns(tmp_path, example_lines):
    err = error_of(write(tmp_path, [example_lines[0].replace("cycle", "run")]
                         + example_lines[1:]))
    assert "missing column 'cycle'" in str(err)
    err = error_of(write(tmp_path, [example_lines[0].replace("target_mm", "target")]
                         + example_lines[1:]))
    assert "missing target column" in str(err) and "'target' has no unit" in str(err)


def test_one_direction_only(tmp_path, example_lines):
    lines = [example_lines[0]] + [ln for ln in example_lines[1:] if ln.split(",")[3] == "+"]
    err = error_of(write(tmp_path, lines))
    assert "only in direction '+'" in str(err)


def test_empty_and_header_only(tmp_path, example_lines):
    assert "empty" in str(error_of(write(tmp_path, [""])))
    assert "no readings" in str(error_of(write(tmp_path, [example_lines[0]])))
    with pytest.raises(FileNotFoundError):
        load_readings(tmp_path / "nope.csv")


def test_header_case_blanks_bom_and_direction_words(tmp_path, example_lines):
    header = " Axis , Target_mm ,CYCLE, direction ,Deviation_UM"
    body = [ln.replace(",+,", ",up,").replace(",-,", ",down,") for ln in example_lines[1:]]
    path = tmp_path / "bom.csv"
    path.write_text("\ufeff" + "\n".join([header] + body) + "\n", encoding="utf-8")
    (a,) = load_readings(path)
    (b,) = load_readings(example_path())
    np.testing.assert_array_equal(a.up, b.up)
    np.testing.assert_array_equal(a.down, b.down)


def test_dataframe_rows_are_numbered_as_in_a_saved_csv():
    df = pd.read_csv(example_path())
    df.loc[10, "deviation_um"] = np.nan
    with pytest.raises(InputError) as info:
        load_readings(df)
    assert info.value.row == 12 and "<DataFrame>" in str(info.value)


def test_rotary_axis_actual_degrees_wraps_at_360():
    # targets 0, 90, 180, 270 deg; readings slightly off, the one at 0 deg read as 359.999 deg
    rows = []
    dev_arcsec = {0.0: -3.6, 90.0: 1.8, 180.0: 0.0, 270.0: 7.2}
    for c in (1, 2):
        for d, order in (("+", [0.0, 90.0, 180.0, 270.0]), ("-", [270.0, 180.0, 90.0, 0.0])):
            for t in order:
                dev = dev_arcsec[t] + (0.36 if c == 2 else 0.0)
                actual = (t + dev / 3600.0) % 360.0
                rows.append(("C", t, c, d, actual))
    df = pd.DataFrame(rows, columns=["axis", "target_deg", "cycle", "direction", "actual_deg"])
    (ax,) = load_readings(df)
    assert ax.units.kind == "rotary"
    np.testing.assert_allclose(ax.targets, np.deg2rad([0, 90, 180, 270]))
    # internal rad; -3.6 arcsec at 0 deg although the reading was 359.999 deg
    np.testing.assert_allclose(ax.up[:, 0] * 180 / math.pi * 3600, [-3.6, 1.8, 0.0, 7.2],
                               atol=1e-6)
    res = evaluate(df, degree=2, type_a="paper")
    names = set(res.parameters_table()["name"])
    assert {"E_bidir_arcsec", "A_bidir_arcsec", "first_target_deg"} <= names
    assert "target_deg" in res.targets_table().columns


def test_several_axes_evaluated_each_on_its_own(tmp_path, example_lines):
    other = [ln.replace("X,", "Y,", 1) for ln in example_lines[1:]]
    other = [",".join(f[:4] + [f"{float(f[4]) * 2:.1f}"]) for f in (ln.split(",") for ln in other)]
    both = write(tmp_path, example_lines + other, "both.csv")
    only_y = write(tmp_path, [example_lines[0]] + other, "y.csv")
    res = evaluate(both)
    assert [a.axis for a in res.axes] == ["X", "Y"]
    ref_x = evaluate(example_path()).parameters_table()
    ref_y = evaluate(only_y).parameters_table()
    got = res.parameters_table()
    np.testing.assert_allclose(got[got.axis == "X"]["value"].to_numpy(), ref_x["value"].to_numpy())
    np.testing.assert_allclose(got[got.axis == "Y"]["value"].to_numpy(), ref_y["value"].to_numpy())
    # doubling every deviation doubles E
    e = got.set_index(["axis", "name"])["value"]
    assert e[("Y", "E_bidir_um")] == pytest.approx(2 * e[("X", "E_bidir_um")], abs=0.11)


def test_input_dataframe_is_not_modified():
    df = pd.read_csv(example_path())
    before = df.copy(deep=True)
    evaluate(df)
    pd.testing.assert_frame_equal(df, before)


def test_blank_lines_count_as_rows_and_field_counts_are_checked(tmp_path, example_lines):
    lines = example_lines[:3] + [""] + example_lines[3:]
    lines[6] = lines[6].replace("4.3", "x")                  # row 7 after the blank row 4
    err = error_of(write(tmp_path, lines))
    assert err.row == 7 and err.column == "deviation_um"
    lines = list(example_lines)
    lines[8] = lines[8] + ",9"
    err = error_of(write(tmp_path, lines))
    assert err.row == 9 and "6 fields, but the header has 5" in str(err)
