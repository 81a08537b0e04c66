"""``volcal compensate``: compensation files a controller reads, from an identification.

Examples::

    volcal compensate --result result/ --format isg --out comp_isg/
    volcal compensate --result result/ --format siemens --target 828d --out comp_840/
    volcal compensate --result result/ --format heidenhain --table-tool 0,0,-120 --out comp/
    volcal compensate --result result/ --format generic --tolerance 0.5 --tool 0,0,0 --out g/

Formats: ``isg`` (Beckhoff TwinCAT CNC / ISG volumetric compensation: ISG CSV files and
the .lis list), ``siemens`` (SINUMERIK CEC and LEC init programs), ``heidenhain`` (*.COM
tables and the *.CMA assignment), ``generic`` (ISO 230-1 error tables per axis and a
volumetric correction grid as CSV and .npz).  See :mod:`volcal.outputs.compensation` and
docs/compensation.md.  The result folder is only read; the output folder is written
atomically (``--force`` replaces an earlier export).  Exit codes: 0 success, 2 bad input
or a compensation that exceeds the controller's limits (the message names the limit).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)

_FORMATS = ("isg", "siemens", "heidenhain", "generic")


def _tool(text: str) -> list[float]:
    parts = [p.strip() for p in str(text).split(",")]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        vals = []
    if len(vals) != 3 or not all(v == v and abs(v) != float("inf") for v in vals):
        raise argparse.ArgumentTypeError(f"expected X,Y,Z in mm (three numbers), got {text!r}")
    return vals


def _axis(text: str) -> tuple[str, str]:
    name, eq, ident = str(text).partition("=")
    if not eq or not name.strip() or not ident.strip():
        raise argparse.ArgumentTypeError(f"expected AXIS=ID (e.g. X=X1 or C=4), got {text!r}")
    return name.strip(), ident.strip()


def _datum(text: str) -> tuple[str, float]:
    name, eq, val = str(text).partition("=")
    try:
        v = float(val)
    except ValueError:
        v = float("nan")
    if not eq or not name.strip() or not (v == v and abs(v) != float("inf")):
        raise argparse.ArgumentTypeError(f"expected AXIS=VALUE (e.g. X=-400), got {text!r}")
    return name.strip(), v


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "compensate",
        help="compensation files for a controller (ISG/TwinCAT, SINUMERIK, HEIDENHAIN, "
        "generic grid)",
        description="Write the compensation files a controller reads from an identification "
        "result: isg (TwinCAT CNC volumetric compensation), siemens (SINUMERIK "
        "CEC/LEC tables), heidenhain (nonlinear axis error compensation *.COM / "
        "*.CMA) or generic (ISO 230-1 tables and a volumetric correction grid). "
        "Grid spacing follows the error's curvature to meet --tolerance; every "
        "file states whether it holds errors or corrections and what the format "
        "cannot carry, and compensation.md reports the residual error after "
        "compensation over the travel and the measurement's tool offsets.",
    )
    p.add_argument(
        "--result",
        required=True,
        type=Path,
        metavar="DIR",
        help="result folder written by `volcal identify` (only read)",
    )
    p.add_argument("--format", required=True, choices=_FORMATS, help="output format")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder")
    p.add_argument(
        "--tolerance",
        type=float,
        default=None,
        metavar="UM",
        help="largest interpolation error at the tool point the grid spacing must "
        "meet, um (default 0.1; generic: the smallest of 0.1 ... 10 whose grid fits "
        "--max-points, reported)",
    )
    p.add_argument(
        "--tool",
        type=_tool,
        action="append",
        metavar="X,Y,Z",
        help="tool offset (mm, tool frame) of the residual report and of the "
        "generic grids; repeatable (default: the tool offsets of the "
        "measurement)",
    )
    p.add_argument(
        "--table-tool",
        type=_tool,
        default=[0.0, 0.0, 0.0],
        metavar="X,Y,Z",
        help="tool offset the siemens / heidenhain tables are built for (default "
        "0,0,0: the spindle reference point)",
    )
    p.add_argument(
        "--sign",
        choices=("correction", "error"),
        default="correction",
        help="what the generic grid holds: correction (-error, default) or error "
        "(siemens and heidenhain follow the sign their manuals document)",
    )
    p.add_argument(
        "--machine-datum",
        type=_datum,
        action="append",
        metavar="AXIS=VALUE",
        help="siemens, heidenhain: position (mm / deg) of the model's zero of an axis in "
        "the control's machine coordinates; table positions are model positions plus "
        "this (default 0, stated in the files); repeatable",
    )
    p.add_argument(
        "--general-axis-names",
        action="store_true",
        help="siemens: name the machine axes AX1, AX2, ... (X, Y, Z, then the rotary "
        "axes) for multi-channel controls; --axis still wins",
    )
    p.add_argument(
        "--control-dir",
        default=None,
        metavar="PATH",
        help="isg, heidenhain: the folder of the files on the control, written into the "
        ".lis / .CMA (default: bare file names)",
    )
    p.add_argument(
        "--axis",
        type=_axis,
        action="append",
        metavar="AXIS=ID",
        help="controller axis identifier of a model axis, repeatable: ISG logical "
        "axis number, SINUMERIK machine axis name (default X1 ...), "
        "HEIDENHAIN axis key",
    )
    p.add_argument(
        "--target",
        choices=("840d", "828d"),
        default=None,
        help="siemens: the control whose limits apply (840d: 62 CEC tables of "
        "2000 points; 828d: 8 tables of 200 points; default 840d)",
    )
    p.add_argument(
        "--max-points",
        type=int,
        default=None,
        metavar="N",
        help="points per table (siemens CEC, heidenhain: default 256), data "
        "records (isg) or grid points (generic: default 2,000,000) allowed",
    )
    p.add_argument(
        "--max-tables",
        type=int,
        default=None,
        metavar="N",
        help="tables allowed (siemens CEC, heidenhain: default 8)",
    )
    p.add_argument(
        "--tool-direction",
        default="-z",
        choices=("+x", "-x", "+y", "-y", "+z", "-z"),
        help="isg: tool zero orientation N0 (default -z)",
    )
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from volcal.base.exceptions import InputError
    from volcal.base.folders import check_out_dir
    from volcal.outputs.compensation import compensate

    for name in ("max_points", "max_tables"):
        v = getattr(args, name)
        if v is not None and v < 1:
            raise InputError(
                f"expected a positive integer, got {v}", source="--" + name.replace("_", "-")
            )
    if args.tolerance is not None and not (args.tolerance > 0 and args.tolerance != float("inf")):
        raise InputError(
            f"expected a tolerance > 0 um, got {args.tolerance:g}", source="--tolerance"
        )
    if args.target is not None and args.format != "siemens":
        raise InputError("--target applies to --format siemens only", source="--target")
    # a bad output folder costs no computing time
    check_out_dir(
        args.out,
        (),
        "a compensation export (volcal compensate)",
        "compensation.json",
        inputs=[args.result],
    )
    axes = dict(args.axis or [])
    comp = compensate(
        args.result,
        args.format,
        args.out,
        tolerance_um=args.tolerance,
        tools=args.tool,
        table_tool=args.table_tool,
        sign=args.sign,
        axis_names=axes,
        max_points=args.max_points,
        max_tables=args.max_tables,
        target=args.target,
        tool_direction=args.tool_direction,
        machine_datum=dict(args.machine_datum or []),
        general_axis_names=args.general_axis_names,
        control_dir=args.control_dir,
    )
    if not getattr(args, "quiet", False):
        print(f"{comp.title}")
        print(
            f"wrote {len(comp.files)} file(s) to {args.out}: {', '.join(comp.files)} "
            "(+ compensation.md, compensation.json)"
        )
        print(f"values: {comp.values}")
        print(comp.spacing_line())
        print(comp.residual_line())
        for line in comp.setup_lines():
            print(line)
        for n in comp.notes:
            print(f"note: {n}")
        for r in comp.per_tool.itertuples():
            print(
                f"  tool ({r.tool_x_mm:g}, {r.tool_y_mm:g}, {r.tool_z_mm:g}) mm: "
                f"uncorrected {r.uncorrected_rms_um:.3f} um RMS, residual "
                f"{r.residual_rms_um:.3f} um RMS ({100 * r.ratio:.2f} %), max "
                f"{r.residual_max_um:.3f} um"
            )
        for n in comp.not_carried:
            print(f"not carried: {n}")
    return 0
