"""ISO 230-2:2014 parameters against hand-computed values.

Every expected number below was worked out by hand from the readings (the derivation is in
the comments); none is produced by the code under test.
"""
import math

import numpy as np
import pandas as pd
import pytest

from volcal.iso230_2 import evaluate, iso230_2_parameters

R2, R3, R7, R10 = math.sqrt(2), math.sqrt(3), math.sqrt(7), math.sqrt(10)

# --- small data set: 3 targets x 3 cycles, deviations in um ------------------------------
# target  up readings   mean  s          down readings  mean  s
#   0 mm   1, 2, 3        2    1           -1, 0, 1       0    1
# 100 mm   4, 4, 7        5    sqrt(3)      1, 2, 6       3    sqrt(7)
# 200 mm   3, 5, 7        5    2            7, 8, 9       8    1
# (s: 4,4,7 -> dev -1,-1,2 -> (1+1+4)/2 = 3;  1,2,6 -> dev -2,-1,3 -> (4+1+9)/2 = 7)
SMALL_UP = {0.0: [1, 2, 3], 100.0: [4, 4, 7], 200.0: [3, 5, 7]}
SMALL_DOWN = {0.0: [-1, 0, 1], 100.0: [1, 2, 6], 200.0: [7, 8, 9]}

SMALL_EXPECTED_PER_TARGET = {
    "mean_up_um": [2, 5, 5],
    "mean_down_um": [0, 3, 8],
    "mean_bidir_um": [1, 4, 6.5],
    "s_up_um": [1, R3, 2],
    "s_down_um": [1, R7, 1],
    "B_um": [2, 2, -3],                         # x̄↑ - x̄↓
    "R_up_um": [4, 4 * R3, 8],                  # 4 s↑
    "R_down_um": [4, 4 * R7, 4],
    # R_i = max(2s↑ + 2s↓ + |B_i|, R_i↑, R_i↓):
    #   0: max(2+2+2, 4, 4) = 6;  100: max(2√3+2√7+2, 4√3, 4√7) = 2+2√3+2√7 = 10.7556;
    # 200: max(4+2+3, 8, 4) = 9
    "R_bidir_um": [6, 2 + 2 * R3 + 2 * R7, 9],
}
SMALL_EXPECTED_AXIS = {
    "B_um": 3.0,                                # max |B_i| = |-3|
    "B_mean_um": 1.0 / 3.0,                     # (2 + 2 - 3) / 3
    "R_up_um": 8.0,                             # max(4, 4√3, 8)
    "R_down_um": 4 * R7,                        # max(4, 4√7, 4) = 10.583
    "R_bidir_um": 2 + 2 * R3 + 2 * R7,          # 10.7556
    "E_up_um": 3.0,                             # 5 - 2
    "E_down_um": 8.0,                           # 8 - 0
    "E_bidir_um": 8.0,                          # max(2,5,5,0,3,8) - min(...) = 8 - 0
    "M_um": 5.5,                                # 6.5 - 1
    # A↑ = max(2+2, 5+2√3, 5+4) - min(2-2, 5-2√3, 5-4) = 9 - 0
    "A_up_um": 9.0,
    # A↓ = max(0+2, 3+2√7, 8+2) - min(0-2, 3-2√7, 8-2) = 10 - (3 - 2√7) = 7 + 2√7
    "A_down_um": 7 + 2 * R7,
    # A = max(9, 10) - min(0, 3 - 2√7) = 7 + 2√7
    "A_bidir_um": 7 + 2 * R7,
}


def small_frame(shuffle_runs=False):
    rows = []
    for c in range(3):
        rows += [("X", t, c + 1, "+", SMALL_UP[t][c]) for t in (0.0, 100.0, 200.0)]
        rows += [("X", t, c + 1, "-", SMALL_DOWN[t][c]) for t in (200.0, 100.0, 0.0)]
    df = pd.DataFrame(rows, columns=["axis", "target_mm", "cycle", "direction", "deviation_um"])
    if shuffle_runs:   # runs (cycle x direction) in another order, each run kept intact
        df = pd.concat([df.iloc[15:18], df.iloc[0:3], df.iloc[9:15], df.iloc[3:9]],
                       ignore_index=True)
    return df


@pytest.fixture(scope="module")
def small_result():
    return evaluate(small_frame(), type_a="paper", degree=2)


def test_small_dataset_every_axis_parameter(small_result):
    table = small_result.parameters_table().set_index("name")
    for name, value in SMALL_EXPECTED_AXIS.items():
        assert table.loc[name, "value"] == pytest.approx(value, abs=1e-12), name
        assert table.loc[name, "unit"] == "um"


def test_small_dataset_every_per_target_value(small_result):
    t = small_result.targets_table()
    assert list(t["target_mm"]) == [0.0, 100.0, 200.0]
    for col, values in SMALL_EXPECTED_PER_TARGET.items():
        np.testing.assert_allclose(t[col].to_numpy(), values, rtol=0, atol=1e-12, err_msg=col)


def test_small_dataset_row_order_of_runs_does_not_matter():
    a = evaluate(small_frame(), type_a="paper", degree=2).parameters_table()
    b = evaluate(small_frame(shuffle_runs=True), type_a="paper", degree=2).parameters_table()
    np.testing.assert_allclose(a["value"].to_numpy(), b["value"].to_numpy(), atol=1e-12)


def test_small_dataset_actual_position_form_gives_the_same():
    df = small_frame()
    actual = df.assign(actual_mm=df["target_mm"] + df["deviation_um"] * 1e-3 + 0.0)
    actual = actual.drop(columns=["deviation_um"])
    res = evaluate(actual, type_a="paper", degree=2).parameters_table().set_index("name")
    for name, value in SMALL_EXPECTED_AXIS.items():
        assert res.loc[name, "value"] == pytest.approx(value, abs=1e-9), name


# --- asymmetric data where the usual mistakes change the result --------------------------
# patterns (deviation from the mean, n = 5):
#   P4 = (-4,-2,0,2,4): s = sqrt(40/4) = √10;  P1 = (-1,0,0,0,1): s = sqrt(2/4) = 1/√2;
#   P2 = (-2,-1,0,1,2): s = sqrt(10/4) = √10/2
P4 = np.array([-4, -2, 0, 2, 4.0])
P1 = np.array([-1, 0, 0, 0, 1.0])
P2 = np.array([-2, -1, 0, 1, 2.0])
# target 0: up  0 + P4, down -3 + P1   -> B_0 =  3, one direction scatters, B small
# target 1: up  9 + P1, down  6 + P1   -> B_1 =  3
# target 2: up -1 + P2, down  8 + P2   -> B_2 = -9 (largest |B_i| is negative)
ASYM_UP = np.vstack([0 + P4, 9 + P1, -1 + P2])
ASYM_DOWN = np.vstack([-3 + P1, 6 + P1, 8 + P2])


def test_asymmetric_means_are_over_cycles_and_s_uses_n_minus_1():
    p = iso230_2_parameters(ASYM_UP, ASYM_DOWN)
    np.testing.assert_allclose(p.mean_up, [0, 9, -1], atol=1e-12)
    np.testing.assert_allclose(p.mean_down, [-3, 6, 8], atol=1e-12)
    np.testing.assert_allclose(p.s_up, [R10, 1 / R2, R10 / 2], atol=1e-12)
    np.testing.assert_allclose(p.s_down, [1 / R2, 1 / R2, R10 / 2], atol=1e-12)
    # mistake: 1/n instead of 1/(n-1) -> s_0↑ = sqrt(40/5) = 2.828
    assert p.s_up[0] != pytest.approx(math.sqrt(8.0))
    # mistake: the mean of all 2n readings at a target is not a directional mean
    assert p.mean_up[2] != pytest.approx(np.mean([*ASYM_UP[2], *ASYM_DOWN[2]]))


def test_asymmetric_bidirectional_repeatability_takes_the_max():
    p = iso230_2_parameters(ASYM_UP, ASYM_DOWN)
    # target 0: 2√10 + √2 + 3 = 10.739 < R_0↑ = 4√10 = 12.649  -> R_0 = 4√10
    # target 1: √2 + √2 + 3 = 5.828;  target 2: √10 + √10 + 9 = 15.325
    np.testing.assert_allclose(p.R_i, [4 * R10, 2 * R2 + 3, 2 * R10 + 9], atol=1e-12)
    assert p.R == pytest.approx(2 * R10 + 9, abs=1e-12)
    assert p.R_up == pytest.approx(4 * R10, abs=1e-12)          # max(4√10, 2√2, 2√10)
    assert p.R_down == pytest.approx(2 * R10, abs=1e-12)        # max(2√2, 2√2, 2√10)
    # mistake 1: only 2s↑ + 2s↓ + |B_i| (no max with R_i↑, R_i↓) -> 10.739 at target 0
    assert p.R_i[0] != pytest.approx(2 * R10 + R2 + 3)
    # mistake 2: 4 s of the 2n readings of both directions pooled -> 4 * 4.85 at target 2
    pooled = 4 * np.std(np.r_[ASYM_UP[2], ASYM_DOWN[2]], ddof=1)
    assert p.R_i[2] != pytest.approx(pooled)
    # mistake 3: R = max(R↑, R↓) = 4√10
    assert p.R != pytest.approx(max(p.R_up, p.R_down))


def test_asymmetric_systematic_deviation_uses_extremes_over_both_directions():
    p = iso230_2_parameters(ASYM_UP, ASYM_DOWN)
    # means ↑ (0, 9, -1), ↓ (-3, 6, 8): overall max 9 (↑, target 1), min -3 (↓, target 0)
    assert p.E_up == pytest.approx(10.0)          # 9 - (-1)
    assert p.E_down == pytest.approx(11.0)        # 8 - (-3)
    assert p.E == pytest.approx(12.0)             # 9 - (-3)
    assert p.M == pytest.approx(9.0)              # bidir means (-1.5, 7.5, 3.5)
    # mistakes: E = max(E↑, E↓) = 11, or E = M = 9
    assert p.E != pytest.approx(max(p.E_up, p.E_down))
    assert p.E != pytest.approx(p.M)


def test_asymmetric_reversal_value_is_max_abs_and_mean_is_signed():
    p = iso230_2_parameters(ASYM_UP, ASYM_DOWN)
    np.testing.assert_allclose(p.B_i, [3, 3, -9], atol=1e-12)
    assert p.B == pytest.approx(9.0)              # max |B_i|, from a negative B_i
    assert p.B_mean == pytest.approx(-1.0)        # (3 + 3 - 9) / 3
    assert p.B != pytest.approx(p.B_i.max())      # mistake: max B_i without |.| = 3
    assert p.B_mean != pytest.approx(np.abs(p.B_i).mean())   # mistake: mean |B_i| = 5


def test_asymmetric_accuracy_uses_extremes_over_both_directions():
    p = iso230_2_parameters(ASYM_UP, ASYM_DOWN)
    # ↑: x̄+2s = (2√10, 9+√2, -1+√10) -> max 9+√2;  x̄-2s = (-2√10, 9-√2, -1-√10) -> min -2√10
    assert p.A_up == pytest.approx(9 + R2 + 2 * R10, abs=1e-12)        # 16.739
    # ↓: x̄+2s = (-3+√2, 6+√2, 8+√10) -> max 8+√10; x̄-2s = (-3-√2, 6-√2, 8-√10) -> min -3-√2
    assert p.A_down == pytest.approx(11 + R10 + R2, abs=1e-12)         # 15.576
    # A: max 8+√10 (↓, target 2) - min -2√10 (↑, target 0) = 8 + 3√10
    assert p.A == pytest.approx(8 + 3 * R10, abs=1e-12)                # 17.487
    assert p.A != pytest.approx(max(p.A_up, p.A_down))                  # mistake: 16.739


def test_parameters_reject_bad_shapes():
    with pytest.raises(ValueError):
        iso230_2_parameters(np.zeros((3, 5)), np.zeros((3, 4)))
    with pytest.raises(ValueError):
        iso230_2_parameters(np.zeros((3, 1)), np.zeros((3, 1)))
