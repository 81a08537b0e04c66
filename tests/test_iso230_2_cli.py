"""``volcal iso230-2`` and ``write_report``: files, units, consistency, all-or-nothing output."""
import argparse
import hashlib
import math

import numpy as np
import pandas as pd
import pytest

from volcal.base.exceptions import InputError
from volcal.iso230_2 import OUTPUT_FILES, evaluate, example_path, write_report
from volcal.iso230_2 import report as report_module
from volcal.iso230_2.cli import add_parser


def run_cli(argv):
    """The command as `volcal` runs it (``--force`` as the command line's output policy)."""
    from volcal.base.folders import output_policy
    force = "--force" in argv
    parser = argparse.ArgumentParser(prog="volcal")
    parser.add_argument("-q", "--quiet", action="store_true")
    add_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args([a for a in argv if a != "--force"])
    with output_policy(force):
        return args.func(args)


@pytest.fixture(scope="module")
def example_out(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "res"
    assert run_cli(["iso230-2", str(example_path()), "--out", str(out), "--mpe-um", "0.5",
                    "--spacing-mm", "25"]) == 0
    return out


def test_cli_writes_every_file_and_prints_where(tmp_path, capsys):
    out = tmp_path / "r"
    assert run_cli(["iso230-2", "--example", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == sorted([*OUTPUT_FILES, "manifest.json"])
    printed = capsys.readouterr().out
    assert str(out) in printed and "E = " in printed
    assert (out / "iso230_2.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]   # no temp left


def test_parameters_match_an_independent_groupby(example_out):
    raw = pd.read_csv(example_path())
    g = raw.groupby(["target_mm", "direction"])["deviation_um"]
    mean, sd = g.mean().unstack(), g.std(ddof=1).unstack()
    params = pd.read_csv(example_out / "parameters.csv").set_index("name")
    assert params.loc["E_bidir_um", "unit"] == "um"
    E = mean.to_numpy().max() - mean.to_numpy().min()
    A = (mean + 2 * sd).to_numpy().max() - (mean - 2 * sd).to_numpy().min()
    B = (mean["+"] - mean["-"]).abs().max()
    R = np.maximum.reduce([2 * sd["+"] + 2 * sd["-"] + (mean["+"] - mean["-"]).abs(),
                           4 * sd["+"], 4 * sd["-"]]).max()
    for name, value in (("E_bidir_um", E), ("A_bidir_um", A), ("B_um", B), ("R_bidir_um", R)):
        assert params.loc[name, "value"] == pytest.approx(value, rel=1e-12), name
    assert params.loc["u_instrument_um", "value"] == pytest.approx(0.5 / math.sqrt(3))


def test_correction_table_is_minus_the_polynomial_and_its_uncertainty(example_out):
    table = pd.read_csv(example_out / "correction_table.csv")
    poly = pd.read_csv(example_out / "polynomial.csv")
    pos = table["position_mm"].to_numpy()
    assert pos[0] == 0.0 and pos[-1] == 750.0
    np.testing.assert_allclose(np.diff(pos), 25.0)
    for lab, sym in (("up", "+"), ("down", "-"), ("bidir", "bidir")):
        rows = poly[poly["direction"] == sym].sort_values("power")
        a = rows["value"].to_numpy()
        C = rows[[f"cov_a{l}" for l in range(4)]].to_numpy()
        g = pos[:, None] ** np.arange(4)
        np.testing.assert_allclose(table[f"deviation_{lab}_um"], g @ a, rtol=1e-6, atol=1e-6)
        np.testing.assert_array_equal(table[f"correction_{lab}_um"],
                                      -table[f"deviation_{lab}_um"])
        U = 2.0 * np.sqrt(np.einsum("ij,jk,ik->i", g, C, g))
        np.testing.assert_allclose(table[f"U_{lab}_um"], U, rtol=1e-5)
    assert list(rows["unit"]) == ["um", "um/mm", "um/mm^2", "um/mm^3"]


def test_report_markdown_and_targets(example_out):
    md = (example_out / "report.md").read_text(encoding="utf-8")
    for needle in ("E_bidir_um", "A_bidir_um", "R_bidir_um", "B_mean_um", "iso230_2.png",
                   "correction", "MPE / sqrt(3)"):
        assert needle in md
    t = pd.read_csv(example_out / "targets.csv")
    assert len(t) == 11
    assert {"target_mm", "mean_up_um", "s_down_um", "R_bidir_um", "B_um"} <= set(t.columns)


def test_python_api_mirrors_the_cli(example_out, tmp_path):
    res = evaluate(example_path(), mpe_um=0.5)
    out = write_report(res, tmp_path / "api", spacing_mm=25)
    for name in ("parameters.csv", "targets.csv", "polynomial.csv", "correction_table.csv"):
        pd.testing.assert_frame_equal(pd.read_csv(out / name), pd.read_csv(example_out / name))


def test_bad_input_is_an_input_error_and_writes_nothing(tmp_path):
    lines = example_path().read_text().splitlines()
    lines[6] = lines[6].replace(",+,", ",sideways,")
    data = tmp_path / "bad.csv"
    data.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    with pytest.raises(InputError) as info:
        run_cli(["iso230-2", str(data), "--out", str(out)])
    assert info.value.row == 7 and info.value.column == "direction"
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.csv"]


def test_main_prints_the_error_and_exits_2(tmp_path, capsys, monkeypatch):
    import volcal.cli.main
    # only this command: the others are written elsewhere and need not exist here
    monkeypatch.setattr(volcal.cli.main, "_COMMANDS", ["volcal.iso230_2.cli"])
    main = volcal.cli.main.main
    data = tmp_path / "bad.csv"
    data.write_text("axis,target_mm,cycle,direction,deviation_um,actual_mm\nX,0,1,+,1,0\n")
    assert main(["iso230-2", str(data), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "mixed units" in err and "row 1" in err


def test_options_are_validated(tmp_path):
    for argv in (["--k", "0"], ["--mpe-um", "-1"], ["--degree", "-1"], ["--spacing-mm", "0"],
                 ["--degree", "11"]):
        with pytest.raises(InputError):
            run_cli(["iso230-2", "--example", "--out", str(tmp_path / "o"), *argv])
    assert not (tmp_path / "o").exists()


def test_existing_folder_with_other_files_is_refused_and_untouched(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    with pytest.raises(InputError) as info:
        run_cli(["iso230-2", "--example", "--out", str(out)])
    assert "notes.txt" in str(info.value)
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


def test_earlier_result_is_replaced_and_input_not_modified(tmp_path):
    data = tmp_path / "in.csv"
    data.write_bytes(example_path().read_bytes())
    digest = hashlib.sha256(data.read_bytes()).hexdigest()
    out = tmp_path / "res"
    assert run_cli(["iso230-2", str(data), "--out", str(out), "--degree", "2"]) == 0
    with pytest.raises(InputError, match="--force"):
        run_cli(["iso230-2", str(data), "--out", str(out), "--degree", "3"])
    assert run_cli(["iso230-2", str(data), "--out", str(out), "--degree", "3", "--force"]) == 0
    poly = pd.read_csv(out / "polynomial.csv")
    assert set(poly["coefficient"]) == {"a0", "a1", "a2", "a3"}
    assert hashlib.sha256(data.read_bytes()).hexdigest() == digest
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.csv", "res"]


def test_failure_while_writing_leaves_nothing(tmp_path, monkeypatch):
    def boom(*args, **kwargs):
        raise RuntimeError("disk full")
    monkeypatch.setattr(report_module, "plot", boom)
    with pytest.raises(RuntimeError):
        write_report(evaluate(example_path()), tmp_path / "res")
    assert list(tmp_path.iterdir()) == []


def test_plane_cli(tmp_path):
    """Two-axis model (eq. 13) from a plane table; noise-free plus a known repeat scatter."""
    rng = np.random.default_rng(7)
    rows = []
    for p in np.linspace(0, 600, 5):
        for r in np.linspace(0, 400, 4):
            true = 1.0 + 4e-3 * p - 5e-6 * p ** 2 + 2e-3 * r + 1e-9 * r ** 3       # um
            for c in range(1, 6):
                rows.append((p, r, c, round(true + rng.normal(0, 0.3), 3)))
    data = tmp_path / "plane.csv"
    pd.DataFrame(rows, columns=["p_mm", "r_mm", "cycle", "deviation_um"]).to_csv(data,
                                                                               index=False)
    out = tmp_path / "plane_out"
    assert run_cli(["iso230-2", str(data), "--plane", "--out", str(out), "--mpe-um", "0.3",
                    "--spacing-mm", "100"]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(["plane_parameters.csv", "plane_polynomial.csv", "plane_grid.csv",
                            "plane_means.csv", "report.md", "plane.png", "manifest.json"])
    grid = pd.read_csv(out / "plane_grid.csv")
    assert len(grid) == 7 * 5
    np.testing.assert_array_equal(grid["correction_um"], -grid["deviation_um"])
    true = (1.0 + 4e-3 * grid.p_mm - 5e-6 * grid.p_mm ** 2 + 2e-3 * grid.r_mm
            + 1e-9 * grid.r_mm ** 3)
    # the truth lies within a few expanded uncertainties of the fit everywhere
    assert np.all(np.abs(grid["deviation_um"] - true) < 2.5 * grid["U_um"])
    poly = pd.read_csv(out / "plane_polynomial.csv")
    assert list(poly["coefficient"]) == ["a0", "p1", "p2", "p3", "r1", "r2", "r3"]


def test_identical_readings_need_a_resolution_floor():
    df = pd.read_csv(example_path())
    sel = (df.target_mm == 300.681) & (df.direction == "-")
    df.loc[sel, "deviation_um"] = 2.0                     # s_i = 0 at one target
    with pytest.raises(InputError) as info:
        evaluate(df)
    assert "--resolution-um" in str(info.value) and "300.681" in str(info.value)
    res = evaluate(df, resolution_um=0.1)
    u = res["X"].model.u_means[1]
    i = int(np.argmin(np.abs(res["X"].readings.targets - 300.681)))
    assert u[i] == pytest.approx(0.1e-3 / math.sqrt(12))  # floor r / sqrt(12), in mm
