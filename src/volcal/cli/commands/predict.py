"""``volcal predict``: volumetric errors at given poses from an identification result.

Example::

    volcal predict --result result/ --points poses.csv --out errors.csv

The points table holds one column per model axis (mm / deg), optionally ``tool_x,
tool_y, tool_z`` (mm, default 0) and a ``point`` id.  The output repeats those columns
and adds ``dx_um, dy_um, dz_um`` (the error: actual - nominal tool point, machine frame)
and their standard uncertainties ``u_dx_um, u_dy_um, u_dz_um``.  Without ``--out`` the
table goes to standard output as CSV.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import tempfile
from pathlib import Path

log = logging.getLogger(__name__)


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "predict",
        help="volumetric errors at given poses from an identification result",
        description="Predict the volumetric error (actual - nominal tool point, um) and its "
        "standard uncertainty at the poses of a points table, from the "
        "result.json that `volcal identify` wrote.",
    )
    p.add_argument(
        "--result",
        required=True,
        type=Path,
        metavar="DIR",
        help="result folder written by `volcal identify`",
    )
    p.add_argument(
        "--points",
        required=True,
        type=Path,
        metavar="P.csv",
        help="poses: one column per axis (mm / deg), optional tool_x, tool_y, "
        "tool_z (mm) and point",
    )
    p.add_argument(
        "--out", type=Path, metavar="V.csv", help="output CSV (default: standard output)"
    )
    p.add_argument(
        "--no-uncertainty",
        action="store_true",
        help="leave out the u_dx_um, u_dy_um, u_dz_um columns",
    )
    p.set_defaults(func=run)
    return p


def _write_csv(df, out: Path) -> None:
    """Write-then-rename: a reader never sees a half-written file."""
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.tmp-", dir=out.parent)
    try:
        with os.fdopen(fd, "w", newline="", encoding="utf-8") as fh:
            df.to_csv(fh, index=False)
        mask = os.umask(0o022)
        os.umask(mask)
        os.chmod(tmp, 0o666 & ~mask)  # mkstemp makes it private; follow the umask
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def run(args: argparse.Namespace) -> int:
    from volcal.base.exceptions import InputError
    from volcal.outputs.results import RESULT_FILES, load_result

    if args.out is not None:
        out = args.out.resolve()
        if args.points.exists() and out == args.points.resolve():
            raise InputError(
                "the output would overwrite the points file; choose another name", source="--out"
            )
        if out.parent == args.result.resolve() and out.name in RESULT_FILES:
            raise InputError(
                "the output would overwrite a file of the result folder", source="--out"
            )
        if out.is_dir():
            raise InputError("expected a file name, got a folder", source="--out")
        if out.exists() and not getattr(args, "force", False):
            raise InputError(
                "the file exists; choose another name or pass --force to replace it",
                source=str(out),
            )
    log.info("loading %s", args.result)
    res = load_result(args.result)
    log.info("predicting at the poses of %s", args.points)
    table = res.predict(args.points, with_uncertainty=not args.no_uncertainty)
    if args.out is None:
        # printed: six significant digits (the file written with --out keeps full precision)
        table.to_csv(sys.stdout, index=False, float_format="%.6g")
    else:
        _write_csv(table, args.out)
        if not getattr(args, "quiet", False):
            print(f"wrote {len(table)} predictions to {args.out}")
    return 0
