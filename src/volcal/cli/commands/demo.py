"""``volcal demo``: the main job on the bundled example, end to end.

Simulate the MCV 754 example (paper 000's machine and stations, paper 002's budget),
identify it, compare with the simulated truth, write the report and plots, print a summary.
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)


@dataclass
class DemoSummary:
    """Figures of a demo run (um unless named otherwise)."""

    out_dir: Path
    status: str
    max_volumetric_um: float
    grid_axes: list[str]
    adequacy: str
    residual_rms_um: float
    field_error_rms_um: float
    field_error_max_um: float
    within_2u_fraction: float
    unidentifiable: list[str]
    seconds: float
    n_readings: int


DEMO_FILES = ("truth_comparison.csv",)
DEMO_DIRS = ("simulation", "identification")


def run_demo(
    out_dir: str | Path = "volcal-demo",
    *,
    seed: int | None = None,
    strategy: str = "joint",
    example_name: str = "mcv754",
    plots: bool = True,
    plotter=None,
) -> DemoSummary:
    """Simulate the bundled example, identify it, analyse it and write everything to
    ``out_dir`` (``simulation/``, ``identification/``, ``truth_comparison.csv``);
    ``plotter``: a :class:`volcal.outputs.plot_process.PlotProcess` that draws the plots
    (else they are drawn here)."""
    # numpy here, not at the top: `volcal --help` imports every command's module
    import numpy as np

    from volcal.analysis.identify import rigid_fit
    from volcal.base.folders import check_out_dir, write_folder
    from volcal.measurement.simulate import example, save_simulation
    from volcal.outputs.results import save_result
    from volcal.workflow.dispatch import identify

    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    # before any computing: the folder must be new, empty or an earlier demo
    check_out_dir(
        out_dir, DEMO_FILES, "volcal demo", "truth_comparison.csv", allowed_dirs=DEMO_DIRS
    )
    ex = example(example_name)
    log.info("simulating %s (%s)", ex.name, ex.description)
    sim = ex.simulate(seed)
    log.info("identifying %d readings (strategy %s)", len(sim.measurements), strategy)
    res = identify(
        ex.machine,
        sim.measurements,
        strategy=strategy,
        budget=ex.budget,
        error_model=ex.error_model,
    )

    # identification error against the simulated truth, on the workspace grid, tool 0;
    # the rigid motion between station and machine frame is invisible to any
    # multilateration and is removed first
    # the summary grid spans the rotary axes' travel too (a model without rotary axes:
    # the 7 x 7 x 7 grid over the linear axes)
    from volcal.measurement.plans import summary_grid

    grid = summary_grid(ex.machine.spec, 7)
    q = ex.machine.axis_to_internal(grid.to_numpy(float))
    pred = res.predict(q)
    _, true_dp, _ = ex.machine.evaluate(
        q, np.zeros(3), ex.error_model.values(q, ex.theta_true), exact=True
    )
    p0, _, _ = ex.machine.evaluate(q, np.zeros(3), np.zeros(ex.machine.n_errors))
    diff = pred[["dx_um", "dy_um", "dz_um"]].to_numpy() - true_dp * 1e3
    _, diff_r = rigid_fit(p0, diff)
    u = pred[["u_dx_um", "u_dy_um", "u_dz_um"]].to_numpy()
    within = float(np.mean(np.abs(diff_r) <= 2 * u))
    table = grid.copy()
    table[["true_dx_um", "true_dy_um", "true_dz_um"]] = true_dp * 1e3
    table[["dx_um", "dy_um", "dz_um"]] = pred[["dx_um", "dy_um", "dz_um"]].to_numpy()
    table[["err_dx_um", "err_dy_um", "err_dz_um"]] = diff_r
    table[["u_dx_um", "u_dy_um", "u_dz_um"]] = u

    def writer(tmp: Path) -> None:
        save_simulation(sim, tmp / "simulation", force=True)
        save_result(
            res,
            tmp / "identification",
            data_name="simulation/measurements.csv",
            plots=plots,
            force=True,
            plotter=plotter,
        )
        table.to_csv(tmp / "truth_comparison.csv", index=False)

    # one folder written as a whole: a demo interrupted while writing leaves nothing
    write_folder(
        out_dir,
        DEMO_FILES,
        "volcal demo",
        writer,
        marker="truth_comparison.csv",
        allowed_dirs=DEMO_DIRS,
    )
    names = np.asarray(res.error_model.param_names)[~res.identifiable].tolist()
    return DemoSummary(
        out_dir=out_dir.resolve(),
        status=res.status,
        max_volumetric_um=float(np.max(np.linalg.norm(pred[["dx_um", "dy_um", "dz_um"]], axis=1))),
        grid_axes=[a for a in ex.machine.axis_names if grid[a].nunique() > 1],
        adequacy=_adequacy_line(res),
        residual_rms_um=res.residual_rms_um,
        field_error_rms_um=float(np.sqrt(np.mean(np.sum(diff_r**2, axis=1)))),
        field_error_max_um=float(np.max(np.linalg.norm(diff_r, axis=1))),
        within_2u_fraction=within,
        unidentifiable=names,
        seconds=time.perf_counter() - t0,
        n_readings=len(sim.measurements),
    )


def _adequacy_line(res) -> str:
    from volcal.analysis.adequacy import assess

    return assess(res).summary


def _handler(args: argparse.Namespace) -> int:
    from volcal.outputs.plot_process import plotting

    # as volcal identify: plotting children that import matplotlib meanwhile
    with plotting(not args.no_plots) as plotter:
        s = run_demo(
            args.out,
            seed=args.seed,
            strategy=args.strategy,
            plots=not args.no_plots,
            plotter=plotter,
        )
    if not args.quiet:
        print(f"volcal demo: MCV 754 example, {s.n_readings} simulated length readings")
        print(f"  solver status            {s.status}")
        print(
            f"  largest volumetric error {s.max_volumetric_um:.1f} um (workspace grid over "
            f"{', '.join(s.grid_axes)}, tool offset (0, 0, 0) mm)"
        )
        print(f"  residual RMS             {s.residual_rms_um:.3f} um")
        print(f"  model adequacy           {s.adequacy}")
        print(
            f"  error vs simulated truth {s.field_error_rms_um:.3f} um RMS, "
            f"{s.field_error_max_um:.3f} um max (rigid motion removed); "
            f"{100 * s.within_2u_fraction:.0f} % of components within 2 u"
        )
        print("  unidentifiable           " + (", ".join(s.unidentifiable) or "none"))
        print(f"  time                     {s.seconds:.1f} s (simulating, identifying, writing)")
        print(f"  report                   {s.out_dir / 'identification' / 'report.md'}")
        print(f"  files                    {s.out_dir}")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser(
        "demo", help="simulate, identify and analyse the bundled example", description=__doc__
    )
    p.add_argument("--out", default="volcal-demo", help="output folder (default ./volcal-demo)")
    p.add_argument(
        "--seed", type=int, default=None, help="simulation seed (default: the example's own)"
    )
    p.add_argument(
        "--strategy", default="joint", choices=["joint", "two-phase", "points-only", "classic"]
    )
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.set_defaults(func=_handler)
