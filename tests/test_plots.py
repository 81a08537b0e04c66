"""The public plots (volcal.plots): every one returns a Figure and writes a PNG, legible at
its printed size with one unit spelling; the volumetric slices are to scale, cover each
rotary axis and say where the other axes stand; the correlation plot names its strongest
pairs and leaves out what the datum ties (no exact +-1 off the diagonal) and what the
data cannot see."""
from __future__ import annotations

import functools
import warnings

import numpy as np
import pytest

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
    # each slice says where the axes out of its plane stand
    c = [t for t in titles if t.startswith("C =")]
    assert c and all("A = 0 deg" in t and "Z = -225 mm" in t for t in c), c
    z = [t for t in titles if t.startswith("Z =")]
    assert z and all("A = 0 deg" in t and "C = 0 deg" in t for t in z), z


def test_volumetric_map_drawn_in_a_frame_built_ahead_is_the_same_picture(tmp_path):
    """``volcal identify``'s plotting child builds the volumetric map's frame from the
    model alone, before the solve (figures.volumetric_frame_key: the slices along the
    third linear axis and around each rotary axis, the travel's scale): the map of a
    machine with two rotary axes takes it, and is byte for byte the map drawn without."""
    from volcal.outputs import figures as F
    from volcal.outputs.plots import volumetric_slices_data

    m = Machine.from_model("trunnion_ac")
    em = ErrorModel(m.spec)
    th = draw_true_parameters(m, em, np.random.default_rng(2), 40.0)
    data = volumetric_slices_data(m, em, th, n=9)
    key = F.volumetric_frame_key([(*a.travel, a.is_rotary) for a in m.spec.axes])
    assert key is not None and key[1] == len(data["slices"])
    F.draw_volumetric_slices(data, tmp_path / "plain.png")
    try:
        F.prepare_frame(key)
        F.draw_volumetric_slices(data, tmp_path / "framed.png")
        assert key not in F._FRAMES  # taken
    finally:
        F._FRAMES.clear()
    assert (tmp_path / "plain.png").read_bytes() == (tmp_path / "framed.png").read_bytes()
    # no map without two linear axes: no frame
    assert F.volumetric_frame_key([(0.0, 500.0, False), (0.0, 360.0, True)]) is None


def _texts(fig):
    """Every visible non-empty text of a figure (titles, labels, tick labels, legends, keys)
    after drawing."""
    from matplotlib.text import Text

    fig.canvas.draw()
    return [t for t in fig.findobj(Text) if t.get_visible() and t.get_text().strip()]


def test_every_plot_is_legible_at_its_printed_size_with_one_unit_spelling(tmp_path):
    """The report shows a figure up to ~1040 px wide at its own size (100 dpi): no figure is
    wider than 10.4 in, so no text is smaller than 8 pt where it is read; units are spelt
    µm / µrad (never um) and the bands ±2u; every panel names its axes."""
    import re

    from volcal.outputs import figures

    res = _result()
    P = volcal.plots
    comp = component_error_table(
        res.error_model, res.theta, res.cov_theta, res.identifiable, COMPONENT_POINTS
    )
    figs = [
        P.component_errors(comp, res.error_model),
        P.volumetric_slices(res.machine, res.error_model, res.theta),
        P.residuals(res.residuals),
        P.residuals_vs_axes(res),
        P.correlations(res),
    ]
    for fig in figs:
        assert fig.get_figwidth() <= figures.MAX_WIDTH + 1e-9
        texts = _texts(fig)
        small = [(t.get_text(), t.get_fontsize()) for t in texts if t.get_fontsize() < 8]
        assert not small, small
        words = " ".join(t.get_text() for t in texts)
        assert not re.search(r"\b(um|urad)\b|\+-", words), words
        for ax in fig.axes:
            if ax.get_visible() and ax.images and ax.get_label() != "<colorbar>":
                assert ax.get_xlabel() or ax.get_xticklabels()
    assert "±2u" in figs[0]._suptitle.get_text()
    assert any("(µm)" in ax.get_ylabel() for ax in figs[0].axes)
    assert any("(µrad)" in ax.get_ylabel() for ax in figs[0].axes)


def test_volumetric_slices_are_drawn_to_scale_with_an_arrow_key():
    """754 x 500 mm is drawn 754 x 500 (equal mm on both axes, not square panels), and one
    arrow scale serves every panel, with a key in µm."""
    from matplotlib.quiver import Quiver, QuiverKey

    res = _result()
    fig = volcal.plots.volumetric_slices(res.machine, res.error_model, res.theta)
    fig.canvas.draw()
    panels = [ax for ax in fig.axes if ax.images and ax.get_xlabel() == "X (mm)"]
    assert len(panels) == 3
    for ax in panels:
        box = ax.get_window_extent()
        assert box.height / box.width == pytest.approx(500 / 754, rel=0.02)
    scales = {q.scale for ax in panels for q in ax.collections if isinstance(q, Quiver)}
    assert len(scales) == 1
    keys = [a for ax in panels for a in ax.get_children() if isinstance(a, QuiverKey)]
    assert len(keys) == 1 and keys[0].text.get_text() == f"{keys[0].U:g} µm"
    assert keys[0].Q.scale == scales.pop()


def test_correlations_name_the_strongest_pairs():
    """A correlation planted between two parameters of a 5-axis model (112+ parameters,
    too many to name on the matrix) is named in the title and heads the list of the
    strongest pairs; the matrix is labelled by the axes of the error quantities."""
    from types import SimpleNamespace

    m = Machine.from_model("trunnion_ac")
    em = ErrorModel(m.spec)
    rng = np.random.default_rng(3)
    n = em.n_params
    A = np.eye(n) + 0.05 * rng.standard_normal((n, n))
    cov = A @ A.T
    i, j = em.param_names.index("EXX_1"), em.param_names.index("ECA_2")
    cov[i, j] = cov[j, i] = -0.9995 * np.sqrt(cov[i, i] * cov[j, j])
    res = SimpleNamespace(
        error_model=em, cov_theta=cov, identifiable=np.ones(n, bool), state=None
    )
    data = volcal.plots.correlations_data(res)
    assert len(data["names"]) > 60
    fig = volcal.plots.correlations(res)
    assert "EXX_1 ~ ECA_2" in fig._suptitle.get_text() or "ECA_2 ~ EXX_1" in (
        fig._suptitle.get_text()
    )
    pairs = fig.axes[-1]
    first = pairs.get_yticklabels()[0].get_text()
    assert set(first.split(" ~ ")) == {"EXX_1", "ECA_2"}
    ticks = {t.get_text() for t in fig.axes[0].get_xticklabels()}
    assert {"axis X", "axis A", "axis C"} <= ticks
    assert min(t.get_fontsize() for t in _texts(fig)) >= 8


def test_titles_placed_before_drawing_give_matplotlibs_picture(tmp_path, monkeypatch):
    """figures.save places the axes' titles before drawing where nothing can be above
    them (sparing matplotlib a second layout of the y tick labels): the PNGs are byte for
    byte those of matplotlib's own placement, on two plots of a result (y axes with a
    ScalarFormatter; the strongest pairs' names, a FixedFormatter) and where the y axis
    shows an offset text (values of about 1e-9) under a title wide enough to meet it,
    which matplotlib moves up: left to matplotlib."""
    from volcal.outputs import figures as F
    from volcal.outputs.plots import correlations_data

    res = _result()
    comp = component_error_table(
        res.error_model, res.theta, res.cov_theta, res.identifiable, COMPONENT_POINTS
    )
    cases = [
        ("component_errors.png", F.draw_component_errors,
         volcal.plots.component_errors_data(comp, res.error_model)),
        ("correlations.png", F.draw_correlations, correlations_data(res)),
    ]

    def offset_title(data, path):
        fig = F.figure(3.0, 2.0)
        ax = fig.add_axes((0.25, 0.2, 0.7, 0.55))
        ax.plot([0.0, 1.0], [1e-9, 3e-9])
        ax.set_title("a title as wide as the axes, over the offset text", fontsize=10)
        return F.save(fig, path)

    cases.append(("offset_title.png", offset_title, None))
    settled = []
    for name, draw, data in cases:
        fig = draw(data, tmp_path / name)
        settled += [ax._autotitlepos is False for ax in fig.axes if ax.get_title()]
    assert sum(settled) == 7  # the result's plots (6 + 1 titles): placed ahead
    assert fig.axes[0]._autotitlepos is not False  # the offset text: left to matplotlib
    monkeypatch.setattr(F, "_settle_titles", lambda fig: None)
    for name, draw, data in cases:
        draw(data, tmp_path / f"mpl_{name}")
        assert (tmp_path / name).read_bytes() == (tmp_path / f"mpl_{name}").read_bytes(), name


def test_plan_png_drawn_in_a_frame_built_ahead_is_the_same_picture(tmp_path):
    """``volcal plan``'s plotting child builds plan.png's frame while it waits
    (figures.plan_frame_ahead: the first child only); the plan drawn into it is byte for
    byte the one drawn without a frame, with and without the re-aimed reflector's centre,
    and the frame is taken by the figure."""
    from volcal.outputs import figures as F

    rng = np.random.default_rng(3)
    data = {
        "stations_mm": rng.uniform(-900.0, 900.0, (4, 3)),
        "points_mm": rng.uniform(-300.0, 300.0, (60, 3)),
        "u_um": rng.uniform(0.1, 0.5, 60),
        "centre_mm": None,
    }
    ahead = F.plan_frame_ahead(2)
    assert len(ahead) == 2 and ahead[1] == [] and len(ahead[0]) == 1
    for case, centre in (("plain", None), ("aimed", np.array([10.0, -20.0, 30.0]))):
        d = dict(data, centre_mm=centre)
        F.draw_plan(d, tmp_path / f"{case}.png")  # no frame built
        try:
            for func, args in ahead[0]:
                func(*args)
            assert ("plan",) in F._FRAMES
            F.draw_plan(d, tmp_path / f"{case}_framed.png")
            assert ("plan",) not in F._FRAMES  # taken
        finally:
            F._FRAMES.clear()
        assert (tmp_path / f"{case}.png").read_bytes() == (
            tmp_path / f"{case}_framed.png"
        ).read_bytes(), case
