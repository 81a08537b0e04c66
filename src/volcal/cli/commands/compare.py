"""``volcal compare``: identification strategies side by side on the same data.

Examples::

    volcal compare --example mcv754 --out cmp/
    volcal compare --model mcv754_wxyzt --data sim/measurements.csv \\
        --truth sim/true_parameters.csv --trials 20 --workers 2 --out cmp/
    volcal compare --model trunnion_ac --data m.csv --strategies joint,two-phase --out cmp/

Runs every strategy (default joint, two-phase, points-only, classic) on the same readings
with the same error model and budget, prints the side-by-side table (status, chi2/dof and
adequacy verdict, residual RMS, the field difference to the reference strategy modulo the
gauge in um and in units of its standard uncertainty, the largest parameter differences,
what each leaves unidentifiable, time; with ``--truth`` each field error against the
truth; with ``--trials`` mean and spread of each field error over seeded simulated data)
and writes the folder of :mod:`volcal.outputs.compare_report` (``volcal report --result
DIR`` reports the reference result with the comparison).  Exit codes: 0 every strategy
solved, 1 a strategy's solver failed (the table says which), 2 bad input.  The input
files are only read; the folder is written whole or not at all and replaces an earlier
comparison only with --force.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from volcal.cli.options import add_datum, add_example_budget, add_model_or_example, add_sim_seed

# kept here (not imported from volcal.analysis) so that `volcal --help` stays light
from volcal.problem.strategies import strategies as _strategies

_DEFAULT = "joint,two-phase,points-only,classic"


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "compare",
        help="identification strategies side by side on the same data",
        description="Identify the same readings with several strategies and compare them: "
        "status, chi2/dof and verdict, residual RMS, field difference to the reference "
        "strategy (gauge removed, um and units of u), largest parameter differences, "
        "what each leaves unidentifiable, time; with --truth the field error against the "
        "truth; with --trials mean and spread over seeded simulated data.  Writes a "
        "table, a plot and a Markdown / HTML section `volcal report` embeds.",
    )
    add_model_or_example(
        p,
        "a bundled example (e.g. mcv754): its simulated data (seed --sim-seed), "
        "its true errors as the truth and its stations as the trials' true stations",
    )
    p.add_argument("--data", type=Path, metavar="D.csv", help="measurement table (with --model)")
    p.add_argument(
        "--stations",
        type=Path,
        metavar="S.csv",
        help="stations table (start values, or known positions where fixed)",
    )
    add_sim_seed(p)
    p.add_argument(
        "--strategies",
        default=_DEFAULT,
        metavar="S1,S2",
        help=f"strategies to compare, comma-separated (default {_DEFAULT}; known: "
        f"{', '.join(_strategies())})",
    )
    p.add_argument(
        "--reference",
        default=None,
        metavar="S",
        help="the strategy the others are compared with (default joint, else the first)",
    )
    p.add_argument(
        "--degree", type=int, default=3, metavar="N", help="degree of the error motions (3)"
    )
    p.add_argument(
        "--basis",
        action="append",
        default=[],
        metavar="NAME=KIND[:N]",
        help="error basis of an axis or error motion, repeatable (as `volcal identify`)",
    )
    add_datum(p, described=False)
    add_example_budget(p)
    p.add_argument(
        "--solver", default="ipopt", choices=("ipopt", "gauss-newton"), help="(default ipopt)"
    )
    p.add_argument(
        "--truth",
        type=Path,
        metavar="P.csv",
        help="true errors, the file `volcal simulate --true-parameters` reads (name, "
        "value, unit; e.g. a simulation's true_parameters.csv): adds each strategy's "
        "field error against them",
    )
    p.add_argument(
        "--trials",
        type=int,
        default=0,
        metavar="N",
        help="repeat the comparison on N simulated data sets (the data's poses, tool "
        "offsets and stations; true errors from --truth, else the reference's estimate) "
        "and report mean and spread of each field error (default 0)",
    )
    p.add_argument(
        "--seed", type=int, default=0, metavar="S", help="seed of the trials (default 0)"
    )
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="W",
        help="local worker processes for the trials (default: all cores, this process "
        "computing too; 1: in this process)",
    )
    p.add_argument(
        "--scheduler", metavar="ADDR", help="Dask scheduler address: run the trials there"
    )
    p.add_argument(
        "--eval-poses",
        type=int,
        default=256,
        metavar="N",
        help="Halton poses of the workspace sample, besides the corners (default 256)",
    )
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="DIR",
        help="output folder (an earlier comparison is replaced with --force)",
    )
    p.add_argument("--no-plots", action="store_true", help="skip field_differences.png")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from volcal.base.exceptions import InputError

    strategies = [s.strip() for s in args.strategies.split(",") if s.strip()]
    known = list(_strategies())
    bad = [s for s in strategies if s not in known]
    if bad or not strategies:
        raise InputError(
            f"unknown strategy {', '.join(bad) or '(none given)'}; expected a comma-separated "
            f"list of {', '.join(known)}",
            source="--strategies",
        )
    if args.reference is not None and args.reference not in strategies:
        raise InputError(
            f"{args.reference!r} is not among --strategies ({', '.join(strategies)})",
            source="--reference",
        )
    for name, v, lo in (
        ("--trials", args.trials, 0),
        ("--seed", args.seed, 0),
        ("--sim-seed", 0 if args.sim_seed is None else args.sim_seed, 0),
        ("--degree", args.degree, 0),
        ("--eval-poses", args.eval_poses, 1),
    ):
        if v < lo:
            raise InputError(f"expected {name} >= {lo}, got {v}", source=name)
    if args.sim_seed is not None and not args.example:
        raise InputError("--sim-seed applies to --example only", source="--sim-seed")
    if args.model and args.data is None:
        raise InputError("--model needs --data (or use --example)", source="--data")
    if args.example and args.data is not None:
        raise InputError("--data goes with --model, not with --example", source="--data")
    for path in (args.data, args.stations, args.truth):
        if path is not None and not path.is_file():
            raise InputError("no such file", source=str(path))
    from volcal.model.errors import parse_basis

    forms = dict(parse_basis(b) for b in args.basis) or None
    # before any solving: the output folder must be writable without touching an input
    from volcal.base.folders import check_out_dir
    from volcal.outputs.compare_report import COMPARE_FILES, REFERENCE_DIR

    inputs = (
        args.data,
        args.stations,
        args.truth,
        Path(args.budget) if args.budget else None,
        Path(args.model) if args.model else None,
    )
    check_out_dir(
        args.out,
        COMPARE_FILES,
        "volcal compare",
        "compare.json",
        inputs=inputs,
        allowed_dirs=(REFERENCE_DIR,),
    )
    from volcal.outputs.compare_report import format_table, write_comparison
    from volcal.workflow.comparison import compare

    truth = args.truth
    truth_name = None
    true_stations = None
    if args.example:
        from volcal.measurement.simulate import example
        from volcal.model.errors import ErrorForm, ErrorModel

        ex = example(args.example)
        machine, stations, data = ex.machine, args.stations, ex.simulate(args.sim_seed).measurements
        em = (
            ex.error_model
            if args.degree == 3 and args.datum == ex.error_model.datum and forms is None
            else ErrorModel(
                machine.spec, forms, default=ErrorForm("poly", args.degree), datum=args.datum
            )
        )
        if truth is None and em is ex.error_model:
            truth, truth_name = ex.theta_true, f"the true errors of example {ex.name}"
        true_stations = ex.stations
        budget = args.budget or ex.budget
        data_name = f"example {ex.name}, seed {ex.seed if args.sim_seed is None else args.sim_seed}"
    else:
        machine, data, stations, em = args.model, args.data, args.stations, None
        budget = args.budget or "paper002"
        data_name = str(args.data)
    cmp = compare(
        machine,
        data,
        stations,
        strategies=strategies,
        reference=args.reference,
        degree=args.degree,
        datum=args.datum,
        forms=forms,
        error_model=em,
        budget=budget,
        solver=args.solver,
        truth=truth,
        trials=args.trials,
        seed=args.seed,
        workers=args.workers,
        scheduler=args.scheduler,
        eval_poses=args.eval_poses,
        true_stations=true_stations,
        truth_name=truth_name,
    )
    out = write_comparison(
        cmp, args.out, plots=not args.no_plots, data_name=data_name, inputs=inputs
    )
    if not getattr(args, "quiet", False):
        print(
            f"volcal compare: model '{cmp.model}', {cmp.n_readings} readings, "
            f"{len(cmp.strategies)} strategies against {cmp.reference}"
            + (f", {cmp.n_trials} trials (seed {cmp.seed})" if cmp.n_trials else "")
            + f", {cmp.seconds:.1f} s"
        )
        print(format_table(cmp.table, cmp.reference))
        for n in cmp.notes:
            print(f"note: {n}")
        print(f"files: {out}")
    args.exit_now = args.scheduler is None
    return 0 if cmp.success else 1
