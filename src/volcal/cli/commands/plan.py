"""``volcal plan``: station placement and a measurement plan that minimise the predicted
uncertainty.

Examples::

    # the bundled setting for the MCV 754 (paper 000's machine): 4 stations, 960 readings
    volcal plan --setting mcv754 --out plan/
    # the same with paper 004's genetic algorithm, scored in 2 local processes
    volcal plan --setting mcv754 --optimizer ga --workers 2 --out plan_ga/
    # every search in this process only (the default uses every core: the same plan)
    volcal plan --setting mcv754 --workers 1 --out plan/
    # your own setting file, flags override it; checkpoints allow a stopped search to resume
    volcal plan --setting my_machine.toml --readings 2000 --checkpoint ckpt/ --out plan/
    # NC programs for two controls
    volcal plan --setting trunnion_ac --nc fanuc,heidenhain --out plan5/
    # and an hour of interferometer lines / ballbar circles chosen to add to the plan
    volcal plan --setting mcv754 --add-minutes 60 --out plan/
    volcal plan --setting mcv754 --add-minutes 40 --add-instruments interferometer \
        --instrument-cost interferometer_setup_min=10,levels=2 --out plan_ifm/

Writes stations.csv, poses.csv, measurement_plan.csv (the columns ``identify`` reads),
program_<dialect>.nc, the predicted uncertainties (error motions, volumetric error over the
workspace, parameters), search_history.csv, summary.json, report.md and plan.png, and with
``--add-minutes`` added_interferometer.csv, added_ballbar.csv and prediction_instruments.csv
(see :mod:`volcal.outputs.plan_files`).  Exit codes: 0 done, 2 bad input (the message names the
file and key), 1 a search that found no feasible design.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def _travel(text: str) -> dict[str, list[float]]:
    out: dict[str, list[float]] = {}
    for item in str(text).split(","):
        name, eq, rng = item.partition("=")
        lo, colon, hi = rng.partition(":")
        try:
            out[name.strip()] = [float(lo), float(hi)]
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected AXIS=LO:HI[,AXIS=LO:HI] in mm / deg, got {text!r}"
            ) from None
        if not eq or not colon:
            raise argparse.ArgumentTypeError(
                f"expected AXIS=LO:HI[,AXIS=LO:HI] in mm / deg, got {text!r}"
            )
    return out


def _costs(text: str) -> dict[str, float | list[float]]:
    """``KEY=VALUE[,KEY=VALUE]`` -> {key: value}; ``ballbar_radii_mm=50:100:150``."""
    out: dict[str, float | list[float]] = {}
    for item in str(text).split(","):
        key, eq, val = item.partition("=")
        try:
            v: float | list[float] = (
                [float(x) for x in val.split(":")] if ":" in val else float(val)
            )
        except ValueError:
            v = None  # type: ignore[assignment]
        if not eq or v is None:
            raise argparse.ArgumentTypeError(
                f"expected KEY=VALUE[,KEY=VALUE] (e.g. interferometer_setup_min=10, "
                f"ballbar_radii_mm=50:100), got {text!r}"
            )
        out[key.strip()] = v
    return out


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "plan",
        help="station placement and measurement plan minimising the predicted uncertainty",
        description="Plan a sequential multilateration measurement: where to put the "
        "tracker (regions, acceptance angle of the reflector, distance, line of sight) "
        "and which poses to measure within a readings budget, by minimising the "
        "predicted uncertainty of the identification (I-optimal by default: the "
        "volumetric error's uncertainty over the workspace).  A setting file (TOML) "
        "holds the model, tools, budget and constraints; flags override it.",
    )
    p.add_argument(
        "--setting",
        required=True,
        metavar="FILE|NAME",
        help="planning setting (TOML file, or a bundled one: mcv754, trunnion_ac)",
    )
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder")
    p.add_argument("--model", metavar="M", help="bundled model name or model file")
    p.add_argument("--stations", type=int, metavar="K", help="number of tracker set-ups")
    p.add_argument(
        "--start-stations",
        type=Path,
        metavar="S.csv",
        help="start (or, with --optimizer none, given) stations: station, x_mm, y_mm, z_mm",
    )
    p.add_argument("--tools", metavar="X,Y,Z;...", help="available tool offsets, mm")
    p.add_argument("--readings", type=int, metavar="N", help="readings budget")
    p.add_argument("--minutes", type=float, metavar="MIN", help="time budget, minutes")
    p.add_argument(
        "--seconds-per-reading",
        type=float,
        metavar="S",
        help="time per reading (move and dwell) for --minutes (default 4 s)",
    )
    p.add_argument(
        "--travel", type=_travel, metavar="AX=LO:HI,...", help="travel to cover, mm / deg"
    )
    p.add_argument(
        "--criterion",
        choices=("I", "A", "D", "E", "MC", "MC-nonlinear"),
        help="design criterion: I (default; RMS predicted u of the volumetric error, um), "
        "A, D, E (on the error parameters), MC or MC-nonlinear (paper 004's Monte Carlo "
        "fitness: the RMS identified volumetric error over simulated measurements, um; "
        "scored by --optimizer ga, the gradient search uses I for it)",
    )
    p.add_argument(
        "--margin-deg",
        type=float,
        metavar="DEG",
        help="kept off the reflector's acceptance half-angle (default 5 deg)",
    )
    p.add_argument(
        "--margin-mm",
        type=float,
        metavar="MM",
        help="kept inside the regions, on the minimum distance, the range and around "
        "obstacles (default 20 mm)",
    )
    p.add_argument(
        "--optimizer", choices=("gradient", "ga", "none"), help="station placement method"
    )
    p.add_argument("--poses", choices=("exchange", "spread"), help="pose selection")
    p.add_argument("--grid", type=int, metavar="N", help="candidate positions per axis")
    p.add_argument("--starts", type=int, metavar="N", help="gradient: starts (default 6)")
    p.add_argument("--population", type=int, metavar="N", help="GA population (default 40)")
    p.add_argument("--generations", type=int, metavar="N", help="GA generations (default 30)")
    p.add_argument("--rounds", type=int, metavar="N", help="placement / exchange rounds")
    p.add_argument("--seed", type=int, help="seed of every random draw (default 0)")
    p.add_argument("--budget", metavar="NAME|FILE", help="uncertainty budget")
    p.add_argument("--degree", type=int, help="polynomial degree of the error motions")
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="local processes solving the gradient search's starts or scoring the GA's "
        "population (default: all cores, this process computing too; 1: in this process; "
        "0: as the default); the same plan whatever the number",
    )
    p.add_argument(
        "--dask",
        metavar="ADDRESS",
        help="Dask scheduler address (tcp://host:8786): solve the starts / score the "
        "population there",
    )
    p.add_argument(
        "--checkpoint",
        type=Path,
        metavar="DIR",
        help="save the searches there after every generation / start and resume from it",
    )
    p.add_argument(
        "--nc",
        default="iso",
        metavar="D[,D]",
        help="NC program dialects: iso, fanuc, siemens, heidenhain (default iso)",
    )
    p.add_argument("--dwell", type=float, default=2.0, metavar="S", help="dwell per point, s")
    p.add_argument("--feed", type=float, default=2000.0, metavar="MM/MIN", help="feed")
    p.add_argument(
        "--add-minutes",
        type=float,
        metavar="MIN",
        help="time budget (minutes, on top of the tracker plan) for interferometer lines "
        "and / or ballbar circles chosen to improve the plan's criterion; writes "
        "added_interferometer.csv, added_ballbar.csv and prediction_instruments.csv "
        "(see docs/instruments.md)",
    )
    p.add_argument(
        "--add-instruments",
        metavar="NAME[,NAME]",
        help="which to add: interferometer and / or ballbar (default both)",
    )
    p.add_argument(
        "--instrument-cost",
        type=_costs,
        metavar="KEY=VALUE,...",
        help="time costs and uncertainties of the added instruments, e.g. "
        "interferometer_setup_min=15, interferometer_seconds_per_target=10, "
        "interferometer_targets=11, interferometer_sigma_um=0.1, ballbar_setup_min=5, "
        "ballbar_seconds_per_rev=60, ballbar_angles=36, ballbar_sigma_um=0.5, "
        "ballbar_radii_mm=50:100:150, levels=3 (the defaults; candidate positions per "
        "other axis); override the setting's [instruments]",
    )
    p.add_argument("--no-plots", action="store_true", help="skip plan.png")
    p.add_argument("--force", action="store_true", help="replace an earlier plan folder")
    # the start-up imports without the cyclic garbage collector, resumed once they are
    # done (volcal.base.processes.pause_gc)
    p.set_defaults(func=run, imports_gc_paused=True)
    return p


def run(args: argparse.Namespace) -> int:
    from volcal.outputs.figures import plan_frame_ahead
    from volcal.outputs.plot_process import plotting

    # first, before the numerics are imported: a child that imports matplotlib on the
    # other core while this process plans, builds plan.png's frame while it waits, then
    # draws the plan into it while this one writes
    with plotting(not args.no_plots, workers=1, ahead=plan_frame_ahead) as plotter:
        code = _run(args, plotter)
    # everything this command opened is closed (worker processes joined, files written,
    # the plotting child ended): as the program it ends without the interpreter's
    # teardown (0.15-0.3 s of freeing modules and objects, volcal.cli.main._exit_now);
    # not after a Dask cluster, whose library cleans up at exit
    args.exit_now = args.dask is None
    return code


def _run(args: argparse.Namespace, plotter) -> int:
    import numpy as np

    from volcal.analysis.planning import constraints_from_dict, plan
    from volcal.analysis.planning.setting import load_setting
    from volcal.base.exceptions import InputError
    from volcal.base.folders import check_out_dir
    from volcal.outputs.nc_program import NC_DIALECTS
    from volcal.outputs.plan_files import PLAN_FILES, write_plan

    dialects = [d.strip() for d in args.nc.split(",") if d.strip()]
    bad = [d for d in dialects if d not in NC_DIALECTS]
    if bad or not dialects:
        raise InputError(
            f"unknown NC dialect(s) {', '.join(bad) or '(none)'}; expected some of "
            f"{', '.join(NC_DIALECTS)}",
            source="--nc",
        )
    check_out_dir(args.out, PLAN_FILES, "a measurement plan", force=args.force or None)
    cfg = load_setting(args.setting)
    if getattr(args, "gc_paused", False):
        # the libraries are imported and the setting read: the collector again, without
        # walking what the imports allocated (volcal.base.processes.resume_gc)
        from volcal.base.processes import resume_gc

        resume_gc()
    over = {
        "model": args.model,
        "stations": args.stations,
        "readings": args.readings,
        "minutes": args.minutes,
        "seconds_per_reading": args.seconds_per_reading,
        "criterion": args.criterion,
        "optimizer": args.optimizer,
        "poses": args.poses,
        "grid": args.grid,
        "starts": args.starts,
        "population": args.population,
        "generations": args.generations,
        "rounds": args.rounds,
        "margin_deg": args.margin_deg,
        "margin_mm": args.margin_mm,
        "seed": args.seed,
        "budget": args.budget,
        "degree": args.degree,
        "travel": args.travel,
        "start_stations": str(args.start_stations) if args.start_stations else None,
    }
    if args.minutes is not None:
        cfg.pop("readings", None)
    cfg.update({k: v for k, v in over.items() if v is not None})
    if args.tools:
        from volcal.measurement.simulate import parse_tools

        cfg["tools"] = parse_tools(args.tools).tolist()
    if "model" not in cfg:
        raise InputError("the setting names no model (key 'model' or --model)", source=args.setting)
    stations = None
    if cfg.get("start_stations"):
        import pandas as pd

        from volcal.measurement.tables import load_instrument_stations

        stations = load_instrument_stations(cfg["start_stations"], ("x_mm", "y_mm", "z_mm"))
        stations = pd.DataFrame(stations)
    quiet = getattr(args, "quiet", False)
    from volcal.analysis.planning.additions import instruments_from_dict

    inst = instruments_from_dict(cfg.get("instruments", {}), str(cfg.get("_source")))
    if args.add_instruments is not None:
        names = [w.strip() for w in args.add_instruments.split(",") if w.strip()]
        from volcal.analysis.planning.additions import check_instruments

        inst["add"] = check_instruments(names, "--add-instruments")
    if args.add_minutes is not None:
        from volcal.analysis.planning.additions import check_minutes

        inst["minutes"] = check_minutes(args.add_minutes, "--add-minutes")
    if args.add_instruments is not None and inst["minutes"] is None:
        raise InputError(
            "--add-instruments needs a time budget for them: --add-minutes MIN (or minutes "
            "in the setting's [instruments])",
            source="--add-instruments",
        )
    costs = dict(inst["costs"])
    if args.instrument_cost:
        from volcal.analysis.planning.additions import InstrumentCosts

        InstrumentCosts.from_mapping(args.instrument_cost, "--instrument-cost")
        costs.update(args.instrument_cost)

    from volcal.analysis.planning.plan import DEFAULT_MARGIN_DEG, DEFAULT_MARGIN_MM
    from volcal.base import progress as report

    crit = cfg.get("criterion", "I")
    unit = " um" if crit in ("I", "MC", "MC-nonlinear") else " (scaled units)"
    started: dict[str, float] = {}

    def progress(stage: str, step: int, total: int, best: float) -> None:
        # one report per generation / start / exchange, with the total and the time left
        # in this round at its rate so far (volcal.base.progress)
        import time

        now = time.monotonic()
        if step == 0:  # a search round begins
            started[stage] = now
        t0 = started.get(stage)
        left = "" if t0 is None else f", ETA of this round {report.eta(step, total, now - t0)}"
        report.update(f"{stage} {step} of {total}, criterion {crit} {best:.4g}{unit}{left}")

    with report.stage("planning"):
        res = plan(
            cfg["model"],
            n_stations=int(cfg.get("stations", 4)),
            tools=np.asarray(cfg["tools"], float) if "tools" in cfg else None,
            readings=cfg.get("readings"),
            minutes=cfg.get("minutes"),
            seconds_per_reading=float(cfg.get("seconds_per_reading", 4.0)),
            constraints=constraints_from_dict(
                cfg.get("constraints", {}), where=f"{cfg.get('_source')}: [constraints]"
            ),
            travel=cfg.get("travel"),
            budget=cfg.get("budget", "paper002"),
            degree=int(cfg.get("degree", 3)),
            criterion=cfg.get("criterion", "I"),
            optimizer=cfg.get("optimizer", "gradient"),
            poses=cfg.get("poses", "exchange"),
            stations=stations,
            grid=int(cfg.get("grid", 6)),
            seed=int(cfg.get("seed", 0)),
            starts=int(cfg.get("starts", 6)),
            population=int(cfg.get("population", 40)),
            generations=int(cfg.get("generations", 30)),
            rounds=int(cfg.get("rounds", 2)),
            margin_deg=float(cfg.get("margin_deg", DEFAULT_MARGIN_DEG)),
            margin_mm=float(cfg.get("margin_mm", DEFAULT_MARGIN_MM)),
            workers=None if not args.workers else args.workers,
            scheduler=args.dask,
            checkpoint_dir=args.checkpoint,
            progress=progress,
            add_instruments=inst["add"] if inst["minutes"] is not None else None,
            add_minutes=inst["minutes"],
            instrument_costs=costs,
        )
    res.settings["setting_file"] = cfg.get("_source")
    res.settings["project_file"] = getattr(args, "project_file", None)
    out = write_plan(
        res,
        args.out,
        dialects=dialects,
        dwell_s=args.dwell,
        feed_mm_min=args.feed,
        plots=not args.no_plots,
        force=args.force or None,
        plotter=plotter,
    )
    if not quiet:
        s = res.summary()
        print(
            f"{s['model']}: {s['stations']} stations, {s['poses']} poses x "
            f"{s['tool_offsets']} tool offset(s) = {s['readings']} readings\n"
            f"criterion {s['criterion']}: {s['criterion_value']:.4g}{unit} "
            f"(start {s['start_value']:.4g}); predicted volumetric u RMS "
            f"{s['volumetric_u_rms_um']:.3g} um, max {s['volumetric_u_max_um']:.3g} um\n"
            f"unidentifiable error parameters: "
            f"{', '.join(s['unidentifiable_error_parameters']) or 'none'}\n"
            f"margins {s['margins']['deg']:g} deg, {s['margins']['mm']:g} mm; slack left: "
            + ", ".join(f"{r['constraint']} {r['slack']:.3g} {r['unit']}" for r in s["slack"])
            + "\n"
            + (_additions_lines(res.additions) if res.additions is not None else "")
            + f"written to {out} in {s['seconds']:.1f} s"
        )
    return 0


def _additions_lines(add) -> str:
    """What the planner added, for the terminal."""
    pred = add.prediction()
    a, b = pred.iloc[0], pred.iloc[-1]
    pos = [c for c in pred.columns if c.startswith("positioning_u_")]
    per = ", ".join(
        f"{k} {v['setups']} set-up(s) {v['minutes']:.1f} min"
        for k, v in add.summary()["per_instrument"].items()
    )
    return (
        f"added within {add.minutes:g} min: {per} ({add.spent_minutes:.1f} min; "
        + (", ".join(c.setup for c in add.chosen) or "nothing")
        + ")\n"
        f"with the additions: criterion {a['criterion']} {a['criterion_value']:.4g} -> "
        f"{b['criterion_value']:.4g} {b['criterion_unit']}; field u RMS "
        f"{a['field_u_rms_um']:.3g} -> {b['field_u_rms_um']:.3g} um; positioning u "
        + ", ".join(f"{c.split('_')[2]} {a[c]:.3g} -> {b[c]:.3g}" for c in pos)
        + " um\n"
    )
