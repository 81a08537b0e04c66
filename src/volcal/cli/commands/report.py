"""``volcal report``: one self-contained HTML report of an identification, for a customer.

Examples::

    volcal report --result result/ --out report.html
    volcal report --result result/ --compensation comp/ --title "Machine 7, May 2025" --out r.html
    volcal report --result result/ --pdf --out report.pdf

The report holds the model, the data summary, the datum in force, the identification with
its model adequacy verdict (a fit that does not fit says so in a red banner), what the
data do not determine, the uncertainties, every parameter (six significant digits), the
plots of the result folder (those it lacks, e.g. written with ``volcal identify
--no-plots``, are drawn from the saved result: the same figures) and, with
``--compensation``, the summary of a ``volcal compensate`` export, and with ``--compare``
the table and plot of a ``volcal compare`` folder (given a compare folder as ``--result``,
the report is of its reference result with the comparison).  It is one file: CSS
inline, plots embedded as data URIs, no script, no external address.  Everything is
read from the folders; nothing is identified again.  See :mod:`volcal.outputs.html_report`.

``--pdf`` prints it to PDF (``--out`` with the suffix ``.pdf``) through a headless
Chromium (chromium, chromium-browser or google-chrome on the PATH).  The input folders are
only read; the output file is written atomically and an existing one is replaced only with
``--force``.  Exit codes: 0 success, 2 bad input (a missing folder, a folder that is not
a result, no browser for ``--pdf``; the message names the folder or option).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "report",
        help="one self-contained HTML (or PDF) report of an identification result",
        description="Write one self-contained HTML document from a result folder of `volcal "
        "identify` (and optionally a `volcal compensate` export) to hand to a customer: "
        "model, data, datum, identification and model adequacy, what the data do "
        "not determine, uncertainties, every parameter, the plots and the "
        "compensation summary. No external files or scripts; plots are embedded. "
        "--pdf prints it to PDF with a headless Chromium.",
    )
    p.add_argument(
        "--result",
        required=True,
        type=Path,
        metavar="DIR",
        help="result folder written by `volcal identify` (only read)",
    )
    p.add_argument(
        "--compensation",
        type=Path,
        metavar="DIR",
        default=None,
        help="folder written by `volcal compensate` from this result: add its summary (only read)",
    )
    p.add_argument(
        "--compare",
        type=Path,
        metavar="DIR",
        default=None,
        help="folder written by `volcal compare` for the same model: add its strategies "
        "table and plot (only read; found by itself when --result is that folder or the "
        "reference result inside it)",
    )
    p.add_argument(
        "--out", required=True, type=Path, metavar="FILE", help="output file (e.g. report.html)"
    )
    p.add_argument("--title", default=None, help="document title (default: the model's name)")
    p.add_argument(
        "--pdf",
        action="store_true",
        help="print to PDF with a headless Chromium; the output gets the suffix .pdf",
    )
    p.add_argument(
        "--no-plots",
        action="store_true",
        help="leave the plots out (by default the result folder's plots are embedded and "
        "those it lacks are drawn from the saved result)",
    )
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from volcal.base.exceptions import InputError
    from volcal.outputs.html_report import (
        find_browser,
        find_comparison,
        missing_plots,
        write_report,
    )

    out: Path = args.out.with_suffix(".pdf") if args.pdf else args.out
    if out.is_dir():
        raise InputError("expected a file name, got a folder", source="--out")
    if out.exists() and not getattr(args, "force", False):
        raise InputError(
            "the file exists; choose another name or pass --force to replace it",
            source=str(out),
        )
    if args.pdf and find_browser() is None:
        # the same message write_report gives, but before any reading
        raise InputError(
            "no browser engine is installed to print the PDF (looked for chromium, "
            "chromium-browser and google-chrome on the PATH); install Chromium or write the "
            "HTML report and print it from a browser",
            source="--pdf",
        )
    from volcal.outputs.plot_process import plotting

    # plots to draw: two children import matplotlib while this process reads the result,
    # then draw the figures two at a time
    result_dir, _ = find_comparison(args.result, args.compare)
    draws = not args.no_plots and result_dir.is_dir() and bool(missing_plots(result_dir))
    with plotting(draws) as plotter:
        written = write_report(
            args.result,
            args.out,
            compensation_dir=args.compensation,
            compare_dir=args.compare,
            pdf=args.pdf,
            title=args.title,
            plots=not args.no_plots,
            plotter=plotter,
        )
    if not getattr(args, "quiet", False):
        print(f"wrote {written} ({written.stat().st_size / 1024:.0f} kB)")
    return 0
