"""``volcal analyze``: what an experiment can identify, and how well.

Examples::

    # a plan before measuring: the bundled example's stations, poses and tool offsets
    volcal analyze --example mcv754 --out analysis/
    # the same plan with a single reflector offset: names what it cannot identify
    volcal analyze --example mcv754 --tools "0,0,0" --out analysis_one_tool/
    # a plan of your own
    volcal analyze --model mcv754_wxyzt --stations S.csv --plan grid --grid 5 \\
        --tools "0,0,-100;80,0,-100;0,80,-100" --budget paper002 --out analysis/
    # after measuring: identify the data, analyse at the solution
    volcal analyze --model mcv754_wxyzt --data sim/measurements.csv --out analysis/

Prints the summary (rank and tolerance, condition numbers, unidentifiable directions with
their explanation, weakest directions, largest uncertainties and correlations, volumetric
uncertainty) and writes summary.txt, report.md, CSV tables and plots to ``--out``
(see :mod:`volcal.outputs.analysis_report`).  Exit codes: 0 done, 1 identification failed, 2 bad
input.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from volcal.cli.options import (
    MODEL_LIST_HELP,
    add_datum,
    add_degree,
    add_example_budget,
    add_model_or_example,
    add_result,
)


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "analyze",
        help="identifiability, conditioning and linearised uncertainty of a plan or result",
        description="Analyse a measurement plan (before any data: stations, poses, tool "
        "offsets, budget) or measured data (identified first): numerical rank "
        "of the scaled Jacobian and its tolerance, singular values, condition "
        "numbers, unidentifiable directions as named parameter combinations with "
        "their tested explanation, weak directions, the linearised covariance "
        "under the datum constraints, correlations and the uncertainty of the "
        "volumetric error over the workspace.",
    )
    src = add_model_or_example(
        p,
        "a bundled example (e.g. mcv754): its model, stations, plan, "
        "tools and budget; the options below override parts",
        MODEL_LIST_HELP,
    )
    add_result(src, " and analysed at the solution")
    p.add_argument(
        "--data",
        type=Path,
        metavar="D.csv",
        help="measured data: identify them and analyse the result (otherwise the plan is analysed)",
    )
    p.add_argument(
        "--stations",
        type=Path,
        metavar="S.csv",
        help="stations table (station, x, y, z mm, dead_length): the plan's "
        "stations, or start values for --data",
    )
    p.add_argument(
        "--plan",
        metavar="default|grid|lines|diagonals|FILE.csv",
        help="the plan's poses (default: the default plan of `volcal simulate`, "
        "a grid, with rotary axes a linear grid plus rotary sweeps; with "
        "--example its plan; --grid alone: a grid)",
    )
    p.add_argument("--grid", metavar="N", help="positions per axis (N or X=6,Y=5,Z=5)")
    p.add_argument(
        "--tools",
        metavar='"x,y,z;x,y,z"',
        help="tool (reflector) offsets in mm (default: the example's, or those of "
        "`volcal simulate`: 0,0,0;0,0,-100;80,0,-100;0,80,-100)",
    )
    add_example_budget(p)
    add_degree(p)
    add_datum(p)
    p.add_argument(
        "--strategy",
        default="joint",
        choices=("joint", "two-phase", "points-only"),
        help="identification strategy with --data (default joint)",
    )
    p.add_argument(
        "--scale-covariance",
        action="store_true",
        help="with --data: scale the covariance by the residual variance factor (chi2/dof)",
    )
    p.add_argument(
        "--eval-grid",
        type=int,
        default=5,
        metavar="N",
        help="poses per axis of the workspace grid for the volumetric uncertainty (default 5)",
    )
    p.add_argument(
        "--weak",
        type=int,
        default=8,
        metavar="K",
        help="how many weakest directions to list (default 8)",
    )
    p.add_argument(
        "--out",
        type=Path,
        metavar="DIR",
        help="output folder for the report, CSV and plots (with --force, replaces "
        "a previous analysis)",
    )
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from volcal.base.exceptions import InputError
    from volcal.base.threads import blas_threads
    from volcal.cli.commands.simulate import (
        _DEFAULT_TOOLS,
        PLAN_KINDS,
        _grid_counts,
        _named_plan,
    )
    from volcal.measurement.plans import grid_plan, plan_from_csv
    from volcal.measurement.simulate import example, parse_tools
    from volcal.model.errors import ErrorForm, ErrorModel
    from volcal.model.machine import Machine
    from volcal.outputs.analysis_report import analyze_data, analyze_plan

    if args.degree < 0:
        raise InputError(f"expected a degree >= 0, got {args.degree}", source="--degree")
    if args.eval_grid < 2:
        raise InputError(f"expected --eval-grid >= 2, got {args.eval_grid}", source="--eval-grid")
    if args.scale_covariance and args.data is None and args.result is None:
        raise InputError(
            "--scale-covariance needs --data (a plan has no residuals)", source="--scale-covariance"
        )
    tools = parse_tools(args.tools) if args.tools is not None else None
    if args.out is not None:
        # the output folder before any solving
        from pathlib import Path

        from volcal.base.folders import check_out_dir
        from volcal.outputs.analysis_report import ANALYSIS_FILES

        check_out_dir(
            args.out,
            ANALYSIS_FILES,
            "an analysis",
            inputs=[
                args.result,
                args.data,
                args.stations,
                args.model and Path(args.model),
                args.budget and Path(args.budget),
                args.plan and Path(args.plan),
            ],
        )
    if args.result is not None:
        return _run_result(args)
    ex = example(args.example) if args.example else None
    machine = ex.machine if ex else Machine.from_model(args.model)
    spec = machine.spec
    if ex is not None and args.degree == 3 and args.datum == ex.error_model.datum:
        em = ex.error_model
    else:
        em = ErrorModel(spec, default=ErrorForm("poly", args.degree), datum=args.datum)
    budget = args.budget or (ex.budget if ex is not None else "paper002")
    evalp = grid_plan(spec, args.eval_grid)

    with blas_threads(1):  # small dense problems: threads only slow them down here
        if args.data is not None:
            rep, res = analyze_data(
                machine,
                args.data,
                args.stations,
                budget=budget,
                strategy=args.strategy,
                error_model=em,
                scale_covariance=args.scale_covariance,
                eval_points=evalp,
            )
            if not res.success:
                print(f"volcal analyze: identification did not converge ({res.status})")
                return 1
        else:
            kind = args.plan or ("grid" if args.grid is not None else "default")
            if args.plan is None and ex is not None and args.grid is None:
                plan = ex.plan
            elif kind in PLAN_KINDS:
                if kind == "default" and args.grid is not None:
                    raise InputError(
                        "--grid applies to --plan grid, lines or diagonals", source="--grid"
                    )
                plan = _named_plan(kind, spec, _grid_counts(args.grid, kind), args.degree)
            else:
                if args.grid is not None:
                    raise InputError(
                        "--grid applies to --plan grid, lines or diagonals", source="--grid"
                    )
                plan = plan_from_csv(kind, spec)
            if args.stations is not None:
                stations = args.stations
            elif ex is not None:
                stations = ex.stations
            else:
                from volcal.measurement.plans import default_stations

                stations = default_stations(spec, 6, tools=tools)
            if tools is None:
                tools = ex.tools if ex is not None else parse_tools(_DEFAULT_TOOLS)
            rep = analyze_plan(
                machine,
                plan,
                stations,
                tools,
                budget,
                error_model=em,
                eval_points=evalp,
                n_weak=args.weak,
            )
    return _finish(args, rep)


def _run_result(args: argparse.Namespace) -> int:
    import numpy as np

    from volcal.base.threads import blas_threads
    from volcal.measurement.plans import grid_plan
    from volcal.outputs.analysis_report import analyze_data, result_inputs

    inp = result_inputs(args.result)
    with blas_threads(1):
        rep, res = analyze_data(
            inp["machine"],
            inp["data"],
            inp["stations"],
            budget=args.budget or inp["budget"],
            strategy=inp["strategy"],
            error_model=inp["error_model"],
            scale_covariance=args.scale_covariance,
            eval_points=grid_plan(inp["machine"].spec, args.eval_grid),
        )
    if not res.success:
        print(f"volcal analyze: identification did not converge ({res.status})")
        return 1
    diff = (
        float(np.max(np.abs(res.theta - inp["theta"])))
        if len(res.theta) == len(inp["theta"])
        else float("inf")
    )
    rep.notes.append(
        f"re-identified the result's data: largest difference from the saved "
        f"estimate {diff:.2g} (mm / rad)"
    )
    return _finish(args, rep)


def _finish(args: argparse.Namespace, rep) -> int:
    if not getattr(args, "quiet", False):
        print(rep.summary(top=args.weak))
    if args.out is not None:
        out = rep.save(args.out, plots=not args.no_plots)
        if not getattr(args, "quiet", False):
            print(f"  files                 {out}")
    return 0
