"""Regenerate the images shown in the README (docs/images/):

* the plots of a 3-axis result (the bundled MCV 754 example) and of a 5-axis result
  (trunnion_ac, simulated on a plan made by ``volcal plan --setting trunnion_ac``), each
  identified by volcal;
* screenshots of the HTML report of ``volcal demo`` (with a ``volcal compensate``
  export), taken by a headless Chromium at the report's own width: its first screen
  (report.png), its error-motion tables (report_error_motions.png) and its plots section
  (report_plots.png), as a reader sees them.

    python docs/make_images.py                 # everything (about a minute)
    python docs/make_images.py --only report   # the report screenshots
    python docs/make_images.py --only plots    # the plots

The screenshots need Chromium on the PATH (``apt-get install chromium``).
"""

from __future__ import annotations

import argparse
import io
import os
import shutil
import subprocess
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

HERE = Path(__file__).resolve().parent / "images"
PLOTS = ("component_errors", "volumetric_map", "residuals", "residuals_vs_axes", "correlations")
#: the report's screenshots: file, the part of the report shown (None: its first screen),
#: window height (px) before the empty bottom is cropped
SHOTS = (
    ("report.png", None, 1500),
    ("report_error_motions.png", "error-motions", 2600),
    ("report_plots.png", "plots", 1500),
)
#: the report's content width (its CSS max-width) plus a margin
WIDTH = 1100
MAX_BYTES = 400_000


def _copy(folder: Path, tag: str) -> None:
    for p in PLOTS:
        shutil.copyfile(folder / f"{p}.png", HERE / f"{p}_{tag}.png")


def plots(tmp: Path) -> int:
    from volcal.analysis.identify import identify
    from volcal.analysis.planning import plan
    from volcal.analysis.planning.setting import load_setting
    from volcal.measurement.simulate import draw_true_parameters, example, simulate
    from volcal.outputs.results import save_result

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ex = example("mcv754")
        sim = ex.simulate()
        res = identify(ex.machine, sim.measurements, ex.stations)
        _copy(save_result(res, tmp / "three", data_name="mcv754 example"), "3axis")
        cfg = load_setting("trunnion_ac")
        pl = plan(
            cfg["model"],
            n_stations=4,
            tools=np.array(cfg["tools"]),
            starts=1,
            rounds=1,
            readings=cfg["readings"],
            constraints=cfg["constraints"],
        )
        m, em = pl.machine, pl.error_model
        theta = draw_true_parameters(m, em, np.random.default_rng(5), 40.0)
        st = pl.stations.assign(dead_length_mm=0.2)
        s5 = simulate(m, em, theta, st, pl.poses, pl.tools, "paper002", 5)
        start = s5.stations[["station", "x_mm", "y_mm", "z_mm"]].copy()
        start[["x_mm", "y_mm", "z_mm"]] += 1.0
        res5 = identify(m, s5.measurements, pd.DataFrame(start))
        _copy(save_result(res5, tmp / "five", data_name="trunnion_ac simulated"), "5axis")
    return 2 * len(PLOTS)


def _only(html: str, section: str) -> str:
    """The report showing one section only (the others hidden, nothing else changed)."""
    css = f"<style>main > *:not(#{section}) {{ display: none; }}</style>"
    return html.replace("</head>", css + "</head>", 1)


def _shot(browser: str, html: str, out: Path, height: int, tmp: Path) -> None:
    from PIL import Image, ImageChops

    page = tmp / "page.html"
    page.write_text(html, encoding="utf-8")
    png = tmp / "shot.png"
    cmd = [
        browser,
        "--headless",
        "--disable-gpu",
        "--no-sandbox",
        "--disable-dev-shm-usage",
        f"--user-data-dir={tmp / 'profile'}",
        "--hide-scrollbars",
        f"--window-size={WIDTH},{height}",
        f"--screenshot={png}",
        page.as_uri(),
    ]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=180, cwd=tmp)
    if run.returncode != 0 or not png.is_file():
        raise SystemExit(f"chromium failed: {run.stderr[-2000:]}")
    with Image.open(png) as im:
        im = im.convert("RGB")
        # crop the empty bottom (a section shorter than the window)
        box = ImageChops.difference(im, Image.new("RGB", im.size, "white")).getbbox()
        if box is not None:
            im = im.crop((0, 0, im.width, min(im.height, box[3] + 24)))
        # a palette image keeps the text sharp at a fraction of the size
        buf = io.BytesIO()
        im.quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(buf, "PNG", optimize=True)
    if len(buf.getvalue()) > MAX_BYTES:
        raise SystemExit(f"{out.name}: {len(buf.getvalue())} bytes, more than {MAX_BYTES}")
    out.write_bytes(buf.getvalue())


def report(tmp: Path) -> int:
    from volcal.cli.commands.demo import run_demo
    from volcal.outputs import html_report as hr
    from volcal.outputs.compensation import compensate

    browser = hr.find_browser()
    if browser is None:
        raise SystemExit("no chromium on the PATH: install it (apt-get install chromium)")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run_demo(tmp / "demo")
        compensate(tmp / "demo" / "identification", "generic", tmp / "comp")
    # relative folder names, as a user who ran `volcal demo` sees them
    cwd = Path.cwd()
    os.chdir(tmp)
    try:
        html = hr.html_report(Path("demo/identification"), compensation_dir=Path("comp"))
    finally:
        os.chdir(cwd)
    for name, section, height in SHOTS:
        _shot(browser, html if section is None else _only(html, section), HERE / name, height, tmp)
    return len(SHOTS)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", choices=("plots", "report"), help="regenerate only these")
    args = ap.parse_args()
    HERE.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="volcal-images-"))
    try:
        n = 0
        if args.only in (None, "plots"):
            n += plots(tmp)
        if args.only in (None, "report"):
            n += report(tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"wrote {n} images to {HERE}")


if __name__ == "__main__":
    main()
