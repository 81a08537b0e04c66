"""`volcal report` and volcal.outputs.html_report: one self-contained HTML document.

Two result folders, each made once: the demo (MCV 754, `volcal demo` run once per session
in tests/conftest.py, with plots; plus a generic compensation export) and a poor fit of
the same readings (one tool offset, Legendre degree 1: the model does not fit and some
parameters are not identifiable), written without plots.  The browser test runs only where
a Chromium is installed (CI installs one in .ci/run); the README's screenshots of the
report are written by `python docs/make_images.py --only report`.
"""
from __future__ import annotations

import base64
import hashlib
import json
import re
import subprocess
import warnings
from html.parser import HTMLParser
from pathlib import Path

import pandas as pd
import pytest

import volcal.cli.main
from volcal.outputs import html_report as hr

SECTIONS = ("header", "identification", "model", "data", "datum", "unidentifiable",
            "uncertainty", "parameters")


def run_cli(argv: list[str], monkeypatch) -> int:
    """volcal.cli.main.main with only the report command registered."""
    monkeypatch.setattr(volcal.cli.main, "_COMMANDS", ["volcal.cli.commands.report"])
    return volcal.cli.main.main(argv)


def folder_hashes(path: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(Path(path).iterdir()) if p.is_file()}


class Refs(HTMLParser):
    """Every tag and every src / href attribute of a document."""

    def __init__(self) -> None:
        super().__init__()
        self.tags: list[str] = []
        self.refs: list[tuple[str, str, str]] = []
        self.ids: set[str] = set()

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        for k, v in attrs:
            if k in ("src", "href", "srcset", "action", "data") and v is not None:
                self.refs.append((tag, k, v))
            if k == "id" and v:
                self.ids.add(v)


def parse(html: str) -> Refs:
    p = Refs()
    p.feed(html)
    return p


@pytest.fixture(scope="module")
def demo(tmp_path_factory, demo_run):
    from volcal.outputs.compensation import compensate

    run, folder = demo_run
    assert run.returncode == 0, run.stdout + run.stderr
    tmp = tmp_path_factory.mktemp("report")
    result = folder / "identification"
    comp = tmp / "comp"
    compensate(result, "generic", comp)
    return {"tmp": tmp, "demo": folder, "result": result, "comp": comp}


@pytest.fixture(scope="module")
def poor(demo):
    """The demo's readings at one tool offset fitted with degree 1: an inadequate fit
    with unidentifiable parameters (the angular errors of Z need a second tool offset)."""
    from volcal.analysis.identify import identify
    from volcal.measurement.simulate import example
    from volcal.outputs.results import save_result

    m = pd.read_csv(demo["demo"] / "simulation" / "measurements.csv")
    m = m[(m["tool_x"] == 0) & (m["tool_y"] == 0) & (m["tool_z"] == 0)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the single tool offset is warned about
        res = identify(example("mcv754").machine, m, degree=1)
    folder = save_result(res, demo["tmp"] / "poor", data_name="one_tool.csv", plots=False)
    # the same result with its plots, for the report's drawing of the plots it lacks
    save_result(res, demo["tmp"] / "poor_plotted", data_name="one_tool.csv")
    return folder


# --------------------------------------------------------------------------------------
# the document


def test_report_is_self_contained_with_every_section(demo, monkeypatch, capsys):
    before = folder_hashes(demo["result"]), folder_hashes(demo["comp"])
    out = demo["tmp"] / "out" / "report.html"
    code = run_cli(["report", "--result", str(demo["result"]), "--compensation",
                    str(demo["comp"]), "--out", str(out)], monkeypatch)
    assert code == 0, capsys.readouterr().err
    assert f"wrote {out}" in capsys.readouterr().out
    assert (folder_hashes(demo["result"]), folder_hashes(demo["comp"])) == before
    assert not [p for p in out.parent.iterdir() if p.name != "report.html"]  # no temp left
    html = out.read_text(encoding="utf-8")
    doc = parse(html)
    # nothing to fetch: no script, no stylesheet link, no external address anywhere
    assert "script" not in doc.tags and "link" not in doc.tags and "iframe" not in doc.tags
    assert not re.search(r"(src|href)\s*=\s*[\"']?\s*(https?:)?//", html, re.I)
    assert "http://" not in html and "https://" not in html
    for tag, attr, value in doc.refs:
        assert tag == "a" and value.startswith("#") or tag == "img", (tag, attr, value[:60])
    images = [v for t, a, v in doc.refs if t == "img"]
    pngs = sorted(p.name for p in demo["result"].glob("*.png"))
    assert len(images) == len(pngs) >= 4
    for src in images:
        prefix = "data:image/png;base64,"
        assert src.startswith(prefix)
        assert base64.b64decode(src[len(prefix):], validate=True).startswith(b"\x89PNG")
    assert set(SECTIONS) | {"plots", "compensation"} <= doc.ids
    # the verdict and its message; the key figures
    assert 'data-verdict="fits"' in html and "the model fits the data" in html
    assert "Solved_To_Acceptable_Level" in html and "joint" in html
    assert "mcv754_wxyzt" in html and "simulation/measurements.csv" in html
    assert "3576" in html and "Reading uncertainties from" in html
    assert "Datum convention <code>iso230</code>" in html
    assert "Every parameter is identifiable" in html and "Gauge freedoms held" in html
    assert "Largest parameter uncertainties" in html and "RMS standard uncertainty" in html
    # every parameter, six significant digits
    params = pd.read_csv(demo["result"] / "parameters.csv")
    rows = re.findall(r'<td class="mono">([^<]+)</td><td class="num">([^<]+)</td>',
                      html.split('id="parameters"')[1].split("</table>")[0])
    assert [r[0] for r in rows] == list(params["name"])
    for (name, value), v in zip(rows, params["value"]):
        assert value == format(v, ".6g"), name
    # the compensation summary
    assert "generic: per-axis ISO 230-1 error tables" in html
    assert "Residual after compensation" in html and "errors_X.csv" in html
    # ... and the rigid motion the files cannot correct (work offset and alignment take it
    # up), with the residual modulo that motion, as compensation.json states them
    comp = json.loads((demo["comp"] / "compensation.json").read_text())
    assert "Set-up part." in html and "work offset" in comp["setup_part"]
    assert comp["setup_part"].split(";")[0] in html
    assert "Residual modulo the set-up" in html


def test_an_inadequate_fit_says_so_in_a_red_banner(poor):
    html = hr.html_report(poor, plots=False)
    banner = html.split('id="adequacy-verdict"')[1].split("</div>")[0]
    assert 'class="banner bad"' in html.split('id="adequacy-verdict"')[0][-80:]
    assert 'data-verdict="does_not_fit"' in banner
    assert "does NOT fit the data" in banner and "Likely cause" in banner
    # the banner says each cause once (not the paragraph and then its causes again)
    ad = json.loads((poor / "result.json").read_text())["adequacy"]
    for c in ad["causes"]:
        assert banner.count(c["text"][:60].replace("'", "&#39;")) == 1, c["kind"]
    assert "not identifiable from these data" in html and "EAZ_0" in html
    assert "not identifiable</td>" in html  # their std cell in the parameters table
    assert 'id="plots"' not in html and "<img" not in html  # plots=False
    assert "one_tool.csv" in html


def test_the_plots_a_folder_lacks_are_drawn_from_the_saved_result(
    poor, demo, tmp_path, monkeypatch, capsys
):
    """A result written without plots (``volcal identify --no-plots``) gets them in its
    report, drawn from the saved tables: byte for byte the PNGs save_result draws for the
    same result (an inadequate fit with unidentifiable parameters: dashed lines, no
    bands), in the same order, whether plotting processes or this process draw them; the
    folder is only read.  ``--no-plots`` leaves them out."""
    before = folder_hashes(poor)
    out = tmp_path / "report.html"
    assert run_cli(["report", "--result", str(poor), "--out", str(out)], monkeypatch) == 0
    assert folder_hashes(poor) == before
    html = out.read_text(encoding="utf-8")
    images = [v for t, a, v in parse(html).refs if t == "img"]
    plotted = demo["tmp"] / "poor_plotted"
    names = [n for n in hr.PLOT_FILES if (plotted / n).is_file()]
    assert len(names) == 5 and len(images) == 5
    prefix = "data:image/png;base64,"
    for name, src in zip(names, images):
        assert src.startswith(prefix)
        assert base64.b64decode(src[len(prefix):]) == (plotted / name).read_bytes(), name
    # the command line draws them in plotting processes; drawn here, in this process,
    # they are the same again
    assert images == [v for t, a, v in parse(hr.html_report(poor)).refs if t == "img"]

    out2 = tmp_path / "bare.html"
    assert run_cli(["report", "--result", str(poor), "--out", str(out2), "--no-plots"],
                   monkeypatch) == 0
    assert "<img" not in out2.read_text(encoding="utf-8")


def test_text_is_escaped(demo):
    title = '<script>alert("x")</script> & <b>'
    html = hr.html_report(demo["result"], title=title)
    assert "<script" not in html
    assert "&lt;script&gt;alert(&#34;x&#34;)&lt;/script&gt; &amp; &lt;b&gt;" in html


def test_write_report_is_atomic_and_never_replaces_a_result_file(demo, tmp_path, monkeypatch):
    out = tmp_path / "r.html"
    out.write_text("old")
    assert hr.write_report(demo["result"], out) == out  # the API replaces a file it is given
    assert out.read_text(encoding="utf-8").startswith("<!DOCTYPE html>")

    def boom(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(hr, "html_report", boom)
    with pytest.raises(RuntimeError):
        hr.write_report(demo["result"], tmp_path / "new.html")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.html"]
    monkeypatch.undo()
    for name in ("report.md", "result.json", "manifest.json", "residuals.png"):
        with pytest.raises(hr.InputError, match="overwrite a file of the result"):
            hr.write_report(demo["result"], demo["result"] / name)
    with pytest.raises(hr.InputError, match="overwrite a file of the result"):
        hr.write_report(demo["result"], demo["comp"] / "compensation.md",
                        compensation_dir=demo["comp"])


# --------------------------------------------------------------------------------------
# bad input: exit code 2, the message names the folder


def test_bad_inputs_exit_2_naming_the_folder(demo, poor, tmp_path, monkeypatch, capsys):
    out = str(tmp_path / "r.html")
    missing = tmp_path / "no_such_result"
    assert run_cli(["report", "--result", str(missing), "--out", out], monkeypatch) == 2
    err = capsys.readouterr().err
    assert "volcal report: error:" in err and str(missing) in err

    not_result = tmp_path / "some_folder"
    not_result.mkdir()
    (not_result / "notes.txt").write_text("hello")
    assert run_cli(["report", "--result", str(not_result), "--out", out], monkeypatch) == 2
    err = capsys.readouterr().err
    assert str(not_result) in err and "volcal identify" in err

    # a folder that is not a compensation export
    assert run_cli(["report", "--result", str(demo["result"]), "--compensation",
                    str(not_result), "--out", out], monkeypatch) == 2
    err = capsys.readouterr().err
    assert str(not_result) in err and "volcal compensate" in err
    assert not Path(out).exists()

    # the result's own files are never replaced, not even with --force
    target = demo["result"] / "report.md"
    assert run_cli(["report", "--result", str(demo["result"]), "--out", str(target),
                    "--force"], monkeypatch) == 2
    assert "overwrite a file of the result" in capsys.readouterr().err

    # an existing output needs --force
    Path(out).write_text("mine")
    assert run_cli(["report", "--result", str(poor), "--out", out], monkeypatch) == 2
    assert "--force" in capsys.readouterr().err and Path(out).read_text() == "mine"
    assert run_cli(["report", "--result", str(poor), "--out", out, "--force"],
                   monkeypatch) == 0


def test_pdf_without_a_browser_is_an_input_error(demo, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(hr.shutil, "which", lambda name: None)
    out = tmp_path / "r.html"
    assert run_cli(["report", "--result", str(demo["result"]), "--pdf", "--out", str(out)],
                   monkeypatch) == 2
    assert "no browser engine is installed" in capsys.readouterr().err
    with pytest.raises(hr.InputError, match="no browser engine is installed"):
        hr.write_report(demo["result"], out, pdf=True)
    assert not list(tmp_path.iterdir())


# --------------------------------------------------------------------------------------
# rendering in a real browser


def _chromium(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    browser = hr.find_browser()
    assert browser is not None
    cmd = [browser, "--headless", "--disable-gpu", "--no-sandbox", "--disable-dev-shm-usage",
           f"--user-data-dir={cwd / 'profile'}", "--enable-logging=stderr", "--v=0", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=cwd)


def _console_lines(stderr: str) -> list[str]:
    """Console messages of the page (Chromium logs them as ``...:CONSOLE...``); the page
    has no script, so any message is a problem (a failed load, a blocked resource)."""
    return [ln for ln in stderr.splitlines() if ":CONSOLE" in ln or "Uncaught" in ln]


@pytest.mark.skipif(hr.find_browser() is None,
                    reason="no chromium / chromium-browser / google-chrome on the PATH "
                    "(.ci/run installs chromium where apt-get is available)")
def test_report_renders_in_headless_chromium(demo, tmp_path, monkeypatch):
    page = hr.write_report(demo["result"], tmp_path / "report.html",
                           compensation_dir=demo["comp"])
    run = _chromium("--dump-dom", page.as_uri(), cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    assert not _console_lines(run.stderr), _console_lines(run.stderr)
    dom = run.stdout
    assert "<h1>Geometric error identification: mcv754_wxyzt</h1>" in dom
    assert 'id="parameters"' in dom and 'id="compensation"' in dom
    assert dom.count('src="data:image/png;base64,') == len(list(demo["result"].glob("*.png")))

    # the PDF prints through the same engine
    pdf = hr.write_report(demo["result"], tmp_path / "report.html", pdf=True)
    assert pdf == tmp_path / "report.pdf" and pdf.read_bytes().startswith(b"%PDF")
