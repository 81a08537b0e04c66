"""``volcal identify``: identify a machine's geometric errors from a measurement table.

Example::

    volcal identify --model mcv754_wxyzt --data sim/measurements.csv --out result/

Writes the result folder of DESIGN.md (see :mod:`volcal.outputs.results`) and prints a short
summary.  The model adequacy test (:mod:`volcal.analysis.adequacy`) has three outcomes:
the model fits; it fits but the uncertainty budget is pessimistic (chi2/dof below its
99.9 % interval, no significant residual structure: the uncertainties are conservative,
exit code 0, no warning); it does not fit (chi2/dof above its interval or significant
residual structure): then a warning naming the likely cause goes to the terminal (stderr;
silenced only by -q), as does a warning for data from a single station.  Exit codes: 0
success (whatever the adequacy), 1 the solver did not converge, 2 bad input.  The input
files are only read; the output folder is written atomically and replaces only a previous
result folder, with --force.
"""

from __future__ import annotations

import argparse
import json
import logging
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

# kept here (not imported from volcal.analysis.identify) so that `volcal --help` stays light
from volcal.problem.strategies import strategies as _strategies

log = logging.getLogger(__name__)

_STRATEGIES = tuple(_strategies())
_DATUMS = ("iso230", "reference", "none")


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "identify",
        help="identify the geometric errors from length readings",
        description="Identify the geometric error motions of a machine from multilateration "
        "length readings and write parameters, stations, residuals, component "
        "errors, a volumetric grid, plots, report.md and result.json (for "
        "`volcal predict`) to --out.  Every value written is an error "
        "(actual - nominal), not a correction.",
    )
    p.add_argument(
        "--model",
        required=True,
        metavar="M",
        help="bundled model name (see `volcal models`) or model TOML file",
    )
    p.add_argument(
        "--data",
        required=True,
        action=_AppendData,
        metavar="[INSTRUMENT=]D.csv",
        help="measurement table (station, point, axis columns in mm/deg, "
        "optional tool_x/y/z, length in mm, optional time, sigma); repeat for several "
        "instruments' tables identified as one problem, each prefixed with its "
        "instrument unless it is --instrument's: --data tracker.csv --data "
        "interferometer=lines.csv --data ballbar=circles.csv (formats: docs/instruments.md)",
    )
    p.add_argument(
        "--variance-components",
        action="store_true",
        help="estimate each table's budget scale factor (Helmert variance components) and "
        "weight by it; reported with its uncertainty in instruments.csv and the report",
    )
    p.add_argument(
        "--columns",
        metavar="COL=FILECOL[UNIT],...",
        help="column mapping for an instrument export: which file column holds each of "
        "volcal's columns, with the file's unit in brackets, e.g. "
        "'length=Distance[m],station=Tracker,point=Target' (units: mm, m, um, in, deg, "
        "rad, s, ms, min); with several --data tables it applies to the tracker and "
        "multi-laser tables",
    )
    p.add_argument(
        "--max-memory-gb",
        type=float,
        default=None,
        metavar="GB",
        help="memory the identification may take, GB; a table whose estimated peak "
        "(readings x unknowns, see docs/robustness.md) exceeds it is refused before the "
        "solve (default: the memory available now; inf: no check)",
    )
    p.add_argument(
        "--stations",
        type=Path,
        metavar="S.csv",
        help="stations table (station, x, y, z in mm, optional dead_length, "
        "fixed): start values, or known positions where fixed; with several --data "
        "tables it describes the tracker tables' stations",
    )
    p.add_argument(
        "--strategy",
        default="joint",
        choices=_STRATEGIES,
        help="joint (default): errors, stations and dead lengths together; "
        "two-phase; points-only (stations held); classic "
        "(calibrate -> multilaterate -> fit)",
    )
    p.add_argument(
        "--degree",
        default="3",
        metavar="N|auto",
        help="degree of the component error motions: Legendre degree, or the "
        "highest harmonic of the Fourier series on full-turn rotary axes "
        "(default 3); 'auto': per-axis orders chosen from the data by "
        "--order-criterion (order_selection.csv)",
    )
    p.add_argument(
        "--basis",
        action="append",
        default=[],
        metavar="NAME=KIND[:N]",
        help="error basis of an axis or one error motion, repeatable: KIND poly "
        "(N degree), fourier (N harmonics; rotary axes), bspline (N "
        "segments), table (N comma-separated knots, mm/deg) or constant; "
        "e.g. --basis C=fourier:3 --basis X=bspline:6 (overrides the model "
        "file's basis declarations; docs/error_bases.md)",
    )
    p.add_argument(
        "--order-criterion",
        default="bic",
        choices=["bic", "cv"],
        help="with --degree auto: bic (chi2 + k ln N, default) or cv (K-fold "
        "cross-validation on held-out poses)",
    )
    p.add_argument(
        "--cv-folds",
        type=int,
        default=5,
        metavar="K",
        help="folds of --order-criterion cv (default 5)",
    )
    p.add_argument(
        "--datum",
        default="iso230",
        choices=_DATUMS,
        help="datum convention of the error motions (default iso230)",
    )
    p.add_argument(
        "--budget",
        default="paper002",
        metavar="NAME|FILE",
        help="uncertainty budget weighting readings without sigma: bundled name "
        "or TOML file (default paper002)",
    )
    p.add_argument(
        "--robust",
        action="store_true",
        help="reject readings whose normalised residual exceeds --reject-k robust "
        "standard deviations and re-solve (with several --data tables: each table's "
        "robust standard deviation)",
    )
    p.add_argument(
        "--reject-k",
        type=float,
        default=None,
        metavar="K",
        help="rejection threshold of --robust (default 4)",
    )
    p.add_argument(
        "--station-method",
        default="sqrt",
        choices=["sqrt", "squared", "linear", "linear_taylor", "paper002"],
        help="classic strategy: station self-calibration (paper 000 Case A sqrt, "
        "squared, Case B linear, Case B + Taylor; paper 002 linear)",
    )
    p.add_argument(
        "--point-method",
        default="sqrt",
        choices=["sqrt", "squared", "linear", "linear_taylor"],
        help="classic strategy: point multilateration method",
    )
    p.add_argument(
        "--solver",
        default="auto",
        choices=["auto", "ipopt", "gauss-newton"],
        help="auto (default: ipopt below 10,000 readings, gauss-newton from there), "
        "ipopt (followed by Gauss-Newton polish steps) or gauss-newton "
        "(Levenberg-Marquardt with the datum eliminated, evaluated in chunks of "
        "poses: no per-reading graph, for large tables); both reach the same minimiser",
    )
    p.add_argument(
        "--instrument",
        default="tracker",
        metavar="NAME",
        help="observation model: tracker (default; sequential multilateration) "
        "or multilaser (paper 001's head); see volcal.measurement.instruments",
    )
    p.add_argument(
        "--exact",
        action="store_true",
        help="exact rotations in the model instead of the first-order one",
    )
    p.add_argument(
        "--scale-covariance",
        action="store_true",
        help="scale the covariance by the residual variance factor (chi2/dof); for a "
        "budget that is off, not for residual structure (a misfit is not noise)",
    )
    p.add_argument(
        "--out",
        required=True,
        type=Path,
        metavar="DIR",
        help="output folder (created; a previous result folder is replaced with --force)",
    )
    p.add_argument(
        "--no-plots",
        action="store_true",
        help="skip the PNG plots (0.4 s; `volcal report` draws them later from the result)",
    )
    # the collector stays paused through this command's imports (_run resumes it)
    p.set_defaults(func=run, imports_gc_paused=True)
    return p


class _AppendData(argparse.Action):
    """``--data`` given several times: a list.  Given on the command line it replaces a
    project file's ``data`` (as every flag overrides the file)."""

    def __call__(self, parser, namespace, values, option_string=None):
        given = getattr(namespace, "_data_given", False)
        current = getattr(namespace, self.dest, None)
        items = list(current) if given and isinstance(current, list) else []
        items.append(str(values))
        setattr(namespace, self.dest, items)
        namespace._data_given = True


def _data_sets(args: argparse.Namespace) -> list:
    """The --data tables as :class:`volcal.measurement.datasets.DataSet` (a project
    file's single ``data`` too)."""
    from volcal.measurement.datasets import parse_data_argument

    data = args.data if isinstance(args.data, list) else [args.data]
    return [parse_data_argument(str(d), args.instrument) for d in data]


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.resolve().relative_to(folder.resolve())
        return True
    except ValueError:
        return False


def _read_inputs(args: argparse.Namespace, rows_checked: Callable[[], object] = lambda: None):
    """The measurement table (and the stations table) read and validated first, before
    the model is built or the solver imported, and its cells before the plotting
    processes are started: a bad table is reported at once (exit code 2).
    ``rows_checked`` is called once every row and cell of the table is checked when that
    is before pandas' import (the tracker's tables, read with the standard library): the
    caller starts the plotting processes there, a third of a second earlier than after
    the reading (the whole-table checks, e.g. duplicate readings, come after; an error
    there ends the plotting processes at once).  Returns (Measurements, stations table or
    None, seconds spent reading the measurement table)."""
    import time

    from volcal.model.spec import resolve_model

    sets = _data_sets(args)
    args.data_sets = sets
    if len(sets) > 1 or sets[0].instrument != args.instrument or args.variance_components:
        args.data = None  # several tables: read by identify, each with its instrument
        return None, None, 0.0
    args.data = Path(sets[0].source)
    spec = resolve_model(args.model)
    source: object = args.data
    t0 = time.perf_counter()
    if not args.columns:
        # before pandas' import (a third of a second): the header from the first line,
        # then for the tracker's tables (positive lengths) the rows and cells, with the
        # loader's messages; the numbers read there are the loader's (no second reading)
        from volcal.measurement.cells import scan_measurements
        from volcal.measurement.header import check_header

        check_header(args.data, spec)
        if args.instrument == "tracker":
            source = scan_measurements(args.data, spec) or args.data
    t_scan = time.perf_counter() - t0
    if source is not args.data:  # the rows and cells read and checked (not yet the
        # whole-table checks: duplicates, readings per station, geometry)
        rows_checked()
    from volcal.measurement.instruments import get_instrument
    from volcal.measurement.tables import (
        load_instrument_stations,
        load_measurements,
        load_stations,
    )

    ins = get_instrument(args.instrument)
    stations = None
    if args.stations is not None:
        stations = (
            load_stations(args.stations)
            if ins.name == "tracker"
            else load_instrument_stations(args.stations, ins.station_param_names)
        )
    t0 = time.perf_counter()
    meas = load_measurements(
        source,
        spec,
        stations=stations,
        relative_lengths=not ins.positive_readings,
        columns=args.columns,
    )
    return meas, stations, t_scan + time.perf_counter() - t0


def run(args: argparse.Namespace) -> int:
    from volcal.outputs.plot_process import plotting

    # a bad input ends the program without the interpreter's teardown too: the error is
    # raised before anything is opened that a `with` does not close (volcal.cli.main)
    args.exit_now_on_error = True
    # once the table's rows are checked, before the numerics are imported: two children
    # that import matplotlib on the other core while this process reads and solves, build
    # the frames of the figures each will draw, then draw the plots two at a time while
    # this one writes the report.  Started as soon as the table's cells are known good
    # (for the tracker's tables before pandas' import: the children's work, not this
    # process's, is what the default outputs wait for), else once it is read
    with ExitStack() as stack:
        plotters: list = []

        def start() -> None:
            if not plotters:
                ahead = _frames_ahead(args)
                plotters.append(stack.enter_context(plotting(not args.no_plots, ahead=ahead)))

        inputs = _read_inputs(args, start)
        start()
        code = _run(args, plotters[0], inputs)
    # everything is written and closed: skip the interpreter's teardown (0.1 s of freeing
    # modules; see volcal.cli.main._exit_now)
    args.exit_now = True
    return code


def _frames_ahead(args: argparse.Namespace):
    """The plotting children's frames to build ahead (``workers -> plan``,
    :func:`volcal.outputs.figures.frame_plan`), from the model's axes (their number, and
    their travel for the volumetric map's); None when the model cannot be read here (the
    error is reported where it is built)."""
    if args.no_plots:
        return None
    from volcal.model.spec import resolve_model

    try:
        axes = resolve_model(args.model).axes
    except Exception:
        return None
    from volcal.outputs.figures import frame_plan, volumetric_frame_key

    try:
        vol = volumetric_frame_key([(a.travel[0], a.travel[1], a.is_rotary) for a in axes])
    except Exception:  # no map, or one of another layout: drawn without a frame
        vol = None
    n_axes = len(axes)
    return lambda workers: frame_plan(n_axes, workers, vol)


def _run(args: argparse.Namespace, plotter, inputs: tuple) -> int:
    import time

    t_command = time.perf_counter()
    from volcal.analysis.adequacy import assess
    from volcal.base.exceptions import InputError
    from volcal.model.errors import parse_basis
    from volcal.outputs.results import check_out_dir, save_result
    from volcal.workflow.dispatch import identify

    degree: int | str = str(args.degree).strip().lower()
    if degree != "auto":
        try:
            degree = int(degree)
        except ValueError:
            degree = -1
        if degree < 0:
            raise InputError(
                f"expected an integer degree >= 0 or 'auto', got {args.degree!r}", source="--degree"
            )
    elif args.cv_folds < 2:
        raise InputError(f"expected at least 2 folds, got {args.cv_folds}", source="--cv-folds")
    if degree != "auto" and (args.order_criterion != "bic" or args.cv_folds != 5):
        raise InputError(
            "--order-criterion and --cv-folds apply with --degree auto only",
            source="--order-criterion",
        )
    forms = dict(parse_basis(b) for b in args.basis) or None
    if args.max_memory_gb is not None and not args.max_memory_gb > 0:
        raise InputError(
            f"expected a memory limit > 0 GB, got {args.max_memory_gb:g}", source="--max-memory-gb"
        )
    if args.reject_k is not None and not args.robust:
        raise InputError("--reject-k applies with --robust only", source="--reject-k")
    reject_k = 4.0 if args.reject_k is None else args.reject_k
    if not reject_k > 0:
        raise InputError(f"expected a positive threshold, got {reject_k:g}", source="--reject-k")
    # fail before the solve: the output must be writable without touching any input
    out = check_out_dir(args.out)
    for name, path in (
        *(("--data", Path(d.source)) for d in args.data_sets),
        ("--stations", args.stations),
        ("--budget", Path(args.budget)),
        ("--model", Path(args.model)),
    ):
        if path is not None and path.exists() and _inside(path, out):
            raise InputError(
                f"the input {path} is inside the output folder, which is "
                "replaced; write the result elsewhere",
                source=name,
            )

    if getattr(args, "gc_paused", False):
        # the libraries are imported (the table read, the output checked): the collector
        # again, without walking what they allocated (volcal.base.processes.resume_gc)
        from volcal.base.processes import resume_gc

        resume_gc()
    data_name = ", ".join(str(d.source) for d in args.data_sets)
    log.info("identifying: model %s, data %s, strategy %s", args.model, data_name, args.strategy)
    meas, stations, read_s = inputs
    several = {}
    if meas is None:  # several tables (volcal.analysis.fusion), read there
        meas = [(d.instrument, d.source) for d in args.data_sets]
        several = {"variance_components": args.variance_components}
        stations = args.stations  # the tracker tables' stations (volcal.analysis.fusion)
    # the residual and volumetric plots need no covariance: sent to the plotting children
    # as soon as the solve has ended, drawn while the uncertainty is computed and the
    # tables written, kept in memory until the result folder exists (save_result)
    held: dict[str, int] = {}

    def on_solved(solved) -> None:
        from volcal.base import progress
        from volcal.outputs.plots import hold_solved_plots

        with progress.stage("plotting"):
            held.update(hold_solved_plots(plotter, solved))

    res = identify(
        args.model,
        meas,
        stations,
        strategy=args.strategy,
        degree=degree,
        forms=forms,
        order_criterion=args.order_criterion,
        cv_folds=args.cv_folds,
        datum=args.datum,
        budget=args.budget,
        robust=args.robust,
        reject_k=reject_k,
        exact=args.exact,
        scale_covariance=args.scale_covariance,
        station_method=args.station_method,
        point_method=args.point_method,
        verbose=getattr(args, "verbose", 0) > 1,
        progress=not getattr(args, "quiet", False),
        solver=args.solver,
        instrument=args.instrument,
        columns=args.columns,
        max_memory_gb=args.max_memory_gb,
        on_solved=on_solved if plotter is not None else None,
        # this command does not solve again: IPOPT's graph freed before the uncertainty
        release_graph=True,
        **several,
    )
    log.info("solved (%s) in %.2f s; writing %s", res.status, res.seconds, out)
    from volcal.base.progress import record

    record("reading the data", read_s)  # read before identify() started its record
    from volcal.base.processes import return_freed_memory

    return_freed_memory()  # the solve's freed work memory, before the plotting processes draw
    options = {
        "model": args.model,
        "strategy": args.strategy,
        "degree": degree,
        "basis": list(args.basis),
        "order_criterion": args.order_criterion,
        "datum": args.datum,
        "budget": args.budget,
        "robust": args.robust,
        "reject_k": reject_k,
        "exact": args.exact,
        "scale_covariance": args.scale_covariance,
        "station_method": args.station_method,
        "point_method": args.point_method,
        "solver": args.solver,
        "instrument": args.instrument,
        "stations": str(args.stations) if args.stations else None,
        "project_file": getattr(args, "project_file", None),
        "columns": args.columns,
        "data": [f"{d.instrument}={d.source}" for d in args.data_sets],
        "variance_components": args.variance_components,
    }
    path = save_result(
        res,
        out,
        data_name=data_name,
        plots=not args.no_plots,
        options=options,
        plotter=plotter,
        held=held,
    )
    meta = json.loads((path / "result.json").read_text(encoding="utf-8"))
    adequacy = assess(res)  # computed once per result (kept on it), as in the report
    if not getattr(args, "quiet", False):
        spec = res.machine.spec
        n_rej = meta["n_rejected"]
        unid = meta["unidentifiable"]
        iters = sum(o.iterations for o in res.outcomes)
        print(
            f"volcal identify: model '{spec.name}', {meta['n_readings']} readings from "
            f"{res.residuals['station'].nunique()} stations, strategy {res.strategy}"
        )
        print(f"  solver status            {res.status} ({iters} iterations)")
        print(
            f"  residual RMS             {res.residual_rms_um:.3f} um (chi2/dof "
            f"{res.conditions.get('chi2_per_dof', float('nan')):.3g})"
        )
        print("  model adequacy           " + adequacy.summary)
        if res.instruments is not None:
            for _, row in res.instruments.iterrows():
                # with variance components every scaled chi2/dof is 1: the check that
                # says something is the one with the budgets as given
                vce = "scale_factor" in row
                scale = (
                    f" with the budgets as given, budget x{row['scale_factor']:.3g} "
                    f"(95 %: {row['scale_low_95']:.3g}..{row['scale_high_95']:.3g})"
                    if vce
                    else ""
                )
                chi = row["chi2_per_dof_given"] if vce else row["chi2_per_dof"]
                verdict = row["verdict_given"] if vce else row["verdict"]
                print(
                    f"    {row['instrument']:<14} {row['n_readings']} readings, chi2/dof "
                    f"{chi:.3g} ({verdict}){scale}"
                )
        axes = meta.get("max_volumetric_axes") or []
        fixed = [a for a in spec.axis_names if a not in axes]
        print(
            f"  largest volumetric error {meta['max_volumetric_um']:.2f} um "
            f"(grid over {', '.join(axes) or 'no axis'}"
            + (f", {', '.join(fixed)} at reference" if fixed else "")
            + ", tool offset (0, 0, 0) mm)"
        )
        print("  unidentifiable           " + (", ".join(unid) if unid else "none"))
        if res.datum is not None and len(res.datum):
            free = res.datum.loc[~res.datum["imposed"]]
            print(
                f"  datum ({res.error_model.datum})           "
                f"{int(res.datum['imposed'].sum())} of {len(res.datum)} conditions imposed"
                + (
                    "; not imposed (the data determine them, values in datum.csv): "
                    + ", ".join(c.split(" ")[0] for c in free["condition"])
                    if len(free)
                    else ""
                )
            )
        if args.robust:
            print(f"  rejected readings        {n_rej}")
        # two times, each saying what it covers (the report's identification time is
        # the first; the progress lines time each stage)
        print(
            f"  time                     identification {res.seconds:.1f} s (reading, "
            f"solving, uncertainty); {time.perf_counter() - t_command:.1f} s with writing "
            "the result and its plots"
        )
        print(f"  report                   {path / 'report.md'}")
        print(f"  files                    {path}")
    # warnings reach the terminal (stderr) unless -q
    if not adequacy.adequate:
        log.warning("%s (report: %s)", adequacy.message, path / "report.md")
    elif adequacy.verdict == "budget_pessimistic":
        # not a failure: said once, at info level (the summary line above has it too)
        log.info("%s (report: %s)", adequacy.message, path / "report.md")
    for w in adequacy.warnings:
        log.warning("%s", w)
    why = res.unidentifiable_explanation()
    if why is not None:
        log.warning("%s (report: %s)", why["text"], path / "report.md")
    if not res.success:
        return 1
    return 0
