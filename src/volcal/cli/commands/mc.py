"""``volcal mc``: Monte Carlo uncertainty of an identification (GUM Supplement 1).

Examples::

    volcal mc --example mcv754 --trials 10000 --seed 1 --out mc/
    volcal mc --example mcv754 --trials 10000 --mode linear --out mc_lin/
    volcal mc --model mcv754_wxyzt --data sim/measurements.csv --trials 2000 \\
        --contributions --workers 2 --out mc/
    volcal mc --example mcv754 --trials 10000 --scheduler tcp://10.0.0.5:8786 --out mc/

Identifies the data (or the bundled example's simulated data), then samples the budget's
input sources, re-solves the full nonlinear problem for every trial with the solver built
once (checked against IPOPT on a few trials), and writes estimates, standard and expanded
(k = 2) uncertainties, 95 % coverage intervals, the comparison with the linearised
covariance and, with ``--contributions``, each source's share (one source at a time).
The run is deterministic for a seed whatever the workers; an interrupted run resumes from
the chunks saved in ``--out/samples``.  Exit codes: 0 done, 1 solver failure, 2 bad input.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from volcal.cli.options import (
    add_datum,
    add_degree,
    add_example_budget,
    add_model_or_example,
    add_result,
    add_sim_seed,
)

log = logging.getLogger(__name__)

MC_FILES = (
    "parameters.csv",
    "error_motions.csv",
    "volumetric.csv",
    "comparison.csv",
    "contributions.csv",
    "summary.json",
    "report.md",
    "volumetric_U.png",
    "max_volumetric.png",
    "contributions.png",
)


def _write(out_dir: Path, inputs, write) -> dict:
    """The outputs through :func:`volcal.base.folders.write_folder` (temporary folder, manifest,
    rename); the resumable ``samples/`` chunks written during the run move in with them."""
    import os
    import shutil

    from volcal.base.folders import write_folder

    summary: dict = {}

    def link(src: str, dst: str) -> None:
        try:
            os.link(src, dst)
        except OSError:
            shutil.copy2(src, dst)

    def writer(tmp: Path) -> None:
        summary.update(write(tmp))
        # linked, not moved: until the finished folder is renamed into place the chunks
        # stay where a rerun resumes them, whatever fails (a full disk, a signal)
        samples = Path(out_dir) / "samples"
        if samples.is_dir():
            shutil.copytree(samples, tmp / "samples", copy_function=link)

    write_folder(
        out_dir,
        MC_FILES,
        "volcal mc",
        writer,
        marker="summary.json",
        inputs=inputs,
        allowed_dirs=("samples",),
        force=True,
    )
    return summary


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "mc",
        help="Monte Carlo uncertainty of an identification (GUM Supplement 1)",
        description="Monte Carlo uncertainty per GUM Supplement 1: sample the budget's "
        "sources, re-solve with the solver built once, report estimates, "
        "standard and expanded uncertainties, 95 % coverage intervals, source "
        "contributions and the comparison with the linearised covariance.  "
        "Local worker processes by default, a Dask cluster with --scheduler; "
        "resumable from --out.",
    )
    src = add_model_or_example(
        p,
        "a bundled example (e.g. mcv754): simulate it (seed --sim-seed), "
        "identify, then Monte Carlo",
    )
    add_result(src, ", then Monte Carlo")
    p.add_argument("--data", type=Path, metavar="D.csv", help="measurement table (with --model)")
    p.add_argument("--stations", type=Path, metavar="S.csv", help="stations table")
    add_sim_seed(p)
    add_example_budget(p)
    add_degree(p)
    add_datum(p, described=False)
    p.add_argument("--strategy", default="joint", choices=("joint", "two-phase", "points-only"))
    p.add_argument(
        "--trials",
        type=int,
        default=1000,
        metavar="N",
        help="Monte Carlo trials (default 1000; GUM S1 suggests 1e5 or an "
        "adaptive check; paper 002 uses 1e4)",
    )
    p.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default 0)")
    p.add_argument(
        "--mode",
        default="nonlinear",
        choices=("nonlinear", "linear"),
        help="nonlinear: re-solve every trial (default); linear: the linearised "
        "map (one factorisation, many right-hand sides) for quick looks",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="W",
        help="local worker processes (default: all cores, this process computing "
        "too; 1: in this process)",
    )
    p.add_argument(
        "--scheduler",
        metavar="ADDR",
        help="Dask scheduler address (tcp://host:8786): run the trials there",
    )
    p.add_argument(
        "--chunk-size",
        type=int,
        default=200,
        metavar="C",
        help="trials per chunk (part of the run's definition; default 200)",
    )
    p.add_argument(
        "--contributions",
        action="store_true",
        help="also run one input source at a time (paper 002 Fig. 5)",
    )
    p.add_argument(
        "--contribution-trials",
        type=int,
        default=None,
        metavar="N",
        help="trials per source for --contributions (default --trials)",
    )
    p.add_argument(
        "--tool-sigma-um",
        type=float,
        default=0.0,
        metavar="U",
        help="standard uncertainty of the tool offsets, um per component "
        "(default 0: known exactly)",
    )
    p.add_argument(
        "--station-sigma-um",
        type=float,
        default=0.0,
        metavar="U",
        help="standard uncertainty of stations held fixed, um per coordinate",
    )
    p.add_argument(
        "--reference",
        type=Path,
        metavar="REF.csv",
        help="reference results (name, value, unit, U with k = 2): E_n per "
        "quantity (paper 002 eq. 25)",
    )
    p.add_argument(
        "--quantities",
        metavar="Q1,Q2",
        help="quantities to tabulate: parameter names or error motions at a "
        'position, e.g. "EXX(754),EC0Y" (default: every error at the end '
        "of its travel)",
    )
    p.add_argument(
        "--verify",
        type=int,
        default=2,
        metavar="K",
        help="re-solve K trials with IPOPT as a cross-check (default 2; 0: skip)",
    )
    p.add_argument(
        "--eval-grid",
        type=int,
        default=5,
        metavar="N",
        help="poses per axis of the workspace grid for volumetric errors",
    )
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="DIR",
        help="output folder (samples kept there: rerun an interrupted run to "
        "resume it; a finished run is replaced with --force)",
    )
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    import time

    from volcal.base.timing import Stages, process_seconds

    started = process_seconds()
    t_run = time.perf_counter()
    stages = Stages()
    if started is not None:
        stages.add("start-up (interpreter, command line)", started)
    from contextlib import ExitStack

    with ExitStack() as closing:
        # first: a child process that imports matplotlib while this one computes, and
        # draws the plots while this one writes the tables
        with stages("plotting process start"):
            from volcal.outputs import mc_plots
            from volcal.outputs.plot_process import plotting

            plotter = closing.enter_context(
                plotting(not args.no_plots, workers=1, warm=(mc_plots.warm_up,))
            )
        return _run(args, stages, t_run, started, plotter)


def _run(args: argparse.Namespace, stages, t_run: float, started: float | None, plotter) -> int:
    import time

    with stages("imports"):
        import pandas as pd

        from volcal.analysis.uncertainty.montecarlo import monte_carlo
        from volcal.base.exceptions import InputError
        from volcal.base.threads import blas_threads
        from volcal.measurement.plans import grid_plan
        from volcal.measurement.simulate import example
        from volcal.model.errors import ErrorForm, ErrorModel
        from volcal.model.machine import Machine
        from volcal.outputs.mc_report import write_mc_outputs

    for name, v, lo in (
        ("--trials", args.trials, 2),
        ("--chunk-size", args.chunk_size, 1),
        ("--eval-grid", args.eval_grid, 2),
        ("--degree", args.degree, 0),
        ("--verify", args.verify, 0),
        ("--seed", args.seed, 0),
    ):
        if v < lo:
            raise InputError(f"expected {name} >= {lo}, got {v}", source=name)
    if args.tool_sigma_um < 0 or args.station_sigma_um < 0:
        raise InputError("uncertainties must be >= 0", source="--tool-sigma-um")
    if args.model and args.data is None:
        raise InputError("--model needs --data (or use --example)", source="--data")
    reference = None
    if args.reference is not None:
        if not args.reference.is_file():
            raise InputError("no such file", source=str(args.reference))
        reference = pd.read_csv(args.reference)
    # fail before any solving: the output folder must be writable without touching an input
    from volcal.base.folders import check_out_dir

    inputs = (
        args.result,
        args.data,
        args.stations,
        args.reference,
        Path(args.budget) if args.budget else None,
        Path(args.model) if args.model else None,
    )
    check_out_dir(
        args.out, MC_FILES, "volcal mc", "summary.json", inputs=inputs, allowed_dirs=("samples",)
    )
    strategy = args.strategy
    with stages("model build"):
        ex = example(args.example) if args.example else None
        if args.result is not None:
            from volcal.outputs.analysis_report import result_inputs

            inp = result_inputs(args.result)
            machine, em = inp["machine"], inp["error_model"]
            budget = args.budget or inp["budget"]
            data, stations, strategy = inp["data"], inp["stations"], inp["strategy"]
        else:
            machine = ex.machine if ex else Machine.from_model(args.model)
            if ex is not None and args.degree == 3 and args.datum == ex.error_model.datum:
                em = ex.error_model
            else:
                em = ErrorModel(
                    machine.spec, default=ErrorForm("poly", args.degree), datum=args.datum
                )
            budget = args.budget or (ex.budget if ex is not None else "paper002")
            data, stations = args.data, args.stations
    if args.result is None and ex is not None:
        with stages("simulation"):
            data = ex.simulate(args.sim_seed).measurements
    quantities = [q.strip() for q in args.quantities.split(",")] if args.quantities else None

    with blas_threads(1):
        out = monte_carlo(
            machine,
            data,
            stations,
            budget=budget,
            trials=args.trials,
            seed=args.seed,
            mode=args.mode,
            workers=args.workers,
            scheduler=args.scheduler,
            out_dir=args.out,
            chunk_size=args.chunk_size,
            error_model=em,
            strategy=strategy,
            eval_points=grid_plan(machine.spec, args.eval_grid),
            tool_sigma_um=args.tool_sigma_um,
            station_sigma_um=args.station_sigma_um,
            with_contributions=args.contributions,
            contribution_trials=args.contribution_trials,
            progress=not args.no_progress and not getattr(args, "quiet", False),
            verify=args.verify,
            stages=stages,
        )
        res, mc = out["result"], out["mc"]
        if not res.success:
            print(f"volcal mc: identification did not converge ({res.status})")
            return 1
        extra = {
            "identification": {
                "status": res.status,
                "strategy": res.strategy,
                "chi2_per_dof": res.conditions.get("chi2_per_dof"),
                "residual_rms_um": res.residual_rms_um,
                # the verdict on the identification the trials scatter around
                "adequacy": res.adequacy.verdict,
                "adequacy_causes": res.adequacy.cause_kinds,
            },
            "verify_against_ipopt": out["verify"],
        }
        t_write = time.perf_counter()
        inner = dict(stages.seconds)
        summary = _write(
            args.out,
            inputs,
            lambda tmp: write_mc_outputs(
                tmp,
                mc,
                em,
                contributions=out["contributions"],
                reference=reference,
                quantities=quantities,
                plots=not args.no_plots,
                extra=extra,
                stages=stages,
                plotter=plotter,
            ),
        )
        # the output folder's own work: manifest, lock, renames
        stages.add(
            "writing (folder)",
            time.perf_counter()
            - t_write
            - sum(v - inner.get(k, 0.0) for k, v in stages.seconds.items()),
        )
    if not res.adequacy.adequate:
        # the trials draw the budget's noise around the identified model: a misfit the
        # model cannot follow is not in their spread
        log.warning("%s; the Monte Carlo uncertainties leave that misfit out", res.adequacy.message)
    if not getattr(args, "quiet", False):
        mv, ag = summary["max_volumetric"], summary["agreement_with_linearised"]
        print(
            f"volcal mc: {summary['trials']} trials ({summary['mode']}), seed "
            f"{summary['seed']}, {summary['seconds']:.1f} s"
            + (
                f" ({summary['resumed_chunks']} chunk(s) resumed)"
                if summary["resumed_chunks"]
                else ""
            )
        )
        print(f"  input sources            {', '.join(summary['sources'])}")
        print(f"  identification           {res.adequacy.summary}")
        print(
            f"  largest volumetric error {mv['max_norm_um']:.2f} um, U(k=2) "
            f"{mv['U_norm_at_max_um']:.2f} um; largest U(|d|) {mv['U_norm_largest_um']:.2f} um"
        )
        print(
            f"  MC vs linearised u       parameters within "
            f"{100 * ag['parameters_max_rel_diff']:.1f} %, volumetric within "
            f"{100 * ag['volumetric_max_rel_diff']:.1f} %"
        )
        if out["verify"]:
            v = out["verify"]
            print(
                f"  IPOPT cross-check        {v['trials']} trials, max difference "
                f"{v['max_abs_scaled']:.2g} um/urad ({v['theta_rel']:.2g} relative)"
            )
        if summary["not_converged"]:
            print(f"  not converged            {summary['not_converged']} trials")
        if "comparison" in summary:
            c = summary["comparison"]
            print(
                f"  reference comparison     {c['agree']} of {c['n']} with E_n <= 1 "
                f"(max {c['max_E_n']:.2f})"
            )
        print(f"  files                    {args.out}")
        if getattr(args, "verbose", 0):
            total = time.perf_counter() - t_run + (started or 0.0)
            print("stage timings (wall clock):")
            print(stages.table(total))
    # everything this command opened is closed (worker processes joined, files written):
    # as the program it may end without the interpreter's teardown; not after a Dask
    # cluster, whose library cleans up at exit
    args.exit_now = args.scheduler is None
    return 1 if summary["not_converged"] else 0
