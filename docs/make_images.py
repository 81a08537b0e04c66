"""Regenerate the plots shown in the README (docs/images/): a 3-axis result (the bundled
MCV 754 example) and a 5-axis result (trunnion_ac, simulated on a plan made by
``volcal plan --setting trunnion_ac``), each identified by volcal.

    python docs/make_images.py
"""
from __future__ import annotations

import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

HERE = Path(__file__).resolve().parent / "images"
PLOTS = ("component_errors", "volumetric_map", "residuals", "residuals_vs_axes", "correlations")


def _copy(folder: Path, tag: str) -> None:
    for p in PLOTS:
        shutil.copyfile(folder / f"{p}.png", HERE / f"{p}_{tag}.png")


def main() -> None:
    from volcal.analysis.identify import identify
    from volcal.analysis.planning import plan
    from volcal.analysis.planning.setting import load_setting
    from volcal.measurement.simulate import draw_true_parameters, example, simulate
    from volcal.outputs.results import save_result

    HERE.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ex = example("mcv754")
        sim = ex.simulate()
        res = identify(ex.machine, sim.measurements, ex.stations)
        _copy(save_result(res, tmp / "three", data_name="mcv754 example"), "3axis")
        cfg = load_setting("trunnion_ac")
        pl = plan(cfg["model"], n_stations=4, tools=np.array(cfg["tools"]), starts=1, rounds=1,
                  readings=cfg["readings"], constraints=cfg["constraints"])
        m, em = pl.machine, pl.error_model
        theta = draw_true_parameters(m, em, np.random.default_rng(5), 40.0)
        st = pl.stations.assign(dead_length_mm=0.2)
        s5 = simulate(m, em, theta, st, pl.poses, pl.tools, "paper002", 5)
        start = s5.stations[["station", "x_mm", "y_mm", "z_mm"]].copy()
        start[["x_mm", "y_mm", "z_mm"]] += 1.0
        res5 = identify(m, s5.measurements, pd.DataFrame(start))
        _copy(save_result(res5, tmp / "five", data_name="trunnion_ac simulated"), "5axis")
    shutil.rmtree(tmp, ignore_errors=True)
    print(f"wrote {len(PLOTS) * 2} images to {HERE}")


if __name__ == "__main__":
    main()
