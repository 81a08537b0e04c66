"""Report of an ISO 230-2 evaluation: markdown, plot, CSV tables, written all-or-nothing."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from volcal.base.exceptions import InputError
from volcal.base.folders import check_out_dir, write_folder

from .parameters import SCALAR_PARAMETERS

__all__ = ["OUTPUT_FILES", "write_report", "markdown_report", "plot"]

OUTPUT_FILES = (
    "parameters.csv",
    "targets.csv",
    "polynomial.csv",
    "correction_table.csv",
    "report.md",
    "iso230_2.png",
)


def _g(x, digits=4) -> str:
    x = float(x)
    if x == 0:
        return "0"
    if abs(x) >= 1e5 or abs(x) < 1e-3:
        return f"{x:.{digits}g}"
    dec = max(0, digits - 1 - int(np.floor(np.log10(abs(x)))))
    return f"{x:.{min(dec, 4)}f}"


def _cell(text: str) -> str:
    return str(text).replace("|", "\\|")


def _md_table(df, fmt=_g) -> str:
    """Markdown table; ``fmt`` formats float cells (a callable, or a dict column -> callable
    with ``_g`` for the rest)."""
    cols = list(df.columns)
    fmts = [(fmt.get(c, _g) if isinstance(fmt, dict) else fmt) for c in cols]
    lines = [
        "| " + " | ".join(_cell(c) for c in cols) + " |",
        "|" + "|".join("---" for _ in cols) + "|",
    ]
    for rec in df.itertuples(index=False):
        cells = [
            f(v) if isinstance(v, (float, np.floating)) else _cell(v) for f, v in zip(fmts, rec)
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(result, path) -> None:
    """ISO-style plot per axis: mean deviations per direction with the ±2s limits (joined
    linearly between targets, as the standard draws them), the fitted polynomial per
    direction and its expanded-uncertainty band (paper 003, Fig. 2)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    k = result.settings.get("k", 2.0)
    na = len(result.axes)
    fig = Figure(figsize=(9.0, 4.2 * na), layout="constrained")
    FigureCanvasAgg(fig)  # Agg, without touching pyplot's global backend
    axs = fig.subplots(na, 1, squeeze=False)[:, 0]
    for ax_plot, ax in zip(axs, result.axes):
        u = ax.units
        ps, ds = u.position_scale, u.deviation_scale
        P = ax.readings.targets * ps
        iso, mdl = ax.iso, ax.model
        x = np.linspace(mdl.lower, mdl.upper, 300)
        for lab, sym, col, mean, s in (
            ("up", "+", "tab:blue", iso.mean_up, iso.s_up),
            ("down", "-", "tab:red", iso.mean_down, iso.s_down),
        ):
            ax_plot.plot(P, mean * ds, "o", color=col, ms=4, label=f"mean deviation x̄ ({sym})")
            ax_plot.plot(P, (mean + 2 * s) * ds, "--", color=col, lw=0.8, label=f"x̄ ± 2s ({sym})")
            ax_plot.plot(P, (mean - 2 * s) * ds, "--", color=col, lw=0.8)
            f = mdl.value(x, lab) * ds
            U = mdl.expanded(x, lab, k) * ds
            ax_plot.plot(
                x * ps, f, "-", color=col, lw=1.5, label=f"degree {mdl.degree} fit ({sym})"
            )
            ax_plot.fill_between(
                x * ps,
                f - U,
                f + U,
                color=col,
                alpha=0.15,
                lw=0,
                label=f"fit ± U, k = {k:g} ({sym})",
            )
        ax_plot.axhline(0.0, color="0.5", lw=0.5)
        ax_plot.set_xlabel(f"target position [{u.position}]")
        ax_plot.set_ylabel(f"positional deviation [{u.deviation}]")
        ax_plot.set_title(
            f"axis {ax.axis}: E = {_g(iso.E * ds)} {u.deviation}, "
            f"A = {_g(iso.A * ds)} {u.deviation}, R = {_g(iso.R * ds)} "
            f"{u.deviation}, B = {_g(iso.B * ds)} {u.deviation}"
        )
        ax_plot.grid(True, lw=0.3)
        ax_plot.legend(fontsize=7, ncol=2)
    fig.savefig(path, dpi=130)


def markdown_report(result, *, correction=None, image: str | None = "iso230_2.png") -> str:
    from volcal import __version__

    k = result.settings.get("k", 2.0)
    st = result.settings
    out = [
        "# ISO 230-2 positioning evaluation",
        "",
        f"Source: `{result.source}` (volcal {__version__}).",
        "",
        "Conventions: positional deviation x = actual - target position (an error, ISO 230-1); "
        "a correction is its negative and is labelled `correction_*`. Linear axes: positions "
        "in mm, deviations in um; rotary axes: deg and arcsec.",
        "",
        f"Settings: polynomial degree {st.get('degree')}; coverage factor k = {k:g}; "
        f"instrument MPE {st.get('mpe_um', 0):g} um (linear) / {st.get('mpe_arcsec', 0):g} "
        f"arcsec (rotary), length-proportional MPE {st.get('mpe_ppm', 0):g} ppm, each turned "
        "into a standard uncertainty as MPE / sqrt(3) (rectangular distribution) and treated "
        "as fully correlated over all readings (paper 003, eqs. 7-9); "
        f"reading resolution floor {st.get('resolution_um', 0):g} um / "
        f"{st.get('resolution_arcsec', 0):g} arcsec (u(x̄_i) >= r / sqrt(12)); type A "
        "uncertainty of each mean: "
        + (
            "sqrt((n-1)/(n-3)) s_i / sqrt(n) (GUM Supplement 1, 6.4.9)"
            if st.get("type_a", "gum-s1") == "gum-s1"
            else "s_i / sqrt(n) (paper 003, eq. 10)"
        )
        + ".",
        "",
    ]
    if image:
        out += [f"![ISO 230-2 plot]({image})", ""]
    tt = result.targets_table()
    pt = result.polynomial_table()
    for ax in result.axes:
        u = ax.units
        du, ds = u.deviation, u.deviation_scale
        iso, mdl = ax.iso, ax.model
        out += [
            f"## Axis {ax.axis} ({u.kind}, {ax.readings.m} targets from "
            f"{_g(ax.readings.targets[0] * u.position_scale)} to "
            f"{_g(ax.readings.targets[-1] * u.position_scale)} {u.position}, "
            f"{ax.readings.n} bidirectional cycles)",
            "",
            "### ISO 230-2:2014 parameters",
            "",
            "| parameter | value | unit | definition |",
            "|---|---|---|---|",
        ]
        for attr, stem, desc in SCALAR_PARAMETERS:
            out.append(f"| `{stem}_{du}` | {_g(getattr(iso, attr) * ds)} | {du} | {_cell(desc)} |")
        out += ["", "### Per target", ""]
        sub = tt[tt["axis"] == ax.axis].drop(columns=["axis"])
        keep = [c for c in sub.columns if not c.startswith(("fit_", "U_fit_", "u_mean_"))]
        out += [_md_table(sub[keep], fmt=lambda v: f"{v:.3f}"), ""]
        out += [
            "### Polynomial model (paper 003)",
            "",
            f"Δ(P) = Σ a_k P^k, k = 0..{mdl.degree}, P in {u.position}, fitted by "
            "generalised least squares to the mean deviations of each direction with "
            "covariance diag(u²(x̄_i)) + u²(instrument) 1 1ᵀ; `bidir` is the mean of the "
            "two directions.",
            "",
        ]
        sub = pt[pt["axis"] == ax.axis][["direction", "coefficient", "value", "u", "unit"]]
        out += [_md_table(sub, fmt=lambda v: f"{v:.6g}"), ""]
        for lab, c2 in zip(mdl.labels, mdl.chi2):
            out.append(
                f"- chi-square of the fit ({'+' if lab == 'up' else '-'}): {c2:.3g} with "
                f"{mdl.dof} degrees of freedom"
            )
        grid = np.linspace(mdl.lower, mdl.upper, 201)
        for lab in ("up", "down", "bidir"):
            out.append(
                f"- largest expanded uncertainty U (k = {k:g}) of the fitted deviation "
                f"({lab}): {_g(mdl.expanded(grid, lab, k).max() * ds)} {du}"
            )
        out.append(
            f"- standard uncertainty of the instrument error: {_g(mdl.u_instrument * ds)} {du}"
        )
        out.append("")
    if correction is not None:
        out += [
            "## Correction table",
            "",
            f"`correction_table.csv`: {len(correction)} positions; columns "
            + ", ".join(f"`{c}`" for c in correction.columns)
            + ". `deviation_*` is the fitted error, `correction_*` = -deviation, `U_*` its "
            f"expanded uncertainty (k = {k:g}).",
            "",
        ]
    if result.warnings:
        out += ["## Warnings", ""] + [f"- {w}" for w in result.warnings] + [""]
    out += [
        "## Files",
        "",
        "- `parameters.csv`: axis parameters (name with unit suffix, value, unit)",
        "- `targets.csv`: per target: means, s, R, B per direction, fitted values",
        "- `polynomial.csv`: coefficients a_k with u and covariance (cov_a<l> in "
        "deviation-unit² / position-unit^(k+l))",
        "- `correction_table.csv`: fitted deviation, correction and U on a grid",
        "- `iso230_2.png`: the plot",
        "",
    ]
    return "\n".join(out)


def write_report(
    result, out_dir, *, spacing_mm: float | None = None, spacing_deg: float | None = None
) -> Path:
    """Write the result files (see ``OUTPUT_FILES``) into ``out_dir`` and return its path.

    All files are written into a temporary folder next to ``out_dir`` which is then renamed
    into place, so an interrupted run leaves no half-written result.  An existing
    ``out_dir`` is replaced only if it holds nothing but files of an earlier evaluation.
    """
    for name, v in (("--spacing-mm", spacing_mm), ("--spacing-deg", spacing_deg)):
        if v is not None and not (np.isfinite(v) and v > 0):
            raise InputError(
                f"{v!r} is not allowed; expected a number > 0", source=f"option {name}"
            )
    check_out_dir(Path(out_dir).absolute(), OUTPUT_FILES, "volcal iso230-2")
    correction = result.correction_table(spacing_mm=spacing_mm, spacing_deg=spacing_deg)

    def writer(tmp: Path) -> None:
        result.parameters_table().to_csv(tmp / "parameters.csv", index=False)
        result.targets_table().to_csv(tmp / "targets.csv", index=False)
        result.polynomial_table().to_csv(tmp / "polynomial.csv", index=False)
        correction.to_csv(tmp / "correction_table.csv", index=False)
        plot(result, tmp / "iso230_2.png")
        (tmp / "report.md").write_text(
            markdown_report(result, correction=correction), encoding="utf-8"
        )

    return write_folder(out_dir, OUTPUT_FILES, "volcal iso230-2", writer)
