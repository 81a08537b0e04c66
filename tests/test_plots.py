"""The public plots (volcal.plots): every one returns a Figure and writes a PNG; the
volumetric slices cover each rotary axis; the correlation plot leaves out what the datum
ties (no exact +-1 off the diagonal) and what the data cannot see."""
from __future__ import annotations

import functools
import warnings

import numpy as np

import volcal
from volcal.analysis.identify import identify
from volcal.measurement.simulate import draw_true_parameters, example
from volcal.model.errors import ErrorModel
from volcal.model.machine import Machine
from volcal.outputs.results import COMPONENT_POINTS, component_error_table


@functools.cache
def _result():
    ex = example("mcv754")
    sim = ex.simulate()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return identify(ex.machine, sim.measurements, ex.stations)


def test_every_plot_returns_a_figure_and_writes_a_png(tmp_path):
    res = _result()
    P = volcal.plots
    comp = component_error_table(
        res.error_model, res.theta, res.cov_theta, res.identifiable, COMPONENT_POINTS
    )
    figs = {
        "component_errors": P.component_errors(comp, res.error_model, tmp_path / "c.png"),
        "volumetric_slices": P.volumetric_slices(
            res.machine, res.error_model, res.theta, tmp_path / "v.png"
        ),
        "residuals": P.residuals(res.residuals, tmp_path / "r.png"),
        "residuals_vs_axes": P.residuals_vs_axes(res, tmp_path / "ra.png"),
        "correlations": P.correlations(res, tmp_path / "co.png"),
    }
    for name, fig in figs.items():
        assert fig is not None and len(fig.axes) >= 1, name
    for f in ("c", "v", "r", "ra", "co"):
        assert (tmp_path / f"{f}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the residual figure has the QQ panel
    assert any("QQ" in ax.get_title() for ax in figs["residuals"].axes)


def test_correlations_leave_out_datum_ties():
    res = _result()
    fig = volcal.plots.correlations(res)
    R = fig.axes[0].images[0].get_array()
    off = np.abs(np.asarray(R))[~np.eye(R.shape[0], dtype=bool)]
    assert off.max() < 0.999  # an exact +-1 is a datum tie, not the data
    assert R.shape[0] < int(np.asarray(res.identifiable).sum())


def test_volumetric_slices_cover_every_rotary_axis():
    m = Machine.from_model("trunnion_ac")
    em = ErrorModel(m.spec)
    th = draw_true_parameters(m, em, np.random.default_rng(1), 40.0)
    fig = volcal.plots.volumetric_slices(m, em, th, heights=2, angles=3, n=9)
    titles = [ax.get_title() for ax in fig.axes if ax.get_visible() and ax.get_title()]
    assert sum(t.startswith("Z =") for t in titles) == 2
    assert sum(t.startswith("C =") for t in titles) == 3  # full turn: 3 distinct angles
    assert sum(t.startswith("A =") for t in titles) == 3
