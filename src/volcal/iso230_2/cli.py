"""``volcal iso230-2``: ISO 230-2 evaluation and paper 003's polynomial model from a CSV."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)

_DESCRIPTION = """\
Evaluate laser-interferometer positioning readings by ISO 230-2:2014 (per axis: mean
deviations, s, reversal, repeatability, systematic deviation, accuracy) and fit paper 003's
polynomial model of the positional deviation with its uncertainty. DATA.csv holds one row
per reading: axis, target_mm (or target_deg), cycle, direction (+/-), and deviation_um or
actual_mm (rotary: deviation_arcsec or actual_deg). With --plane, DATA.csv is a plane table
(p_mm, r_mm, cycle, deviation_um) fitted by paper 003's two-axis model (eq. 13).
Writes parameters.csv, targets.csv, polynomial.csv, correction_table.csv, report.md and
iso230_2.png into --out (plane: plane_*.csv, report.md, plane.png).
The instrument MPE becomes a standard uncertainty MPE/sqrt(3) (rectangular distribution),
fully correlated over all readings."""


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "iso230-2",
        help="ISO 230-2 positioning evaluation with a polynomial error model",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "data", nargs="?", metavar="DATA.csv", help="readings table (CSV); see docs/iso230_2.md"
    )
    p.add_argument(
        "--example",
        action="store_true",
        help="evaluate the bundled example data set (11 targets x 5 cycles, 750 mm)",
    )
    p.add_argument(
        "--out",
        metavar="DIR",
        help="output folder (default: <DATA name>_iso230_2 in the current folder)",
    )
    p.add_argument(
        "--degree",
        type=int,
        default=3,
        help="polynomial degree per direction (default 3, as in paper 003)",
    )
    p.add_argument(
        "--mpe-um",
        type=float,
        default=0.0,
        metavar="UM",
        help="instrument maximum permissible error, linear axes [um] (default 0)",
    )
    p.add_argument(
        "--mpe-ppm",
        type=float,
        default=0.0,
        metavar="PPM",
        help="length-proportional instrument MPE [um/m], zeroed at the first target (default 0)",
    )
    p.add_argument(
        "--mpe-arcsec",
        type=float,
        default=0.0,
        metavar="ARCSEC",
        help="instrument maximum permissible error, rotary axes [arcsec]",
    )
    p.add_argument(
        "--resolution-um",
        type=float,
        default=0.0,
        metavar="UM",
        help="reading resolution r [um]: u of each mean is at least r/sqrt(12)",
    )
    p.add_argument(
        "--resolution-arcsec",
        type=float,
        default=0.0,
        metavar="ARCSEC",
        help="reading resolution of rotary axes [arcsec]",
    )
    p.add_argument(
        "--spacing-mm",
        type=float,
        metavar="MM",
        help="spacing of the correction table, linear axes [mm] "
        "(default: a 1-2-5 step giving about 50 intervals)",
    )
    p.add_argument(
        "--spacing-deg",
        type=float,
        metavar="DEG",
        help="spacing of the correction table, rotary axes [deg]",
    )
    p.add_argument(
        "--k",
        type=float,
        default=2.0,
        help="coverage factor of the expanded uncertainties (default 2)",
    )
    p.add_argument(
        "--type-a",
        choices=("gum-s1", "paper"),
        default="gum-s1",
        help="standard uncertainty of each mean deviation: gum-s1 (default, "
        "sqrt((n-1)/(n-3)) s/sqrt(n), GUM Supplement 1) or paper "
        "(s/sqrt(n), paper 003 eq. 10; its k = 2 band undercovers for n = 5)",
    )
    p.add_argument(
        "--plane",
        action="store_true",
        help="DATA.csv is a plane table: fit paper 003's two-axis model (eq. 13)",
    )
    p.add_argument(
        "--degree-r",
        type=int,
        default=None,
        help="with --plane: degree in the second coordinate R (default: --degree)",
    )
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from volcal.base.exceptions import InputError

    if args.example and args.data:
        raise InputError("give either DATA.csv or --example, not both", source="arguments")
    if args.example:
        from . import example_path

        if args.plane:
            raise InputError(
                "--example is a single-axis data set; it cannot be used with --plane",
                source="arguments",
            )
        data = example_path()
    elif args.data:
        data = Path(args.data)
    else:
        raise InputError("no data: give DATA.csv (or --example)", source="arguments")
    out = Path(args.out) if args.out else Path.cwd() / f"{Path(data).stem}_iso230_2"
    quiet = getattr(args, "quiet", False)
    # the output folder before any computing
    from volcal.base.folders import check_out_dir

    if args.plane:
        from .plane import PLANE_FILES as _files
    else:
        from .report import OUTPUT_FILES as _files
    check_out_dir(
        out, _files, "volcal iso230-2 --plane" if args.plane else "volcal iso230-2", inputs=[data]
    )

    if args.plane:
        from .plane import evaluate_plane, write_plane_report

        plane = evaluate_plane(
            data,
            degree_p=args.degree,
            degree_r=args.degree if args.degree_r is None else args.degree_r,
            mpe_um=args.mpe_um,
            k=args.k,
            resolution_um=args.resolution_um,
            type_a=args.type_a,
        )
        for w in plane.warnings:
            log.warning(w)
        path = write_plane_report(plane, out, spacing_mm=args.spacing_mm)
        if not quiet:
            print(
                f"wrote {path}: plane_parameters.csv, plane_polynomial.csv, plane_grid.csv, "
                "plane_means.csv, report.md, plane.png"
            )
        return 0

    from .evaluate import evaluate
    from .report import OUTPUT_FILES, write_report

    result = evaluate(
        data,
        degree=args.degree,
        mpe_um=args.mpe_um,
        mpe_ppm=args.mpe_ppm,
        mpe_arcsec=args.mpe_arcsec,
        k=args.k,
        resolution_um=args.resolution_um,
        resolution_arcsec=args.resolution_arcsec,
        type_a=args.type_a,
    )
    for w in result.warnings:
        log.warning(w)
    path = write_report(result, out, spacing_mm=args.spacing_mm, spacing_deg=args.spacing_deg)
    if not quiet:
        for ax in result.axes:
            du, ds = ax.units.deviation, ax.units.deviation_scale
            i = ax.iso
            print(
                f"axis {ax.axis}: E = {i.E * ds:.4g} {du}, M = {i.M * ds:.4g} {du}, "
                f"A = {i.A * ds:.4g} {du}, R = {i.R * ds:.4g} {du}, B = {i.B * ds:.4g} {du}"
            )
        print(f"wrote {path}: {', '.join(OUTPUT_FILES)}")
    return 0
