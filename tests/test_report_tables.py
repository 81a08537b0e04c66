"""The error-motion tables a metrologist hands over (ISO 230-1 style): peak-to-peak per
error motion (error_motions.csv) and the motions at positions along each axis, in
report.md and the HTML report, checked against component_errors.csv of the same folder and
against polynomials whose peak-to-peak is known by hand."""
from __future__ import annotations

import re
import shutil
from html.parser import HTMLParser

import numpy as np
import pandas as pd
import pytest

from volcal.model.errors import ErrorModel
from volcal.model.machine import Machine
from volcal.outputs import html_report as hr
from volcal.outputs.results import error_motion_table


def test_peak_to_peak_of_known_polynomials():
    """EXX = c P1(t) on the normalised travel t in [-1, 1]: peak-to-peak 2c at the two ends;
    EYY = c P2(t) = c (3t^2 - 1) / 2: from -c/2 mid-travel to c at the ends, 1.5c (the
    datum's shift to zero at the reference changes neither)."""
    m = Machine.from_model("mcv754_wxyzt")
    em = ErrorModel(m.spec)
    th = np.zeros(em.n_params)
    th[em.param_names.index("EXX_1")] = 1e-3  # mm: 1 um
    th[em.param_names.index("EYY_2")] = 2e-3
    th[em.param_names.index("EAZ_1")] = 5e-6  # rad: 5 urad
    t = error_motion_table(em, th).set_index("error_motion")
    assert t.loc["EXX", "peak_to_peak_in_unit"] == pytest.approx(2.0, rel=1e-12)
    assert sorted([t.loc["EXX", "position_of_min_in_axis_unit"],
                   t.loc["EXX", "position_of_max_in_axis_unit"]]) == [0.0, 754.0]
    assert t.loc["EYY", "peak_to_peak_in_unit"] == pytest.approx(3.0, rel=1e-12)
    assert t.loc["EYY", "position_of_min_in_axis_unit"] == pytest.approx(250.0)
    assert t.loc["EAZ", "peak_to_peak_in_unit"] == pytest.approx(10.0, rel=1e-12)
    assert t.loc["EAZ", "unit"] == "urad" and t.loc["EXX", "unit"] == "um"
    assert t.loc["EZX", "peak_to_peak_in_unit"] == 0.0
    assert t.loc["EXX", "description"] == "positioning error of X"
    assert t.loc["EYX", "description"] == "straightness of X in Y"
    assert t.loc["EBX", "description"] == "tilt of X about B"
    assert t.loc["ECZ", "description"] == "roll of Z"
    # one row per component error motion, none for the location errors
    comps = [s.name for s in em.errors if s.kind == "component"]
    assert list(t.index) == comps
    # no covariance: no uncertainty
    assert t["u_peak_to_peak_in_unit"].isna().all()


def test_peak_to_peak_uncertainty_is_the_difference_of_the_extremes():
    """u(max - min) propagates the covariance through the two extreme positions: for
    independent Legendre coefficients with variance s^2 and EXX = c P1, the extremes are
    the travel ends and u = s |P1(1) - P1(-1)| = 2s for the slope's coefficient alone."""
    m = Machine.from_model("mcv754_wxyzt")
    em = ErrorModel(m.spec)
    th = np.zeros(em.n_params)
    k = em.param_names.index("EXX_1")
    th[k] = 1e-3
    cov = np.zeros((em.n_params, em.n_params))
    cov[k, k] = (0.1e-3) ** 2  # 0.1 um
    t = error_motion_table(em, th, cov).set_index("error_motion")
    assert t.loc["EXX", "u_peak_to_peak_in_unit"] == pytest.approx(0.2, rel=1e-9)
    ident = np.ones(em.n_params, bool)
    ident[k] = False
    t = error_motion_table(em, th, cov, ident).set_index("error_motion")
    assert np.isnan(t.loc["EXX", "u_peak_to_peak_in_unit"])


class Tables(HTMLParser):
    """The cells of every <table> of a document, with the table's attributes."""

    def __init__(self) -> None:
        super().__init__()
        self.tables: list[tuple[dict, list[list[str]]]] = []
        self._cell: list[str] | None = None

    def handle_starttag(self, tag, attrs):
        if tag == "table":
            self.tables.append((dict(attrs), []))
        elif tag == "tr" and self.tables:
            self.tables[-1][1].append([])
        elif tag in ("td", "th"):
            self._cell = []

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self.tables[-1][1][-1].append("".join(self._cell).strip())
            self._cell = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)


def _num(text: str) -> float:
    return float(text.split()[0])


def test_report_tables_agree_with_component_errors_csv(demo_result):
    """The printed tables are rows of component_errors.csv (the same positions, values to
    their printed digits) and the peak-to-peak values bound the spread of its columns
    (the peak-to-peak grid is finer: never smaller, and within 1 % for these cubics)."""
    folder = demo_result
    comp = pd.read_csv(folder / "component_errors.csv")
    motions = pd.read_csv(folder / "error_motions.csv")
    assert list(motions.columns[:6]) == ["axis", "error_motion", "description", "unit",
                                         "peak_to_peak_in_unit", "u_peak_to_peak_in_unit"]
    for r in motions.itertuples():
        col = comp.loc[comp["axis"] == r.axis, f"{r.error_motion}_{r.unit}"]
        spread = col.max() - col.min()
        assert spread - 1e-9 <= r.peak_to_peak_in_unit <= 1.01 * spread + 1e-9, r.error_motion
        assert r.min_in_unit <= col.min() + 1e-9 and r.max_in_unit >= col.max() - 1e-9
        assert 0 < r.u_peak_to_peak_in_unit < r.peak_to_peak_in_unit
    # the HTML report
    parser = Tables()
    parser.feed(hr.html_report(folder, plots=False))
    peak = next(rows for attrs, rows in parser.tables if attrs.get("id") == "peak-to-peak")
    assert [r[1] for r in peak[1:]] == list(motions["error_motion"])
    for row, r in zip(peak[1:], motions.itertuples()):
        assert _num(row[3]) == pytest.approx(r.peak_to_peak_in_unit, rel=1e-3)
        assert row[5] == {"um": "µm", "urad": "µrad"}[r.unit]
    by_axis = {attrs["data-axis"]: rows for attrs, rows in parser.tables
               if attrs.get("class") == "motions"}
    assert sorted(by_axis) == sorted(comp["axis"].unique())
    md = (folder / "report.md").read_text(encoding="utf-8")
    assert "### Peak-to-peak per error motion" in md
    for axis, rows in by_axis.items():
        sub = comp[comp["axis"] == axis]
        head = rows[0]
        assert head[0] == f"{axis} position (mm)" and len(rows) == 12  # 11 positions
        names = [re.match(r"(\w+) \((µm|µrad)\)", h).group(1) for h in head[1:]]
        md_block = md.split(f"Axis {axis}, ")[1].split("\n\n")[1].splitlines()
        assert md.split(f"Axis {axis}, ")[1].split(":", 1)[0].endswith(
            "(a tenth of the travel)")  # 41 rows, every fourth
        assert len(md_block) == 2 + 11
        for row, md_row in zip(rows[1:], md_block[2:]):
            hit = sub[np.isclose(sub["position_mm"], float(row[0]))]
            assert len(hit) == 1  # a row of the CSV, not an interpolation
            md_cells = [c.strip() for c in md_row.strip("|").split("|")]
            assert float(md_cells[0]) == pytest.approx(float(row[0]))
            for name, cell, md_cell in zip(names, row[1:], md_cells[1:]):
                unit = "um" if head[names.index(name) + 1].endswith("(µm)") else "urad"
                v = float(hit[f"{name}_{unit}"].iloc[0])
                assert float(cell) == pytest.approx(v, rel=5e-3, abs=1e-6)
                assert float(md_cell) == pytest.approx(v, rel=5e-3, abs=1e-6)


@pytest.fixture(scope="module")
def demo_result(tmp_path_factory):
    """The bundled example identified and saved without plots."""
    import warnings

    from volcal.analysis.identify import identify
    from volcal.measurement.simulate import example
    from volcal.outputs.results import save_result

    ex = example("mcv754")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = identify(ex.machine, ex.simulate().measurements, ex.stations)
    options = {"project_file": None, "robust": True, "degree": 3, "columns": None}
    return save_result(
        res, tmp_path_factory.mktemp("tables") / "result", plots=False, options=options
    )


def test_report_text_is_written_for_a_reader_not_as_python(demo_result):
    """Options are a table of words (no ``project_file = None``), notes carry no literal
    backticks (code spans become <code>), the identification time says what it covers
    and the stages are timed, and the model section says what a parameter is."""
    html = hr.html_report(demo_result, plots=False)
    parser = Tables()
    parser.feed(html)
    options = next(rows for attrs, rows in parser.tables if attrs.get("id") == "options")
    assert ["project file", "not given"] in options and ["robust", "yes"] in options
    assert "None" not in html and "= None" not in html and "True" not in html
    notes = html.split("<h3>Notes</h3>")[1].split("</ul>")[0]
    assert "`" not in notes and "<code>iso230</code>" in notes
    assert "Identification time" in html and "not writing the result folder" in html
    timings = next(rows for attrs, rows in parser.tables if attrs.get("id") == "timings")
    assert ["solving"] == [r[0] for r in timings if r[0] == "solving"]
    assert "error quantities (component error motions" in html
    assert "parameters (the coefficients of their bases" in html
    md = (demo_result / "report.md").read_text(encoding="utf-8")
    assert "identification time" in md and "Per stage" in md
    assert "error quantities (component error motions" in md


def test_code_spans_escape_their_text():
    assert str(hr.code_spans("datum `<b>` & `x`")) == (
        "datum <code>&lt;b&gt;</code> &amp; <code>x</code>"
    )
    assert str(hr.code_spans("one ` alone <i>")) == "one ` alone &lt;i&gt;"


@pytest.mark.skipif(hr.find_browser() is None or shutil.which("pdftotext") is None,
                    reason="needs a Chromium and pdftotext (poppler-utils)")
def test_printed_report_never_leaves_the_plots_heading_alone(demo_result, tmp_path,
                                                              monkeypatch):
    """A figure as tall as a 5-axis component-error figure (10.4 x 14 in) after the
    heading: printed, the heading shares its page with the figure, scaled to fit."""
    import base64
    import io
    import subprocess

    from volcal.outputs import figures

    fig = figures.figure(10.4, 14)
    fig.add_subplot().plot([0, 1], [0, 1])
    buf = io.BytesIO()
    figures.save(fig, buf)
    src = "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()
    tall = [{"name": f"tall{k}.png", "caption": f"tall figure {k}", "src": src}
            for k in range(2)]
    monkeypatch.setattr(hr, "_plots", lambda *a, **k: tall)
    pdf = hr.write_report(demo_result, tmp_path / "r.html", pdf=True)
    text = subprocess.run(["pdftotext", str(pdf), "-"], capture_output=True, text=True,
                          check=True).stdout
    pages = [" ".join(p.split()) for p in text.split("\f")]
    start = next(k for k, p in enumerate(pages) if p.startswith("Plots"))
    assert "tall figure 0" in pages[start], pages[start:]
    assert "tall figure 1" in pages[start + 1]
