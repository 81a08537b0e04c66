"""What an experiment can identify, and how well: the analysis behind ``volcal analyze``.

Two entry points, one report:

* :func:`analyze_plan` - before any data exist: a machine model, stations, commanded
  poses, tool offsets and an uncertainty budget.  The Jacobian is taken at the nominal
  geometry (error parameters zero unless given, noise-free readings of
  :func:`volcal.measurement.simulate.simulate`), weighted by the budget.
* :func:`analyze_result` - after an identification: the Jacobian at the solution, weighted
  as the identification was, and optionally scaled by the residual variance factor.

:class:`AnalysisReport` holds: the numerical rank of the column-scaled, constrained
Jacobian with its tolerance, the singular values and condition numbers (scaled and
unscaled); the unidentifiable directions, split into the gauge (the rigid motion of the
station set, carried by the frame variables), whole error motions the data cannot see
(``ECY, EAZ, EBZ, ECZ: no tool offset variation``) and remaining named combinations
(``EA0Z - 0.804 EAZ_0 + 0.542 EAZ_1``), each with the explanation that was *tested*
(adding reflector offsets in x, y and z makes it identifiable; an axis has too few
distinct positions for its polynomial degree); the weakest identifiable directions with
their singular values; the linearised covariance under the datum constraints (KKT /
Fisher information, :func:`volcal.analysis.constrained_covariance`); correlations and the
strongest pairs; and the standard uncertainty of the volumetric error over a grid of the
workspace.  :meth:`AnalysisReport.save` writes text, CSV and plots (singular value
spectrum, correlation heat map, uncertainty map).  The gauge and the unidentifiable are
kept apart everywhere: ``parameters.csv`` has a ``status`` per variable (determined,
imposed by the datum, gauge, unidentifiable: :meth:`AnalysisReport.status`) and the
singular values below the rank tolerance are labelled gauge or unidentifiable in
``singular_values.csv`` and ``singular_values.png`` (:func:`singular_value_kinds`).

Units: parameter values and uncertainties in um / urad, stations in mm with
uncertainties in um, volumetric errors and uncertainties in um.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import scipy.linalg as sla

from volcal.analysis.identifiability import Identifiability, _describe, scaled_constrained_svd
from volcal.base.units import report_factors
from volcal.model.datum import imposed_parameters
from volcal.model.errors import Datum
from volcal.outputs.figures import figure

log = logging.getLogger(__name__)

__all__ = [
    "AnalysisReport",
    "NullDirection",
    "analyze_plan",
    "analyze_result",
    "analyze_data",
    "analyze_jacobian_report",
    "ANALYSIS_FILES",
]

#: default tool offsets (mm) tried to explain a direction by missing offset variation
PROBE_TOOLS = ((100.0, 0.0, 0.0), (0.0, 100.0, 0.0), (0.0, 0.0, -100.0))

ANALYSIS_FILES = (
    "summary.txt",
    "report.md",
    "analysis.json",
    "singular_values.csv",
    "null_space.csv",
    "weak_directions.csv",
    "parameters.csv",
    "covariance.csv",
    "correlation.csv",
    "strongest_pairs.csv",
    "volumetric_uncertainty.csv",
    "singular_values.png",
    "correlation.png",
    "uncertainty_map.png",
)


@dataclass
class NullDirection:
    """One unidentifiable direction (or group of them).

    kind: ``gauge`` (stations and frame only), ``error`` (whole error motions: every
    datum-free variation of the listed errors), ``combination`` (a named combination);
    text: the description; explanation: the tested reason, or "" when none was found;
    dimension: how many independent directions it stands for; names: the parameters
    involved."""

    kind: str
    text: str
    explanation: str
    dimension: int
    names: list[str] = field(default_factory=list)

    def line(self) -> str:
        return f"{self.text}: {self.explanation}" if self.explanation else self.text


@dataclass
class AnalysisReport:
    """Identifiability, conditioning and linearised uncertainty of an experiment (see the
    module docstring).  ``source`` says what was analysed ("plan" or "result")."""

    source: str
    model: str
    names: list[str]
    units: list[str]
    kinds: list[str]  # per variable: error / station / frame
    x: np.ndarray  # the point of the analysis (physical)
    identifiability: Identifiability
    null: list[NullDirection]
    weak: list[tuple[float, str]]  # weakest identifiable directions (s, description)
    cov: np.ndarray  # (n, n) physical; NaN for held variables
    identifiable: np.ndarray  # (n,) bool
    cov_scale: float  # factor applied to the covariance (1 or chi2/dof)
    n_readings: int
    volumetric: pd.DataFrame
    notes: list[str] = field(default_factory=list)
    datum_tied: np.ndarray | None = None  # (n_theta, n_theta) pairs tied by the datum
    imposed: np.ndarray | None = None  # (n_theta,) parameters the datum alone sets to zero

    # ---- figures -----------------------------------------------------------------------
    @property
    def rank(self) -> int:
        return self.identifiability.rank

    @property
    def tol(self) -> float:
        return self.identifiability.tol

    @property
    def singular_values(self) -> np.ndarray:
        return self.identifiability.singular_values

    @property
    def condition(self) -> float:
        return self.identifiability.condition

    @property
    def condition_unscaled(self) -> float:
        return self.identifiability.condition_unscaled

    @property
    def n_theta(self) -> int:
        return int(sum(k == "error" for k in self.kinds))

    @property
    def unidentifiable_errors(self) -> list[NullDirection]:
        """Null directions that involve error parameters (the gauge left out)."""
        return [d for d in self.null if d.kind != "gauge"]

    def _factors(self) -> np.ndarray:
        return report_factors(self.units)

    def status(self) -> list[str]:
        """Per variable: ``determined`` (by the data), ``imposed`` (an error parameter the
        datum alone sets to zero: u = 0 by convention), ``gauge`` (a station or frame
        variable the rigid motion of the station set moves: held, not a property of the
        machine) or ``unidentifiable`` (the data do not determine it)."""
        gauge = {n for d in self.null if d.kind == "gauge" for n in d.names}
        other = {n for d in self.null if d.kind != "gauge" for n in d.names}
        imposed = np.zeros(len(self.names), bool)
        if self.imposed is not None:
            imposed[: len(self.imposed)] = self.imposed
        out = []
        for name, kind, ok, imp in zip(self.names, self.kinds, self.identifiable, imposed):
            if ok:
                out.append("imposed" if imp else "determined")
            elif kind != "error" and (name in gauge or name not in other):
                out.append("gauge")
            else:
                out.append("unidentifiable")
        return out

    def parameters(self) -> pd.DataFrame:
        """name, kind, unit (um / urad; stations mm with u in um), value, u, identifiable,
        status (:meth:`status`: determined, imposed, gauge or unidentifiable)."""
        f = self._factors()
        u = np.sqrt(np.clip(np.diag(self.cov), 0, None)) * f
        u[~self.identifiable] = np.nan
        unit = []
        val = []
        for i, (k, un) in enumerate(zip(self.kinds, self.units)):
            if k == "station":
                unit.append("mm (u in um)")
                val.append(self.x[i])
            else:
                unit.append("um" if un == "mm" else "urad")
                val.append(self.x[i] * f[i])
        return pd.DataFrame(
            {
                "name": self.names,
                "kind": self.kinds,
                "unit": unit,
                "value": val,
                "u": u,
                "identifiable": self.identifiable,
                "status": self.status(),
            }
        )

    def correlation(self, include_stations: bool = False) -> pd.DataFrame:
        """Correlation matrix of the identifiable error parameters (and stations)."""
        sel = self.identifiable & np.array(
            [k == "error" or (include_stations and k == "station") for k in self.kinds]
        )
        idx = np.flatnonzero(sel)
        C = self.cov[np.ix_(idx, idx)]
        s = np.sqrt(np.clip(np.diag(C), 0, None))
        with np.errstate(invalid="ignore", divide="ignore"):
            R = C / np.outer(s, s)
        names = [self.names[i] for i in idx]
        return pd.DataFrame(R, index=names, columns=names)

    def strongest_pairs(self, k: int = 10, include_stations: bool = False) -> pd.DataFrame:
        """The k most correlated pairs: a, b, rho (|rho| descending).  Pairs that the
        datum constraints alone tie together (e.g. the Legendre coefficients 0 and 2 of a
        straightness held at zero at both ends: rho = -1 whatever the data) are left out."""
        R = self.correlation(include_stations)
        a = R.to_numpy()
        iu = np.triu_indices_from(a, 1)
        vals = a[iu].copy()
        if self.datum_tied is not None:
            pos = {nm: i for i, nm in enumerate(self.names[: self.n_theta])}
            names_ = list(R.index)
            for j, (i1, i2) in enumerate(zip(*iu)):
                p1, p2 = pos.get(names_[i1]), pos.get(names_[i2])
                if p1 is not None and p2 is not None and self.datum_tied[p1, p2]:
                    vals[j] = np.nan
        keep = np.flatnonzero(np.isfinite(vals))
        order = keep[np.argsort(-np.abs(vals[keep]))][:k]
        names = list(R.index)
        return pd.DataFrame(
            {
                "a": [names[iu[0][j]] for j in order],
                "b": [names[iu[1][j]] for j in order],
                "rho": vals[order],
            }
        )

    def covariance_frame(self) -> pd.DataFrame:
        """The covariance in report units (um, urad; products thereof)."""
        f = self._factors()
        return pd.DataFrame(self.cov * np.outer(f, f), index=self.names, columns=self.names)

    def max_volumetric_uncertainty(self) -> dict[str, float]:
        v = self.volumetric
        i = int(np.argmax(v["u_total_um"].to_numpy()))
        return {
            "u_total_max_um": float(v["u_total_um"].iloc[i]),
            "u_component_max_um": float(v[["u_dx_um", "u_dy_um", "u_dz_um"]].max().max()),
            "pose_index": i,
        }

    # ---- text ------------------------------------------------------------------------------
    def summary(self, *, top: int = 8) -> str:
        idn = self.identifiability
        lines = [
            f"volcal analyze ({self.source}): model '{self.model}', "
            f"{self.n_readings} readings, {len(self.names)} variables "
            f"({self.n_theta} parameters: the basis coefficients of the error quantities)",
            f"  numerical rank        {idn.rank} of {idn.rank + idn.n_null} free "
            f"directions under the datum constraints (tolerance {idn.tol:.3g} on "
            f"column-scaled singular values)",
            f"  condition number      {idn.condition:.4g} (scaled), "
            f"{idn.condition_unscaled:.4g} (unscaled)",
        ]
        s = idn.singular_values[: idn.rank]
        if len(s):
            lines.append(f"  singular values       {s[0]:.4g} ... {s[-1]:.4g} (scaled)")
        gauge = [d for d in self.null if d.kind == "gauge"]
        if gauge:
            lines.append(
                f"  gauge                 {sum(d.dimension for d in gauge)} "
                f"direction(s): {gauge[0].explanation}"
            )
        unid = self.unidentifiable_errors
        if unid:
            lines.append(
                f"  unidentifiable        {sum(d.dimension for d in unid)} "
                "direction(s) involving parameters of the error quantities:"
            )
            for d in unid:
                lines.append(f"    {d.line()}")
        else:
            lines.append("  unidentifiable        none (every error parameter is determined)")
        if self.weak:
            lines.append("  weakest directions    (scaled singular value: direction)")
            for sv, txt in self.weak[:top]:
                lines.append(f"    {sv:.3g}: {txt}")
        if self.cov_scale != 1.0:
            lines.append(
                f"  covariance            scaled by the residual variance factor "
                f"{self.cov_scale:.4g}"
            )
        par = self.parameters()
        err = par[(par["kind"] == "error") & par["identifiable"]]
        if len(err):
            big = err.sort_values("u", ascending=False).head(5)
            lines.append(
                "  largest uncertainties "
                + ", ".join(f"{r.name} {r.u:.3g} {r.unit}" for r in big.itertuples())
            )
        pairs = self.strongest_pairs(5)
        if len(pairs):
            lines.append(
                "  strongest correlations (datum ties left out) "
                + ", ".join(f"{r.a}/{r.b} {r.rho:+.3f}" for r in pairs.itertuples())
            )
        mv = self.max_volumetric_uncertainty()
        lines.append(
            f"  volumetric error      standard uncertainty up to "
            f"{mv['u_total_max_um']:.3g} um (vector), {mv['u_component_max_um']:.3g} "
            f"um (component) over {len(self.volumetric)} poses"
        )
        for n in self.notes:
            lines.append(f"  note: {n}")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        idn = self.identifiability
        return {
            "source": self.source,
            "model": self.model,
            "n_readings": self.n_readings,
            "rank": idn.rank,
            "n_free_directions": idn.rank + idn.n_null,
            "tolerance": idn.tol,
            "condition_scaled": idn.condition,
            "condition_unscaled": idn.condition_unscaled,
            "singular_values": idn.singular_values.tolist(),
            "null_space": [
                {
                    "kind": d.kind,
                    "text": d.text,
                    "explanation": d.explanation,
                    "dimension": d.dimension,
                    "names": d.names,
                }
                for d in self.null
            ],
            "weak": [{"singular_value": s, "direction": t} for s, t in self.weak],
            "covariance_scale": self.cov_scale,
            "max_volumetric_uncertainty": self.max_volumetric_uncertainty(),
            "notes": self.notes,
        }

    # ---- files -----------------------------------------------------------------------------
    def save(self, out_dir: str | Path, *, plots: bool = True) -> Path:
        """Write the report files (:data:`ANALYSIS_FILES`) into ``out_dir`` (atomically:
        a temporary folder renamed into place; an existing folder is replaced only if it
        holds nothing but these files)."""
        from volcal.base.folders import write_folder

        return write_folder(out_dir, ANALYSIS_FILES, "an analysis", lambda d: self._write(d, plots))

    def _write(self, d: Path, plots: bool) -> None:
        idn = self.identifiability
        (d / "summary.txt").write_text(self.summary() + "\n")
        (d / "analysis.json").write_text(json.dumps(self.to_dict(), indent=2) + "\n")
        s = idn.singular_values
        pd.DataFrame(
            {
                "index": np.arange(1, len(s) + 1),
                "singular_value": s,
                "relative": s / s[0] if len(s) and s[0] > 0 else s,
                "above_tolerance": s > idn.tol,
                # gauge and unidentifiable apart (see singular_value_kinds)
                "kind": singular_value_kinds(self),
            }
        ).to_csv(d / "singular_values.csv", index=False)
        pd.DataFrame(
            [
                {
                    "kind": n.kind,
                    "direction": n.text,
                    "dimension": n.dimension,
                    "explanation": n.explanation,
                    "parameters": " ".join(n.names),
                }
                for n in self.null
            ],
            columns=["kind", "direction", "dimension", "explanation", "parameters"],
        ).to_csv(d / "null_space.csv", index=False)
        pd.DataFrame(self.weak, columns=["singular_value", "direction"]).to_csv(
            d / "weak_directions.csv", index=False
        )
        self.parameters().to_csv(d / "parameters.csv", index=False)
        self.covariance_frame().to_csv(d / "covariance.csv")
        self.correlation().to_csv(d / "correlation.csv")
        self.strongest_pairs(20).to_csv(d / "strongest_pairs.csv", index=False)
        self.volumetric.to_csv(d / "volumetric_uncertainty.csv", index=False)
        (d / "report.md").write_text(self._markdown(plots))
        if plots:
            plot_singular_values(self, d / "singular_values.png")
            plot_correlation(self.correlation(), d / "correlation.png")
            plot_uncertainty_map(self.volumetric, d / "uncertainty_map.png")

    def _markdown(self, plots: bool) -> str:
        lines = [
            f"# Identifiability and uncertainty analysis ({self.source})",
            "",
            "```",
            self.summary(top=12),
            "```",
            "",
        ]
        if self.null:
            lines += [
                "## Unidentifiable directions",
                "",
                "| kind | direction | dim | explanation |",
                "|---|---|---|---|",
            ]
            for n in self.null:
                lines.append(f"| {n.kind} | {n.text} | {n.dimension} | {n.explanation} |")
            lines.append("")
        pairs = self.strongest_pairs(10)
        if len(pairs):
            lines += ["## Strongest correlations", "", "| a | b | rho |", "|---|---|---|"]
            lines += [f"| {r.a} | {r.b} | {r.rho:+.3f} |" for r in pairs.itertuples()]
            lines.append("")
        if plots:
            lines += [
                "## Plots",
                "",
                "![singular values](singular_values.png)",
                "",
                "![correlation](correlation.png)",
                "",
                "![volumetric uncertainty](uncertainty_map.png)",
                "",
            ]
        lines += [
            "Files: parameters.csv (values and standard uncertainties), covariance.csv, "
            "correlation.csv, strongest_pairs.csv, singular_values.csv, null_space.csv, "
            "weak_directions.csv, volumetric_uncertainty.csv (standard uncertainties "
            "u_dx_um, u_dy_um, u_dz_um, u_total_um = sqrt of their squares' sum, and "
            "u_norm_um of |d| where the error is well above its uncertainty).",
            "",
        ]
        return "\n".join(lines)


# --------------------------------------------------------------------------------------
# plots (matplotlib object API, Agg canvas)


def singular_value_kinds(rep: AnalysisReport) -> np.ndarray:
    """Per singular value: ``determined`` (above the rank tolerance), ``gauge`` or
    ``unidentifiable``.  The null directions below the tolerance are split by count: as
    many as the gauge has dimensions are the gauge (the smallest ones: a rigid motion
    changes no reading at all), the others are unidentifiable (which value belongs to which
    direction is arbitrary inside the null space; the counts are what is known)."""
    s = np.asarray(rep.singular_values, float)
    kind = np.where(s > rep.tol, "determined", "unidentifiable").astype(object)
    below = np.flatnonzero(s <= rep.tol)
    n_gauge = min(sum(d.dimension for d in rep.null if d.kind == "gauge"), len(below))
    if n_gauge:
        smallest = below[np.argsort(s[below], kind="stable")[:n_gauge]]
        kind[smallest] = "gauge"
    return kind


def plot_singular_values(rep: AnalysisReport, path: Path) -> Any:
    """singular_values.png: the determined, gauge and unidentifiable singular values apart
    (:func:`singular_value_kinds`); returns the figure."""
    s = rep.singular_values
    fig = figure(7, 4, layout="constrained")
    ax = fig.subplots()
    idx = np.arange(1, len(s) + 1)
    kind = singular_value_kinds(rep)
    ok = kind == "determined"
    ax.semilogy(idx[ok], s[ok], "o", markersize=3, label="determined by the data")
    floor = np.maximum(s, rep.tol * 1e-3)
    gauge = kind == "gauge"
    if gauge.any():
        ax.semilogy(
            idx[gauge],
            floor[gauge],
            "s",
            markersize=4,
            color="tab:gray",
            label=f"gauge ({int(gauge.sum())}: rigid motion no multilateration sees, "
            "held by the datum)",
        )
    unid = kind == "unidentifiable"
    if unid.any():
        ax.semilogy(
            idx[unid],
            floor[unid],
            "x",
            color="tab:red",
            label=f"unidentifiable ({int(unid.sum())}: error parameters the data do not determine)",
        )
    ax.axhline(rep.tol, color="tab:red", linewidth=0.8, linestyle="--", label="rank tolerance")
    ax.set_xlabel("index")
    ax.set_ylabel("singular value (column-scaled Jacobian)")
    ax.set_title(f"Singular values: rank {rep.rank}, condition {rep.condition:.3g} (scaled)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    return fig


def plot_correlation(R: pd.DataFrame, path: Path) -> None:
    n = len(R)
    size = min(14.0, max(5.0, 0.14 * n + 2))
    fig = figure(size + 1.2, size, layout="constrained")
    ax = fig.subplots()
    im = ax.imshow(R.to_numpy(), cmap="RdBu_r", vmin=-1, vmax=1, interpolation="nearest")
    fig.colorbar(im, ax=ax, shrink=0.7, label="correlation")
    if n <= 120:
        fs = max(3.0, min(8.0, 400.0 / max(n, 1)))
        ax.set_xticks(range(n), R.columns, rotation=90, fontsize=fs)
        ax.set_yticks(range(n), R.index, fontsize=fs)
    ax.set_title("Correlation of the identifiable parameters (basis coefficients)")
    fig.savefig(path, dpi=110)


def plot_uncertainty_map(vol: pd.DataFrame, path: Path) -> None:
    fig = figure(8, 6.5, layout="constrained")
    ax = fig.add_subplot(projection="3d")
    P = vol[["x_mm", "y_mm", "z_mm"]].to_numpy()
    sc = ax.scatter(*P.T, c=vol["u_total_um"].to_numpy(), cmap="viridis", s=25)
    fig.colorbar(
        sc, ax=ax, shrink=0.6, label="standard uncertainty of the volumetric error vector (µm)"
    )
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    ax.set_title(
        "Linearised standard uncertainty of the volumetric error "
        f"(max {vol['u_total_um'].max():.3g} um)",
        fontsize=10,
    )
    fig.savefig(path, dpi=110)


# --------------------------------------------------------------------------------------
# the analysis


def _kinds(ider) -> list[str]:
    return [
        "error" if a else ("station" if b else "frame")
        for a, b in zip(ider.is_theta, ider.is_station)
    ]


def _orth(A: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    if A.size == 0:
        return np.zeros((A.shape[0], 0))
    U, s, _ = np.linalg.svd(A, full_matrices=False)
    return U[:, s > tol * max(1.0, s[0] if len(s) else 0.0)]


def _theta_null(
    J: np.ndarray, Cs: np.ndarray, nt: int, fixed: np.ndarray
) -> tuple[np.ndarray, float]:
    """Orthonormal basis (nt, k) of the theta parts of the null space of J on the free
    variables under C x = 0 (column-scaled as analyse_jacobian), and the rank tolerance
    relative to the largest singular value."""
    sv = scaled_constrained_svd(J, Cs, fixed)
    free, tol = sv.free, sv.tol
    Ny = sv.Z @ sv.Vt[sv.rank :].T * sv.d[:, None]  # problem-scaled free variables
    full = np.zeros((J.shape[1], Ny.shape[1]))
    full[free] = Ny
    return _orth(full[:nt]), tol


def _probe_jacobian(
    ider, x: np.ndarray, q: np.ndarray, tool: np.ndarray, station_index: np.ndarray, w: np.ndarray
) -> np.ndarray:
    """Jacobian (scaled variables) of readings at poses q with tools, using the structured
    first-order model (for testing hypotheses about the plan)."""
    from volcal.analysis.uncertainty.engine import StructuredLSQ, _point_model, reading_tape

    pr = ider.problem
    P0, G = _point_model(pr.machine, pr.error_model, q, tool)
    eng = StructuredLSQ(
        P0=P0,
        G=G,
        w=w,
        m=np.zeros(len(w)),
        station_index=np.asarray(station_index, int),
        n_stations=pr.layout.n_stations,
        x_hat=np.asarray(x, float),
        fixed=np.zeros(pr.n_x, bool),
        scale=pr.scale,
        Z=np.zeros((0, 0)),
        R=np.zeros((0, 0)),
        reading=reading_tape(pr.instrument),
    )
    return eng.jacobian(np.asarray(x, float))


def _null_directions(
    ider,
    J: np.ndarray,
    x: np.ndarray,
    ident: Identifiability,
    user_fixed: np.ndarray,
    q: np.ndarray,
    tool: np.ndarray,
    station_index: np.ndarray,
    w: np.ndarray,
) -> list[NullDirection]:
    """Split the null space into gauge, whole error motions and combinations, and test
    explanations (see the module docstring)."""
    pr = ider.problem
    em = pr.error_model
    nt = pr.n_theta
    names = pr.names
    basis = ident.null_basis  # (n, k), problem-scaled
    out: list[NullDirection] = []
    if basis.shape[1] == 0:
        return out
    Cs = ider._scaled_constraints()
    T, _ = _theta_null(J, Cs, nt, user_fixed)  # theta part of the null space
    k_gauge = basis.shape[1] - T.shape[1]
    if k_gauge > 0:
        involved = [
            names[i] for i in np.flatnonzero(np.abs(basis[nt:]).max(axis=1) > 1e-9).__add__(nt)
        ]
        out.append(
            NullDirection(
                "gauge",
                f"rigid motion of the station set ({k_gauge} directions)",
                "gauge freedom: stations and machine frame move together; held by fixing the "
                "frame variables, not a property of the machine errors",
                k_gauge,
                involved,
            )
        )
    if T.shape[1] == 0:
        return out

    # the explanations: readings with extra reflector offsets; distinct axis positions
    uniq_tools = np.unique(np.round(tool, 9), axis=0)
    probe = [t for t in PROBE_TOOLS]
    qs, ts, ss, ws = [q], [tool], [station_index], [w]
    for t in probe:
        ts.append(tool + np.asarray(t)[None, :])
        qs.append(q)
        ss.append(station_index)
        ws.append(w)
    Jp = _probe_jacobian(
        ider, x, np.concatenate(qs), np.concatenate(ts), np.concatenate(ss), np.concatenate(ws)
    )
    Tp, _ = _theta_null(Jp, Cs, nt, user_fixed)

    def in_space(v: np.ndarray, B: np.ndarray) -> bool:
        if B.shape[1] == 0:
            return False
        return np.linalg.norm(v - B @ (B.T @ v)) < 1e-6 * np.linalg.norm(v)

    n_pos = {a.name: len(np.unique(np.round(q[:, j], 9))) for j, a in enumerate(em.spec.axes)}

    def explain(vs: np.ndarray, err_ids: list[int]) -> str:
        """vs (nt, m) theta directions; err_ids the error quantities involved."""
        few = []
        for k in err_ids:
            f = em.forms[k]
            a = em.errors[k].axis
            if f.kind == "poly" and n_pos[a] <= f.degree:
                few.append(
                    f"only {n_pos[a]} distinct positions of axis {a} for the "
                    f"degree-{f.degree} error motions of {a}"
                )
            elif f.kind in ("fourier", "bspline") and n_pos[a] < f.n_params:
                few.append(
                    f"only {n_pos[a]} distinct positions of axis {a} for the "
                    f"{f.n_params}-function {f.kind} error motions of {a}"
                )
        if few:
            return "; ".join(dict.fromkeys(few))
        if all(not in_space(vs[:, j], Tp) for j in range(vs.shape[1])):
            what = (
                "a single tool offset"
                if len(uniq_tools) == 1
                else f"{len(uniq_tools)} tool offsets"
            )
            return (
                f"no tool offset variation ({what}): identifiable once reflector offsets "
                "in x, y and z are measured too"
            )
        if any(not in_space(vs[:, j], Tp) for j in range(vs.shape[1])):
            return "partly resolved by reflector offsets in x, y and z"
        return "not separated by this plan (more stations or poses needed)"

    # whole error motions: every datum-free variation of error k lies in T
    C = pr.C
    whole: list[int] = []
    for k in range(em.n_errors):
        idx = np.flatnonzero(em.param_error_arr == k)
        rows: Any = np.flatnonzero(np.abs(C[:, idx]).sum(axis=1) > 0) if C.shape[0] else []
        Ck = C[np.ix_(rows, idx)] * pr.scale[idx][None, :] if len(rows) else np.zeros((0, len(idx)))
        E = sla.null_space(Ck) if Ck.shape[0] else np.eye(len(idx))
        if E.shape[1] == 0:
            continue
        Ev = np.zeros((nt, E.shape[1]))
        Ev[idx] = E
        if all(in_space(Ev[:, j], T) for j in range(E.shape[1])):
            whole.append(k)
    rest = T
    if whole:
        # group the whole error motions by their explanation
        groups: dict[str, list[int]] = {}
        W = []
        for k in whole:
            idx = np.flatnonzero(em.param_error_arr == k)
            rows = np.flatnonzero(np.abs(C[:, idx]).sum(axis=1) > 0) if C.shape[0] else []
            Ck = (
                C[np.ix_(rows, idx)] * pr.scale[idx][None, :]
                if len(rows)
                else np.zeros((0, len(idx)))
            )
            E = sla.null_space(Ck) if Ck.shape[0] else np.eye(len(idx))
            Ev = np.zeros((nt, E.shape[1]))
            Ev[idx] = E
            W.append(Ev)
            groups.setdefault(explain(Ev, [k]), []).append(k)
        for why, ks in groups.items():
            dim = sum(W[whole.index(k)].shape[1] for k in ks)
            involved = [names[i] for k in ks for i in np.flatnonzero(em.param_error_arr == k)]
            out.append(
                NullDirection(
                    "error",
                    ", ".join(em.errors[k].name for k in ks) + " (whole error motions)",
                    why,
                    dim,
                    involved,
                )
            )
        Wall = _orth(np.concatenate(W, axis=1))
        rest = _orth(T - Wall @ (Wall.T @ T))
    if rest.shape[1]:
        # one named combination per remaining direction: reduced row echelon on pivots
        m = rest.shape[1]
        _, _, piv = sla.qr(rest.T, pivoting=True, mode="economic")
        piv = list(piv[:m])
        Rr = np.linalg.solve(rest[piv, :].T, rest.T)  # (m, nt), identity on pivots
        for j, pv in enumerate(piv):
            v = Rr[j]
            # in the parameters' own units: scaled variable * scale
            txt = _describe(v, names[:nt], pv)
            err_ids = sorted(
                {
                    int(em.param_error_arr[i])
                    for i in np.flatnonzero(np.abs(v) > 1e-3 * np.abs(v).max())
                }
            )
            involved = [names[i] for i in np.flatnonzero(np.abs(v) > 1e-3 * np.abs(v).max())]
            out.append(NullDirection("combination", txt, explain(v[:, None], err_ids), 1, involved))
    return out


def _weak_directions(
    J: np.ndarray, Cs: np.ndarray, fixed: np.ndarray, names: list[str], rank_tol: float, k: int = 8
) -> list[tuple[float, str]]:
    """The k weakest identifiable directions: (scaled singular value, description)."""
    sv = scaled_constrained_svd(J, Cs, fixed)
    free, Z, s, Vt = sv.free, sv.Z, sv.s, sv.Vt
    ok = np.flatnonzero(s > rank_tol)
    out = []
    fnames = [names[i] for i in free]
    for j in ok[::-1][:k]:
        v = Z @ Vt[j]
        lead = int(np.argmax(np.abs(v)))
        out.append((float(s[j]), _describe(v, fnames, lead, rel=0.05)))
    return out


def _volumetric(
    machine, em, theta: np.ndarray, cov_theta: np.ndarray, eval_points: pd.DataFrame
) -> pd.DataFrame:
    from volcal.analysis.identify import predict_volumetric

    q = machine.axis_to_internal(eval_points[machine.axis_names].to_numpy(float))
    tool = (
        eval_points[["tool_x", "tool_y", "tool_z"]].to_numpy(float)
        if "tool_x" in eval_points
        else np.zeros((len(q), 3))
    )
    pred = predict_volumetric(machine, em, theta, cov_theta, q, tool)
    p0, _, Je = machine.evaluate(q, tool, np.zeros(machine.n_errors))
    out = eval_points[machine.axis_names].reset_index(drop=True).copy()
    out[["tool_x", "tool_y", "tool_z"]] = tool
    out[["x_mm", "y_mm", "z_mm"]] = p0
    for c in ("dx_um", "dy_um", "dz_um", "u_dx_um", "u_dy_um", "u_dz_um"):
        out[c] = pred[c].to_numpy()
    out["u_total_um"] = np.sqrt(out["u_dx_um"] ** 2 + out["u_dy_um"] ** 2 + out["u_dz_um"] ** 2)
    # uncertainty of |d| where |d| is well above its uncertainty (else not linearisable)
    G = em.apply_basis(Je, q)
    d = pred[["dx_um", "dy_um", "dz_um"]].to_numpy()
    nrm = np.linalg.norm(d, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = d / nrm[:, None]
    g = np.einsum("ni,nip->np", np.nan_to_num(n), G)
    var = np.einsum("np,pq,nq->n", g, np.nan_to_num(cov_theta), g) * 1e6
    u_norm = np.sqrt(np.clip(var, 0, None))
    out["norm_um"] = nrm
    out["u_norm_um"] = np.where(nrm > 5 * out["u_total_um"], u_norm, np.nan)
    return out


def analyze_jacobian_report(
    ider,
    x: np.ndarray,
    p: np.ndarray,
    *,
    source: str,
    user_fixed: np.ndarray | None = None,
    cov_scale: float = 1.0,
    eval_points: pd.DataFrame | None = None,
    n_weak: int = 8,
    notes: list[str] | None = None,
    datum_active: np.ndarray | None = None,
) -> AnalysisReport:
    """The report for an Identifier at x (physical) with data vector p (weights included).
    The datum: the candidate conditions ``datum_active`` (those an identification imposed),
    or when None those that remove a null direction at x (:mod:`volcal.model.datum`).
    The null directions' pivots are held (frame variables first, as the joint
    identification does) for the covariance."""
    from volcal.analysis.uncertainty.engine import unpack_data
    from volcal.base import progress
    from volcal.measurement.plans import grid_plan

    pr = ider.problem
    machine = pr.machine
    n = pr.n_x
    user_fixed = np.zeros(n, bool) if user_fixed is None else np.asarray(user_fixed, bool)
    with progress.stage("identifiability and covariance"):
        # datum, rank, null space and pivots are decided at zero errors (the structural
        # point), as identify, mc and plan decide them; the covariance is x's
        if datum_active is None:
            ider.select_datum(x, p, user_fixed)
        else:
            pr.set_datum(datum_active)
        x0 = ider.structural(x)
        _, J0 = ider.jacobian(x0, p)
        _, J = ider.jacobian(x, p)
        ident = ider.analyse(x, p, user_fixed)
        fixed = user_fixed.copy()
        fixed[ident.pivots] = True
        cov = ider.covariance(x, p, fixed) * cov_scale
    identifiable = ~(ident.unidentifiable | fixed)
    q, t, _, w = unpack_data(machine.n_axes, p)
    null = _null_directions(
        ider, J0, x0, ident, user_fixed, q, t, np.asarray(pr.layout.station_index), w
    )
    Cs = ider._scaled_constraints()
    weak = _weak_directions(J, Cs, fixed, pr.names, ident.tol, n_weak)
    if eval_points is None:
        eval_points = grid_plan(machine.spec, 5)
    nt = pr.n_theta
    cov_t = cov[:nt, :nt].copy()
    cov_t[~identifiable[:nt], :] = 0.0
    cov_t[:, ~identifiable[:nt]] = 0.0
    vol = _volumetric(machine, pr.error_model, x[:nt], cov_t, eval_points)
    notes = list(notes or [])
    if (~identifiable[:nt]).any():
        notes.append(
            "volumetric uncertainties leave out the unidentifiable directions "
            "(held at zero); they are not determined at all"
        )
    # pairs the datum constraints tie exactly (correlation +-1 within null(C) alone)
    tied = None
    if pr.C.shape[0]:
        Zc = sla.null_space(pr.C * pr.scale[None, :nt])
        P = Zc @ Zc.T
        dg = np.sqrt(np.clip(np.diag(P), 1e-300, None))
        tied = np.abs(P / np.outer(dg, dg)) > 1 - 1e-9
        np.fill_diagonal(tied, False)
    return AnalysisReport(
        source,
        machine.spec.name,
        list(pr.names),
        list(pr.units),
        _kinds(ider),
        np.asarray(x, float),
        ident,
        null,
        weak,
        cov,
        identifiable,
        float(cov_scale),
        int(len(w)),
        vol,
        notes,
        tied,
        imposed_parameters(pr.conditions, pr.datum_active, nt) & identifiable[:nt],
    )


def analyze_plan(
    model,
    plan: pd.DataFrame,
    stations,
    tools=None,
    budget="paper002",
    *,
    error_model=None,
    degree: int = 3,
    datum: Datum = "iso230",
    theta: np.ndarray | None = None,
    eval_points: pd.DataFrame | None = None,
    n_weak: int = 8,
) -> AnalysisReport:
    """Analyse a measurement plan before measuring: model (name, file, spec or Machine),
    plan (poses, mm / deg), stations (table or file: positions and dead lengths), tools
    (K, 3) mm (default one offset at 0), budget (name, file or Budget).  The readings are
    the noise-free lengths at ``theta`` (default 0), weighted by the budget."""
    from volcal.analysis.identify import Identifier
    from volcal.measurement.budget import load_budget
    from volcal.measurement.simulate import simulate
    from volcal.measurement.tables import load_measurements
    from volcal.model.errors import ErrorForm, ErrorModel
    from volcal.model.machine import Machine
    from volcal.problem.residuals import Layout

    machine = model if isinstance(model, Machine) else Machine.from_model(model)
    em = error_model or ErrorModel(machine.spec, default=ErrorForm("poly", degree), datum=datum)
    bud = load_budget(budget)
    tools = np.zeros((1, 3)) if tools is None else np.atleast_2d(np.asarray(tools, float))
    th = np.zeros(em.n_params) if theta is None else np.asarray(theta, float)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sim = simulate(machine, em, th, stations, plan, tools, bud, 0, noise=False)
        meas = load_measurements(sim.measurements, machine.spec)
    layout = Layout.from_measurements(meas)
    ider = Identifier(machine, em, layout)
    pr = ider.problem
    st = sim.stations[["x_mm", "y_mm", "z_mm", "dead_length_mm"]].to_numpy(float)
    x = pr.pack_x(th, st)
    p = pr.pack_data(meas.q_internal, meas.tool, meas.length, 1.0 / meas.sigma)
    user_fixed = ider.station_fixed(
        np.asarray(sim.stations.get("fixed", np.zeros(len(st), bool)), bool)
    )
    notes = [
        f"plan: {len(plan)} poses x {len(tools)} tool offset(s) x {len(st)} stations; "
        f"budget {bud.name}; readings noise-free at the "
        f"{'given' if theta is not None else 'zero'} parameters"
    ]
    return analyze_jacobian_report(
        ider,
        x,
        p,
        source="plan",
        user_fixed=user_fixed,
        eval_points=eval_points,
        n_weak=n_weak,
        notes=notes,
    )


def analyze_result(
    result,
    measurements,
    *,
    budget=None,
    scale_covariance: bool = False,
    eval_points: pd.DataFrame | None = None,
    n_weak: int = 8,
) -> AnalysisReport:
    """Analyse an identification (an :class:`~volcal.analysis.identify.IdentificationResult` and
    the validated measurements it came from) at its solution, weighted as it was.
    ``scale_covariance`` multiplies the covariance by the residual variance factor
    chi2/dof of the identification."""
    from volcal.analysis.identify import Identifier
    from volcal.analysis.uncertainty.montecarlo import fixed_mask, identification_data
    from volcal.problem.residuals import Layout

    meas = measurements
    layout = Layout.from_measurements(meas)
    ider = Identifier(result.machine, result.error_model, layout)
    pr = ider.problem
    x, w = identification_data(result, meas, budget)
    p = pr.pack_data(meas.q_internal, meas.tool, meas.length, w)
    held = fixed_mask(ider, result)
    # held by the user (fixed stations) or by the strategy, not the null-space pivots
    user_fixed = held.copy()
    if result.identifiability is not None:
        user_fixed[list(result.identifiability.pivots)] = False
    if result.strategy in ("two-phase", "points-only"):
        user_fixed[ider.is_station] = True
    chi2 = float(result.conditions.get("chi2_per_dof", 1.0))
    notes = [
        f"identification: strategy {result.strategy}, status {result.status}, chi2/dof {chi2:.4g}"
    ]
    return analyze_jacobian_report(
        ider,
        x,
        p,
        source="result",
        user_fixed=user_fixed,
        cov_scale=chi2 if scale_covariance else 1.0,
        eval_points=eval_points,
        n_weak=n_weak,
        notes=notes,
        datum_active=pr.datum_active,
    )


def analyze_data(
    model,
    data,
    stations=None,
    *,
    budget="paper002",
    strategy: str = "joint",
    degree: int = 3,
    datum: Datum = "iso230",
    error_model=None,
    scale_covariance: bool = False,
    eval_points: pd.DataFrame | None = None,
) -> tuple[AnalysisReport, Any]:
    """Identify, then :func:`analyze_result`.  Returns (report, identification result)."""
    from volcal.analysis.identify import identify
    from volcal.measurement.budget import load_budget
    from volcal.measurement.tables import load_measurements, load_stations
    from volcal.model.machine import Machine

    machine = model if isinstance(model, Machine) else Machine.from_model(model)
    bud = load_budget(budget)
    st = None
    if stations is not None:
        st = (
            stations
            if isinstance(stations, pd.DataFrame) and "dead_length_given" in stations
            else load_stations(stations)
        )
    meas = (
        data if hasattr(data, "q_internal") else load_measurements(data, machine.spec, stations=st)
    )
    res = identify(
        machine,
        meas,
        st,
        strategy=strategy,
        degree=degree,
        datum=datum,
        error_model=error_model,
        budget=bud,
    )
    return analyze_result(
        res, meas, budget=bud, scale_covariance=scale_covariance, eval_points=eval_points
    ), res


def result_inputs(path) -> dict[str, Any]:
    """What is needed to redo the identification of a result folder written by
    ``volcal identify`` (its ``result.json`` and ``residuals.csv``): ``machine``,
    ``error_model``, ``data`` (the input rows, DataFrame), ``stations`` (the stations file
    the identification was given, when it still exists), ``budget``, ``strategy``,
    ``theta`` (the saved estimate, mm / rad).  Re-identifying these inputs reproduces the
    result (the identification is deterministic); callers compare with ``theta``."""
    from volcal.base.exceptions import InputError
    from volcal.outputs.results import load_result

    res = load_result(path)
    folder = Path(res.path)
    if res.meta.get("instruments"):
        raise InputError(
            "this result identifies several instruments' tables as one problem ("
            + ", ".join(str(r.get("data")) for r in res.meta["instruments"])
            + "); redoing it from the result folder is not supported yet: analyse or "
            "simulate from the tables themselves",
            source=str(folder),
        )
    f = folder / "residuals.csv"
    if not f.is_file():
        raise InputError(
            "the result folder has no residuals.csv (the input rows)", source=str(folder)
        )
    data = pd.read_csv(f)
    data = data.drop(
        columns=[c for c in ("residual_um", "normalised_residual", "rejected") if c in data]
    )
    opts = res.meta.get("options", {}) or {}
    st = opts.get("stations")
    stations = st if st and Path(st).is_file() else None
    return {
        "machine": res.machine,
        "error_model": res.error_model,
        "data": data,
        "stations": stations,
        "budget": opts.get("budget", "paper002"),
        "strategy": res.meta.get("strategy", "joint"),
        "theta": res.theta,
        "robust": bool(opts.get("robust", False)),
        "meta": res.meta,
    }
