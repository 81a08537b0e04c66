"""Regenerate the example compensation exports in this folder.

Simulates and identifies volcal's bundled example (the MCV 754 of paper 000: 3 axes, four
tool offsets, six stations) and writes its compensation in every format:

    isg/         Beckhoff TwinCAT CNC volumetric compensation (ISG CSV + volcomp.lis)
    siemens/     SINUMERIK CEC and LEC init programs
    heidenhain/  HEIDENHAIN *.COM tables and CONFIG.CMA
    generic/     ISO 230-1 tables per axis and a volumetric correction grid (CSV + .npz)

Every folder holds compensation.md (spacing, residual per tool offset, what the format
cannot carry) and compensation.json.  The generic grid is written for the tool offset
(0, 0, 0) only and with a 0.5 um interpolation tolerance to keep this folder small; the
other formats use the default 0.1 um.

Run from anywhere:  python examples/compensation/make_examples.py
"""
from __future__ import annotations

from pathlib import Path

from volcal.outputs.compensation import compensate
from volcal.analysis.identify import identify
from volcal.measurement.simulate import example

HERE = Path(__file__).resolve().parent


def main() -> None:
    ex = example("mcv754")
    sim = ex.simulate()
    res = identify(ex.machine, sim.measurements, sim.stations)
    print(f"identified {ex.model}: {res.status}, residual RMS {res.residual_rms_um:.3f} um")
    runs = {
        "isg": {},
        "siemens": {},
        "heidenhain": {},
        "generic": {"tools": [[0.0, 0.0, 0.0]], "tolerance_um": 0.5},
    }
    for fmt, kw in runs.items():
        comp = compensate(res, fmt, HERE / fmt, **kw)
        print(f"{fmt:10s} {comp.residual_line()}")


if __name__ == "__main__":
    main()
