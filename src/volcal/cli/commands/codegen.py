"""``volcal codegen``: export a C identification solver (or the C machine model alone).

Examples::

    volcal codegen --model mcv754_wxyzt --plan measurements.csv --out solver_c/
    volcal codegen --model mcv754_wxyzt --plan layout.csv --stations stations.csv \\
        --strategy two-phase --name mcv754 --out solver_c/
    volcal codegen --model mcv754_wxyzt --model-only --out model_c/

Writes the C sources, header, Makefile, example main.c, README.md and manifest.json to
``--out`` and builds them with make + gcc (``--no-build`` to skip).  An unchanged export
(same model, plan, options and versions) is reused.  See :mod:`volcal.outputs.codegen`.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

from volcal.cli.options import add_datum, add_degree

log = logging.getLogger(__name__)


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "codegen",
        help="export a C solver (or the C model) that runs without Python",
        description="Export a generated C identification solver for a machine model and a "
        "measurement plan: C sources and header, Makefile (gcc, libc and libm "
        "only), an example program that reads a measurement CSV, a README and a "
        "manifest.  The plan (station, point, axis and tool columns of a "
        "measurement table; a length column, if present, is used only for the "
        "start stations of the export-time identifiability analysis) fixes the "
        "problem size and the variables held fixed; the data stay free.",
    )
    p.add_argument(
        "--model",
        required=True,
        metavar="M",
        help="bundled model name (see `volcal models`) or model TOML file",
    )
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument(
        "--plan", type=Path, metavar="P.csv", help="measurement plan or measurement table (CSV)"
    )
    what.add_argument(
        "--model-only",
        action="store_true",
        help="export the model function alone (tool point, volumetric error, "
        "Jacobians) for controllers",
    )
    p.add_argument(
        "--stations",
        type=Path,
        metavar="S.csv",
        help="stations table: start values and fixed stations; required when the "
        "plan has no length column",
    )
    p.add_argument(
        "--strategy",
        default="joint",
        choices=["joint", "two-phase", "points-only"],
        help="identification strategy (default joint)",
    )
    add_degree(p)
    add_datum(p)
    p.add_argument(
        "--budget",
        default="paper002",
        metavar="NAME|FILE",
        help="uncertainty budget weighting readings without sigma (default paper002)",
    )
    p.add_argument(
        "--exact", action="store_true", help="exact rotations instead of the first-order model"
    )
    p.add_argument("--name", metavar="ID", help="C prefix of the export (default volcal_<model>)")
    p.add_argument(
        "--linsol",
        default="ldl",
        choices=["ldl", "qr"],
        help="linear solver of the Gauss-Newton system (default ldl)",
    )
    p.add_argument("--no-build", action="store_true", help="write the files, do not run make")
    p.add_argument(
        "--force", action="store_true", help="regenerate even when an unchanged export exists"
    )
    p.add_argument("--cc", default="gcc", help="C compiler for the build (default gcc)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="export folder")
    p.set_defaults(func=run)
    return p


def _check_out(args) -> None:
    """The export folder, checked before anything is generated: never a file, never a
    folder of other files (an export writes its own names into it), never the plan."""
    from volcal.base.exceptions import InputError
    from volcal.outputs.codegen.export import MANIFEST

    out = args.out.resolve()
    if out.exists() and not out.is_dir():
        raise InputError("expected a folder for the export, got a file", source=str(out))
    plan = getattr(args, "plan", None)
    if plan is not None and Path(plan).resolve().parent == out:
        raise InputError(
            "the plan lies in the export folder, whose files an export "
            "replaces; choose another folder",
            source=str(out),
        )
    if out.is_dir() and any(out.iterdir()) and not (out / MANIFEST).is_file():
        raise InputError(
            "the folder holds files that are not a volcal export; choose a new or empty folder",
            source=str(out),
        )


def run(args: argparse.Namespace) -> int:
    from volcal.base.exceptions import InputError
    from volcal.outputs.codegen import export_model, export_solver

    if args.degree < 0:
        raise InputError(f"expected a degree >= 0, got {args.degree}", source="--degree")
    _check_out(args)
    # the options both exports take
    common: dict[str, Any] = dict(
        degree=args.degree,
        datum=args.datum,
        exact=args.exact,
        name=args.name,
        build_it=not args.no_build,
        force=args.force,
        cc=args.cc,
    )
    try:
        if args.model_only:
            if args.stations is not None:
                raise InputError(
                    "--stations applies to a solver export, not --model-only", source="--stations"
                )
            info = export_model(args.model, args.out, **common)
        else:
            info = export_solver(
                args.model,
                args.plan,
                args.out,
                stations=args.stations,
                strategy=args.strategy,
                budget=args.budget,
                linsol=args.linsol,
                **common,
            )
    except RuntimeError as exc:  # the C build failed: report, exit 1
        print(f"volcal codegen: {exc}", file=sys.stderr)
        return 1
    if not getattr(args, "quiet", False):
        what = "model" if info.kind == "model" else "solver"
        state = (
            "reused unchanged export" if info.reused else f"exported in {info.export_seconds:.1f} s"
        )
        built = "" if info.build_seconds is None else f", built in {info.build_seconds:.1f} s"
        print(f"C {what} '{info.name}': {state}{built}")
        if info.kind == "solver":
            for ph in info.manifest["phases"]:
                print(
                    f"  phase {ph['name']}: {ph['n_reduced']} free variables after the "
                    f"datum constraints; held fixed: {len(ph['fixed'])}"
                )
        print(f"wrote {info.path} (see README.md there)")
        if info.build_seconds is not None:
            print(
                f"run: {info.example} "
                + (
                    "MEASUREMENTS.csv OUTDIR"
                    if info.kind == "solver"
                    else "PARAMETERS.csv POSES.csv"
                )
            )
    return 0
