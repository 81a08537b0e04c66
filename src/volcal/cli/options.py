"""Command-line options several ``volcal`` subcommands share, defined once so that their
names, defaults and help read the same everywhere.

Only :mod:`argparse` and :mod:`pathlib` here: the parsers are built for ``volcal --help``,
which must stay light.
"""

from __future__ import annotations

import argparse
from pathlib import Path

#: help of ``--model`` where the command does not point to ``volcal models``
MODEL_HELP = "bundled model name or model TOML file"
#: help of ``--model`` pointing to the list of bundled models
MODEL_LIST_HELP = "bundled model name (see `volcal models`) or model TOML file"


def add_model_or_example(
    p: argparse.ArgumentParser, example_help: str, model_help: str = MODEL_HELP
) -> argparse._MutuallyExclusiveGroup:
    """The required choice ``--model M`` | ``--example NAME`` (what the example brings is
    ``example_help``); returns the group so that a command can add ``--result``."""
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--model", metavar="M", help=model_help)
    src.add_argument("--example", metavar="NAME", help=example_help)
    return src


def add_result(src: argparse._MutuallyExclusiveGroup, then: str) -> None:
    """``--result DIR``: a result folder of ``volcal identify`` whose data are identified
    again with its options; ``then`` says what the command does next."""
    src.add_argument(
        "--result",
        type=Path,
        metavar="DIR",
        help="a result folder of `volcal identify`: its data are identified "
        f"again with its options{then}",
    )


def add_sim_seed(p: argparse.ArgumentParser) -> None:
    """``--sim-seed N``: the seed of an example's simulated data."""
    p.add_argument(
        "--sim-seed",
        type=int,
        default=None,
        metavar="N",
        help="with --example: seed of the simulated data (default: the example's)",
    )


def add_example_budget(p: argparse.ArgumentParser) -> None:
    """``--budget NAME|FILE``, by default the example's, else paper002."""
    p.add_argument(
        "--budget",
        metavar="NAME|FILE",
        help="uncertainty budget (default paper002, or the example's)",
    )


def add_degree(p: argparse.ArgumentParser) -> None:
    """``--degree N``: the Legendre degree of the error motions, default 3."""
    p.add_argument(
        "--degree",
        type=int,
        default=3,
        metavar="N",
        help="Legendre degree of the error motions (default 3)",
    )


def add_datum(p: argparse.ArgumentParser, *, described: bool = True) -> None:
    """``--datum iso230|reference|none`` (default iso230); ``described=False`` gives it no
    help line of its own."""
    p.add_argument(
        "--datum",
        default="iso230",
        choices=("iso230", "reference", "none"),
        help="datum convention (default iso230)" if described else None,
    )
