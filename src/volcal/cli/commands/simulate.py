"""``volcal simulate``: simulated multilateration data with its ground truth.

Examples::

    volcal simulate --example mcv754 --seed 1 --out sim/
    volcal simulate --model head_bc --max-volumetric-um 60 --plan grid --grid 4 \\
        --tools "0,0,-100;50,0,-100;0,50,-100" --budget paper002 --seed 7 --out sim_bc/

Writes measurements.csv, stations.csv (the true stations), true_parameters.csv (um /
urad), true_volumetric.csv and simulation.json to ``--out`` (and with ``--instruments
interferometer,ballbar`` interferometer.csv and ballbar.csv of the same true machine;
``--instruments interferometer=plan/added_interferometer.csv`` fills in a planned table) (see
:func:`volcal.measurement.simulate.save_simulation`).
"""

from __future__ import annotations

import argparse
import logging
import re
from pathlib import Path
from typing import Any

from volcal.cli.options import MODEL_LIST_HELP, add_degree, add_model_or_example

log = logging.getLogger(__name__)

_DEFAULT_TOOLS = "0,0,0;0,0,-100;80,0,-100;0,80,-100"


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "simulate",
        help="simulate multilateration length data from true error motions",
        description="Simulate a sequential multilateration measurement: machine model + true "
        "error motions + stations + plan + tool offsets + budget + seed -> "
        "measurement table, with the true parameters and true volumetric errors "
        "beside it.  Actual tool points come from the exact model; the axis "
        "repeatability is drawn anew for every station visit; a seed always gives "
        "the same data.",
    )
    add_model_or_example(
        p,
        "use a bundled example (e.g. mcv754): its model, true parameters, "
        "stations, plan, tools and budget; the options below override parts",
        MODEL_LIST_HELP,
    )
    truth = p.add_mutually_exclusive_group()
    truth.add_argument(
        "--true-parameters",
        metavar="FILE",
        type=Path,
        help="true parameters, CSV `name, value, unit` (um/urad/mm/rad ...); "
        "parameters not listed are zero",
    )
    truth.add_argument(
        "--max-volumetric-um",
        type=float,
        metavar="UM",
        help="draw realistic true errors (with the seed) scaled to this maximum "
        "volumetric error over the workspace, um (default 60)",
    )
    add_degree(p)
    p.add_argument(
        "--stations",
        metavar="S.csv",
        type=Path,
        help="true stations (station, x_mm, y_mm, z_mm[, dead_length_mm]); default: "
        "six stations around the workspace at two heights",
    )
    p.add_argument(
        "--plan",
        metavar="default|grid|lines|diagonals|FILE.csv",
        help="measurement plan: the default (a grid over the travel; with rotary "
        "axes a linear-axis grid plus rotary sweeps over the whole travel at "
        "several linear and rotary positions, see "
        "volcal.measurement.plans.default_plan), "
        "a grid over the travel, lines along the axes, the ISO 230-6 body "
        "diagonals, a CSV of poses (axis columns, mm/deg), or a measurement plan "
        "(measurement_plan.csv of `volcal plan`: its poses, tool offsets and stations "
        "in its order; the station positions from --stations, by default the "
        "stations.csv beside it)",
    )
    p.add_argument(
        "--grid",
        metavar="N",
        help="positions per axis: N for every linear axis (rotary axes coarser), or "
        "per axis as X=6,Y=5,Z=5; for lines/diagonals the points per line "
        "(default 5 for a grid, 11 for lines/diagonals)",
    )
    p.add_argument(
        "--tools",
        metavar='"x,y,z;x,y,z"',
        help=f"tool (reflector) offsets in mm, separated by ';' (default \"{_DEFAULT_TOOLS}\")",
    )
    p.add_argument(
        "--budget",
        metavar="NAME|FILE",
        help="uncertainty budget: bundled name or TOML file (default paper002)",
    )
    p.add_argument(
        "--no-noise",
        action="store_true",
        help="exact lengths: no length noise, no axis repeatability",
    )
    p.add_argument("--drift", action="store_true", help="add the budget's drift model")
    p.add_argument(
        "--instruments",
        metavar="NAME[=FILE],...",
        help="also write other instruments' readings of the same true machine: "
        "interferometer (interferometer.csv: a line along every linear axis through the "
        "middle of the travel, 0.1 um) and/or ballbar (ballbar.csv: a circle in every "
        "plane of two linear axes, 0.5 um), first tool offset; or NAME=FILE: the lines / "
        "circles of a planned table in the instrument's format, its reading column filled "
        "in (e.g. interferometer=plan/added_interferometer.csv of `volcal plan "
        "--add-minutes`); see docs/instruments.md",
    )
    p.add_argument(
        "--seed",
        type=int,
        required=True,
        metavar="N",
        help="seed of the random numbers (same seed -> same data)",
    )
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="DIR",
        help="output folder (created; a previous simulation is replaced with --force)",
    )
    p.set_defaults(func=run)
    return p


#: the plans --plan names (anything else is a file)
PLAN_KINDS = ("default", "grid", "lines", "diagonals")


def _named_plan(kind: str, spec, counts, degree: int):
    """The plan of a kind in :data:`PLAN_KINDS` for machine ``spec``: ``counts`` from
    :func:`_grid_counts` (positions per axis or points per line), ``degree`` the error
    motions' degree the default plan is made for."""
    from volcal.measurement.plans import default_plan, diagonal_plan, grid_plan, line_plan

    if kind == "default":
        return default_plan(spec, degree)
    return {"grid": grid_plan, "lines": line_plan, "diagonals": diagonal_plan}[kind](spec, counts)


def _grid_counts(text: str | None, plan: str):
    from volcal.base.exceptions import InputError

    if plan == "default":
        if text is not None:
            raise InputError(
                "--grid applies to --plan grid, lines or diagonals, not to the default plan",
                source="--grid",
            )
        return None
    if text is None:
        return 5 if plan == "grid" else 11
    text = text.strip()
    if re.fullmatch(r"\d+", text):
        return int(text)
    if plan != "grid":
        raise InputError(f"expected one number of points per line, got {text!r}", source="--grid")
    out = {}
    for item in text.split(","):
        m = re.fullmatch(r"\s*([A-Z][A-Z0-9]{0,3})\s*=\s*(\d+)\s*", item)
        if not m:
            raise InputError(
                f"expected N or AXIS=N,AXIS=N (e.g. X=6,Y=5,Z=5), got {text!r}", source="--grid"
            )
        out[m.group(1)] = int(m.group(2))
    return out


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from volcal.base.exceptions import InputError
    from volcal.measurement.plans import (
        default_stations,
        is_measurement_plan,
        measurement_plan_from_csv,
        plan_from_csv,
    )
    from volcal.measurement.simulate import (
        draw_true_parameters,
        example,
        load_true_parameters,
        parse_tools,
        save_simulation,
        simulate,
    )
    from volcal.model.errors import ErrorForm, ErrorModel
    from volcal.model.machine import Machine

    if args.seed < 0:
        raise InputError(f"expected a non-negative seed, got {args.seed}", source="--seed")
    if args.degree < 0:
        raise InputError(f"expected a degree >= 0, got {args.degree}", source="--degree")
    # parse cheap options first: a typo fails before any model is built
    tools = parse_tools(args.tools) if args.tools is not None else None
    extra: dict[str, Path | None] = {}
    for w in (args.instruments or "").split(","):
        name, eq, path = (x.strip() for x in w.partition("="))
        if not name:
            continue
        if name not in ("interferometer", "ballbar") or (eq and not path):
            raise InputError(
                f"unknown instrument {w.strip()!r}; expected interferometer and/or ballbar, "
                "each optionally =FILE (a planned table)",
                source="--instruments",
            )
        if name in extra:
            raise InputError(f"{name} given twice", source="--instruments")
        extra[name] = Path(path) if eq else None
        if eq and not Path(path).is_file():
            raise InputError(f"no such {name} table file", source=path)
    # no --plan: the default plan, or a grid when only --grid is given
    plan_kind = args.plan or ("grid" if args.grid is not None else "default")
    if plan_kind in PLAN_KINDS:
        counts = _grid_counts(args.grid, plan_kind)
    elif args.grid is not None:
        raise InputError(
            "--grid applies to --plan grid, lines or diagonals, not to a plan file", source="--grid"
        )

    # the output folder before any model is built
    from volcal.base.folders import check_out_dir
    from volcal.measurement.simulate import OPTIONAL_SIMULATION_FILES, SIMULATION_FILES

    check_out_dir(
        args.out,
        SIMULATION_FILES + OPTIONAL_SIMULATION_FILES,
        "a simulation",
        inputs=[
            getattr(args, k, None)
            for k in ("plan", "true_parameters", "stations", "model", "budget")
            if isinstance(getattr(args, k, None), (str, Path))
        ]
        + [p for p in extra.values() if p is not None],
    )
    ex = example(args.example) if args.example else None
    machine = ex.machine if ex else Machine.from_model(args.model)
    spec = machine.spec
    if ex and args.degree == 3:
        em = ex.error_model
    else:
        em = ErrorModel(spec, default=ErrorForm("poly", args.degree))

    if args.true_parameters is not None:
        theta = load_true_parameters(args.true_parameters, em)
        C, _ = em.constraints()
        if C.shape[0] and np.abs(C @ theta).max() > 1e-12:
            log.warning(
                "the true parameters do not satisfy the datum constraints (%s); an "
                "identification with those constraints estimates their projection",
                em.datum,
            )
    elif ex is not None and args.max_volumetric_um is None and em is ex.error_model:
        theta = ex.theta_true
    else:
        rng = np.random.default_rng(np.random.SeedSequence(args.seed, spawn_key=(99,)))
        theta = draw_true_parameters(
            machine, em, rng, 60.0 if args.max_volumetric_um is None else args.max_volumetric_um
        )

    # a measurement plan (``volcal plan``'s measurement_plan.csv) brings its poses, tool
    # offsets and station ids; the positions come from --stations or the stations.csv
    # written beside it
    plan_stations: list[str] = []
    if plan_kind not in PLAN_KINDS and is_measurement_plan(plan_kind):
        plan, plan_tools, plan_stations = measurement_plan_from_csv(plan_kind, spec)
        if tools is not None and not (
            tools.shape == plan_tools.shape and np.allclose(tools, plan_tools)
        ):
            raise InputError(
                "the measurement plan gives its own tool offsets ("
                + "; ".join(",".join(f"{v:g}" for v in t) for t in plan_tools)
                + " mm): drop --tools",
                source="--tools",
            )
        tools = plan_tools
        beside = Path(plan_kind).parent / "stations.csv"
        where = args.stations or (beside if beside.exists() else None)
        if where is None:
            raise InputError(
                f"the measurement plan measures from stations {', '.join(plan_stations)}: "
                "give their positions with --stations (station, x_mm, y_mm, z_mm), e.g. the "
                "stations.csv of the plan's folder",
                source=str(plan_kind),
            )
        from volcal.measurement.tables import load_stations

        st_all = load_stations(where)
        missing = [s for s in plan_stations if s not in set(st_all["station"])]
        if missing:
            raise InputError(
                f"no position for station(s) {', '.join(missing)} of the measurement plan",
                source=str(where),
            )
        stations = st_all.set_index("station").loc[plan_stations].reset_index()
        log.info("stations of the measurement plan from %s", where)
    elif args.stations is not None:
        stations = args.stations
    elif ex is not None:
        stations = ex.stations
    else:
        stations = default_stations(spec, 6, seed=args.seed)

    if args.plan is None and ex is not None and args.grid is None:
        plan = ex.plan
    elif plan_kind in PLAN_KINDS:
        plan = _named_plan(plan_kind, spec, counts, args.degree)
    else:
        plan = plan_from_csv(plan_kind, spec) if not plan_stations else plan
    if tools is None:
        tools = ex.tools if ex is not None else parse_tools(_DEFAULT_TOOLS)
    budget = args.budget or (ex.budget if ex is not None else "paper002")

    sim = simulate(
        machine,
        em,
        theta,
        stations,
        plan,
        tools,
        budget,
        args.seed,
        noise=not args.no_noise,
        drift=args.drift,
    )
    tables = {}
    if extra:
        from volcal.measurement import simulate_instruments as si

        # the same true machine, its own random numbers (the tracker's data stay as
        # without --instruments)
        g = np.random.default_rng(np.random.SeedSequence(args.seed, spawn_key=(32,)))
        t0 = np.atleast_2d(tools)[0]
        tool = (float(t0[0]), float(t0[1]), float(t0[2]))
        fixed: dict[str, Any] = {
            "interferometer": si.interferometer_table,
            "ballbar": si.ballbar_table,
        }
        for name, path in extra.items():
            if path is None:
                tables[f"{name}.csv"] = fixed[name](
                    machine, em, theta, g, tool=tool, noise=not args.no_noise
                )
            else:
                tables[f"{name}.csv"] = si.planned_table(
                    machine, em, theta, g, name, path, noise=not args.no_noise
                )
    out = save_simulation(sim, args.out, tables=tables)
    if not getattr(args, "quiet", False):
        print(
            f"simulated {len(sim.measurements)} readings ({len(sim.stations)} stations x "
            f"{len(plan)} poses x {len(tools)} tool offsets) on model '{spec.name}', seed "
            f"{sim.seed}, noise {'off' if not sim.noise else '+'.join(sim.noise)}; max true "
            f"volumetric error {sim.max_volumetric_um:.1f} um"
        )
        for name, t in tables.items():
            print(f"  and {len(t)} {name[:-4]} readings ({name})")
        print(f"wrote {out}")
    return 0
