"""The README's first command: ``volcal demo`` as a user runs it (a separate process, with
its plotting processes), end to end."""


def test_volcal_demo_writes_everything_and_prints_the_summary(demo_run):
    run, out = demo_run  # tests/conftest.py: the program in its own process, run once
    assert run.returncode == 0, run.stdout + run.stderr
    ident = out / "identification"
    for name in ("component_errors", "volumetric_map", "residuals", "residuals_vs_axes",
                 "correlations"):
        assert (ident / f"{name}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    assert (out / "truth_comparison.csv").is_file()
    assert "error vs simulated truth" in run.stdout and "fits (chi2/dof" in run.stdout
    # the error field against the simulated truth, as the README quotes it
    line = next(ln for ln in run.stdout.splitlines() if "error vs simulated truth" in ln)
    assert float(line.split("truth")[1].split("um")[0]) < 0.5
    # nothing left half-written beside the folder (temporary folders are renamed or removed)
    assert not list(out.parent.glob(".*tmp*"))
