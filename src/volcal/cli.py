"""The ``volcal`` command line.

Each subcommand lives next to the code it drives and registers itself through an
``add_parser(subparsers)`` function listed in ``_COMMANDS``; the handler it sets as
``func`` returns a process exit code.  Exit codes: 0 success, 1 a computation that ran
but failed (solver did not converge, ...), 2 bad usage or bad input.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import sys

# module path of each command's ``add_parser``; kept as strings so that ``volcal --help``
# does not import CasADi or SymPy.
_COMMANDS = [
    "volcal.commands.models",
    "volcal.iso230_2.cli",
    "volcal.commands.simulate",
    "volcal.commands.demo",
    "volcal.commands.identify",
    "volcal.commands.predict",
    "volcal.commands.codegen",
    "volcal.commands.analyze",
    "volcal.commands.mc",
]


from volcal.exceptions import InputError, SolverError


class UserError(Exception):
    """An error caused by the user's input: printed without a traceback, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="volcal",
        description="Identify machine-tool geometric errors from multilateration length data.",
    )
    parser.add_argument("-q", "--quiet", action="store_true", help="print only errors")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more output (repeat for debug output)")
    from volcal import __version__
    parser.add_argument("--version", action="version", version=f"volcal {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for modname in _COMMANDS:
        importlib.import_module(modname).add_parser(sub)
    # -q / -v also after the command name (`volcal identify ... -q`); SUPPRESS keeps a
    # value given before the command when the command line does not repeat it
    for cmd in sub.choices.values():
        cmd.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                         help="print only errors")
        cmd.add_argument("-v", "--verbose", action="count", default=argparse.SUPPRESS,
                         help="more output (repeat for debug output)")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.ERROR if args.quiet else (logging.DEBUG if args.verbose > 1 else
                                              logging.INFO if args.verbose else logging.WARNING)
    logging.basicConfig(level=level, format="%(levelname)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    # small dense problems: one BLAS thread is much faster than a contended pool
    from volcal.threads import set_blas_threads
    set_blas_threads(1)
    try:
        return int(args.func(args) or 0)
    except (UserError, InputError, FileNotFoundError) as exc:
        # Validation errors carry file/row/column in their message: no traceback.
        print(f"volcal {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except SolverError as exc:
        print(f"volcal {args.command}: solver failed: {exc}", file=sys.stderr)
        return 1
    except BrokenPipeError:
        # output piped into e.g. `head`, which closed early: not an error of ours
        sys.stderr.close()
        return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
