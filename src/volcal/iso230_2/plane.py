"""Paper 003's two-axis model (eq. 13): the positional deviation over a plane.

Δ(P, R) = a + b_1 P + c_1 P² + d_1 P³ + b_2 R + c_2 R² + d_2 R³   (no interaction terms)

fitted by generalised least squares to the mean deviations at the measured points
(P_i, R_i), with the covariance of eqs. 7-10: diag(u²(x̄_i)) + u²(δ) 1 1ᵀ, u(δ) = MPE/sqrt(3),
u(x̄_i) the type A uncertainty of each mean (see :func:`.model.type_a_uncertainty`).
Here the coefficients are named ``a0`` (constant), ``p1..p<dP>`` (powers of P) and
``r1..r<dR>`` (powers of R).

Plane table (CSV or DataFrame), one row per reading: ``p_mm``, ``r_mm`` (coordinates of the
point on the two axes, mm), ``cycle`` (1..n), ``deviation_um`` (the measured positional
deviation, actual - target, um).  Every point needs one reading in each cycle 1..n.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from volcal.base.exceptions import InputError
from volcal.base.folders import check_out_dir, write_folder

from .evaluate import check_degree, check_option, check_type_a
from .model import gls, to_raw_matrix, type_a_uncertainty

__all__ = [
    "PlaneModel",
    "fit_plane",
    "PlaneReadings",
    "load_plane",
    "PlaneResult",
    "evaluate_plane",
    "write_plane_report",
    "PLANE_FILES",
]

PLANE_FILES = (
    "plane_parameters.csv",
    "plane_polynomial.csv",
    "plane_grid.csv",
    "plane_means.csv",
    "report.md",
    "plane.png",
)


@dataclass(frozen=True)
class PlaneModel:
    """Fitted eq. (13); positions and values in the units of the fitted data."""

    degree_p: int
    degree_r: int
    center: tuple[float, float]
    half_range: tuple[float, float]
    bounds: tuple[float, float, float, float]  # p_min, p_max, r_min, r_max
    points: np.ndarray  # (m, 2)
    means: np.ndarray  # (m,)
    u_means: np.ndarray  # (m,)
    u_instrument: float
    beta: np.ndarray  # normalised basis
    cov: np.ndarray
    chi2: float
    dof: int

    @property
    def names(self) -> list[str]:
        return (
            ["a0"]
            + [f"p{k}" for k in range(1, self.degree_p + 1)]
            + [f"r{k}" for k in range(1, self.degree_r + 1)]
        )

    def basis(self, p, r) -> np.ndarray:
        p = np.atleast_1d(np.asarray(p, dtype=float))
        r = np.atleast_1d(np.asarray(r, dtype=float))
        tp = (p - self.center[0]) / self.half_range[0]
        tr = (r - self.center[1]) / self.half_range[1]
        cols = (
            [np.ones_like(tp)]
            + [tp**k for k in range(1, self.degree_p + 1)]
            + [tr**k for k in range(1, self.degree_r + 1)]
        )
        return np.column_stack(cols)

    def value(self, p, r) -> np.ndarray:
        return self.basis(p, r) @ self.beta

    def std(self, p, r) -> np.ndarray:
        G = self.basis(p, r)
        return np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", G, self.cov, G), 0.0))

    def expanded(self, p, r, k: float = 2.0) -> np.ndarray:
        return k * self.std(p, r)

    def raw(self) -> tuple[np.ndarray, np.ndarray]:
        """Coefficients of powers of P and R (order of :attr:`names`) and their covariance."""
        dp, dr = self.degree_p, self.degree_r
        Tp = to_raw_matrix(dp, self.center[0], self.half_range[0])
        Tr = to_raw_matrix(dr, self.center[1], self.half_range[1])
        q = 1 + dp + dr
        W = np.zeros((q, q))
        W[0, 0] = 1.0
        W[0, 1 : 1 + dp] = Tp[0, 1:]
        W[0, 1 + dp :] = Tr[0, 1:]
        W[1 : 1 + dp, 1 : 1 + dp] = Tp[1:, 1:]
        W[1 + dp :, 1 + dp :] = Tr[1:, 1:]
        return W @ self.beta, W @ self.cov @ W.T


def fit_plane(
    p, r, means, u_means, *, degree_p: int = 3, degree_r: int = 3, u_instrument: float = 0.0
) -> PlaneModel:
    """GLS fit of eq. (13) to the mean deviations ``means`` at points (p, r)."""
    p = np.asarray(p, dtype=float)
    r = np.asarray(r, dtype=float)
    means = np.asarray(means, dtype=float)
    u_means = np.asarray(u_means, dtype=float)
    m = means.size
    if not (p.shape == r.shape == means.shape == u_means.shape == (m,)):
        raise ValueError("p, r, means and u_means must be 1-D of the same length")
    for name, d in (("degree_p", degree_p), ("degree_r", degree_r)):
        if int(d) != d or d < 0:
            raise ValueError(f"{name} must be an integer >= 0, got {d}")
    if np.any(~np.isfinite(u_means)) or np.any(u_means <= 0):
        raise ValueError(
            "every mean needs a positive standard uncertainty (s_i = 0 at a "
            "point? give the reading resolution as a floor)"
        )
    if np.unique(p).size < degree_p + 1 or np.unique(r).size < degree_r + 1:
        raise ValueError(
            f"degrees ({degree_p}, {degree_r}) need at least {degree_p + 1} "
            f"distinct P and {degree_r + 1} distinct R values; got "
            f"{np.unique(p).size} and {np.unique(r).size}"
        )
    bounds = (float(p.min()), float(p.max()), float(r.min()), float(r.max()))
    center = (0.5 * (bounds[0] + bounds[1]), 0.5 * (bounds[2] + bounds[3]))
    half = (0.5 * (bounds[1] - bounds[0]) or 1.0, 0.5 * (bounds[3] - bounds[2]) or 1.0)
    proto = PlaneModel(
        int(degree_p),
        int(degree_r),
        center,
        half,
        bounds,
        np.empty((0, 2)),
        means,
        u_means,
        float(u_instrument),
        np.empty(0),
        np.empty((0, 0)),
        0.0,
        0,
    )
    X = proto.basis(p, r)
    V = np.diag(u_means**2) + u_instrument**2 * np.ones((m, m))
    beta, cov, chi2 = gls(X, means, V)
    return PlaneModel(
        int(degree_p),
        int(degree_r),
        center,
        half,
        bounds,
        np.column_stack([p, r]),
        means.copy(),
        u_means.copy(),
        float(u_instrument),
        beta,
        cov,
        chi2,
        m - X.shape[1],
    )


@dataclass(frozen=True)
class PlaneReadings:
    points: np.ndarray  # (m, 2) mm, in order of first appearance
    readings: np.ndarray  # (m, n) deviations, mm; column j = cycle j + 1
    source: str


def load_plane(data, *, source: str | None = None) -> PlaneReadings:
    """Validate a plane table (CSV path or DataFrame); errors name file, row and column."""
    if isinstance(data, pd.DataFrame):
        src = source or "<DataFrame>"
        df = data.copy().reset_index(drop=True)
        df.columns = [str(c) for c in df.columns]
    else:
        path = Path(data)
        src = source or str(path)
        if not path.exists():
            raise FileNotFoundError(f"{src}: no such file")
        try:
            df = pd.read_csv(path, dtype=str, keep_default_na=False, encoding="utf-8-sig")
        except pd.errors.EmptyDataError:
            raise InputError(
                "the file is empty; expected a header row and readings", source=src, row=1
            ) from None
        except (pd.errors.ParserError, UnicodeDecodeError) as exc:
            raise InputError(f"malformed CSV: {exc}", source=src) from None
    original = {c.strip().lower(): c for c in df.columns}
    df = df.rename(columns={c: c.strip().lower() for c in df.columns})
    if "actual_mm" in df.columns and "deviation_um" in df.columns:
        raise InputError(
            "mixed units: give deviation_um only", source=src, row=1, column=original["actual_mm"]
        )
    for need, what in (
        ("p_mm", "coordinate P of the point [mm]"),
        ("r_mm", "coordinate R of the point [mm]"),
        ("cycle", "cycle number 1..n"),
        ("deviation_um", "measured positional deviation [um]"),
    ):
        if need not in df.columns:
            raise InputError(
                f"missing column '{need}' ({what}); columns found: "
                f"{', '.join(map(repr, df.columns))}",
                source=src,
                row=1,
                column=need,
            )
    if len(df) == 0:
        raise InputError("no readings: the table has a header but no data rows", source=src, row=2)
    vals = {}
    for col in ("p_mm", "r_mm", "cycle", "deviation_um"):
        out = np.empty(len(df))
        for k, raw in enumerate(df[col].tolist()):
            text = str(raw).strip()
            try:
                x = float(text)
            except ValueError:
                x = math.nan
            if not math.isfinite(x):
                raise InputError(
                    f"'{text}' is not a finite number", source=src, row=k + 2, column=original[col]
                )
            if col == "cycle" and (x != int(x) or x < 1):
                raise InputError(
                    f"'{text}' is not a cycle number; expected an integer 1..n",
                    source=src,
                    row=k + 2,
                    column=original[col],
                )
            out[k] = x
        vals[col] = out
    cyc = vals["cycle"].astype(int)
    n = int(cyc.max())
    missing = sorted(set(range(1, n + 1)) - set(cyc.tolist()))
    if missing:
        raise InputError(
            f"missing cycle(s) {', '.join(map(str, missing))}; cycles must be "
            "numbered 1..n without gaps",
            source=src,
            column=original["cycle"],
        )
    keys = list(zip(np.round(vals["p_mm"], 6), np.round(vals["r_mm"], 6)))
    order = list(dict.fromkeys(keys))
    index = {key: i for i, key in enumerate(order)}
    readings = np.full((len(order), n), np.nan)
    for k, (key, c) in enumerate(zip(keys, cyc)):
        i = index[key]
        if not np.isnan(readings[i, c - 1]):
            raise InputError(
                f"second reading at point p = {key[0]:g} mm, r = {key[1]:g} mm in cycle {c}",
                source=src,
                row=k + 2,
                column=original["cycle"],
            )
        readings[i, c - 1] = vals["deviation_um"][k] * 1e-3
    holes = np.argwhere(np.isnan(readings))
    if holes.size:
        i, j = holes[0]
        raise InputError(
            f"unequal cycle counts: point p = {order[i][0]:g} mm, r = "
            f"{order[i][1]:g} mm has no reading in cycle {j + 1}; every point "
            f"needs one reading in each cycle 1..{n}",
            source=src,
            column=original["cycle"],
        )
    if n < 2:
        raise InputError(
            "only 1 cycle; at least 2 are needed for the type A uncertainty",
            source=src,
            column=original["cycle"],
        )
    return PlaneReadings(points=np.array(order, dtype=float), readings=readings, source=src)


@dataclass(frozen=True)
class PlaneResult:
    source: str
    readings: PlaneReadings
    model: PlaneModel
    settings: dict = field(default_factory=dict)
    warnings: tuple[str, ...] = ()

    def parameters_table(self) -> pd.DataFrame:
        mdl, k = self.model, self.settings.get("k", 2.0)
        pts = self.readings.points
        g = _grid(mdl, None)
        rows = [
            ("points", pts.shape[0], "-", "number of measured points m"),
            ("cycles", self.readings.readings.shape[1], "-", "number of cycles n"),
            ("degree_p", mdl.degree_p, "-", "polynomial degree in P"),
            ("degree_r", mdl.degree_r, "-", "polynomial degree in R"),
            (
                "u_instrument_um",
                mdl.u_instrument * 1e3,
                "um",
                "standard uncertainty of the constant instrument error, MPE / sqrt(3)",
            ),
            ("k", k, "-", "coverage factor"),
            ("chi2", mdl.chi2, "-", f"chi-square of the fit, {mdl.dof} degrees of freedom"),
            (
                "U_max_um",
                float(mdl.expanded(g[:, 0], g[:, 1], k).max() * 1e3),
                "um",
                "largest expanded uncertainty of the fitted deviation over the measured box",
            ),
        ]
        return pd.DataFrame(rows, columns=["name", "value", "unit", "description"])

    def polynomial_table(self) -> pd.DataFrame:
        mdl = self.model
        a, C = mdl.raw()
        powers = (
            [(0, 0)]
            + [(k, 0) for k in range(1, mdl.degree_p + 1)]
            + [(0, k) for k in range(1, mdl.degree_r + 1)]
        )
        scale = np.array([1e3 for _ in powers])  # mm -> um on the value
        a, C = a * scale, C * np.outer(scale, scale)
        rows = []
        for q, (name, (kp, kr)) in enumerate(zip(mdl.names, powers)):
            kk = kp + kr
            unit = "um" if kk == 0 else ("um/mm" if kk == 1 else f"um/mm^{kk}")
            row = dict(
                coefficient=name,
                power_p=kp,
                power_r=kr,
                value=a[q],
                u=math.sqrt(max(C[q, q], 0.0)),
                unit=unit,
            )
            for l, nm in enumerate(mdl.names):
                row[f"cov_{nm}"] = C[q, l]
            row["cov_unit"] = f"um^2/mm^({kk}+power of the column's coefficient)"
            rows.append(row)
        return pd.DataFrame(rows)

    def means_table(self) -> pd.DataFrame:
        mdl, rd = self.model, self.readings
        k = self.settings.get("k", 2.0)
        p, r = rd.points[:, 0], rd.points[:, 1]
        fit = mdl.value(p, r)
        return pd.DataFrame(
            {
                "p_mm": p,
                "r_mm": r,
                "mean_um": mdl.means * 1e3,
                "s_um": rd.readings.std(axis=1, ddof=1) * 1e3,
                "u_mean_um": mdl.u_means * 1e3,
                "fit_um": fit * 1e3,
                "residual_um": (mdl.means - fit) * 1e3,
                "U_fit_um": mdl.expanded(p, r, k) * 1e3,
            }
        )

    def grid_table(self, spacing_mm: float | None = None) -> pd.DataFrame:
        mdl, k = self.model, self.settings.get("k", 2.0)
        g = _grid(mdl, spacing_mm)
        dev = mdl.value(g[:, 0], g[:, 1]) * 1e3
        return pd.DataFrame(
            {
                "p_mm": g[:, 0],
                "r_mm": g[:, 1],
                "deviation_um": dev,
                "correction_um": -dev + 0.0,
                "U_um": mdl.expanded(g[:, 0], g[:, 1], k) * 1e3,
            }
        )


def _grid(mdl: PlaneModel, spacing):
    from .tables import correction_positions, nice_spacing

    p0, p1, r0, r1 = mdl.bounds
    if spacing is None:
        spacing = nice_spacing(max(p1 - p0, r1 - r0), 20)
    gp = correction_positions(p0, p1, spacing)
    gr = correction_positions(r0, r1, spacing)
    PP, RR = np.meshgrid(gp, gr, indexing="ij")
    return np.column_stack([PP.ravel(), RR.ravel()])


def evaluate_plane(
    data,
    *,
    degree_p: int = 3,
    degree_r: int = 3,
    mpe_um: float = 0.0,
    k: float = 2.0,
    resolution_um: float = 0.0,
    type_a: str = "gum-s1",
    source: str | None = None,
) -> PlaneResult:
    """Load a plane table and fit eq. (13); the instrument MPE [um] enters as MPE/sqrt(3).

    ``type_a`` as in :func:`volcal.iso230_2.evaluate` ("gum-s1" or "paper")."""
    check_type_a(type_a)
    check_option("--mpe-um", mpe_um)
    check_option("--resolution-um", resolution_um)
    check_option("--k", k, strict=True)
    check_degree("--degree", degree_p)
    check_degree("--degree-r", degree_r)
    rd = load_plane(data, source=source)
    n = rd.readings.shape[1]
    if type_a == "gum-s1" and n < 4:
        raise InputError(
            f"{n} cycles; the GUM-S1 type A uncertainty needs at least 4 (use "
            "--type-a paper for fewer)",
            source=rd.source,
        )
    u = type_a_uncertainty(rd.readings, resolution_um * 1e-3 / math.sqrt(12.0), type_a)
    try:
        model = fit_plane(
            rd.points[:, 0],
            rd.points[:, 1],
            rd.readings.mean(axis=1),
            u,
            degree_p=degree_p,
            degree_r=degree_r,
            u_instrument=mpe_um * 1e-3 / math.sqrt(3.0),
        )
    except ValueError as exc:
        raise InputError(str(exc), source=rd.source) from None
    warnings = []
    if n < 5:
        warnings.append(f"{n} cycles; ISO 230-2 asks for 5")
    if model.dof > 0:
        from scipy.stats import chi2 as chi2_dist

        pval = float(chi2_dist.sf(model.chi2, model.dof))
        if pval < 0.01:
            warnings.append(
                f"eq. (13) does not explain the means within their uncertainty "
                f"(chi2 = {model.chi2:.3g}, {model.dof} dof, p = {pval:.2g}); "
                "interaction terms or other degrees may be needed"
            )
    return PlaneResult(
        source=rd.source,
        readings=rd,
        model=model,
        settings=dict(
            degree_p=int(degree_p),
            degree_r=int(degree_r),
            mpe_um=float(mpe_um),
            k=float(k),
            resolution_um=float(resolution_um),
            type_a=type_a,
        ),
        warnings=tuple(warnings),
    )


def _plane_plot(result: PlaneResult, path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    mdl, k = result.model, result.settings.get("k", 2.0)
    p0, p1, r0, r1 = mdl.bounds
    gp, gr = np.linspace(p0, p1, 80), np.linspace(r0, r1, 80)
    PP, RR = np.meshgrid(gp, gr, indexing="xy")
    dev = mdl.value(PP.ravel(), RR.ravel()).reshape(PP.shape) * 1e3
    U = mdl.expanded(PP.ravel(), RR.ravel(), k).reshape(PP.shape) * 1e3
    fig = Figure(figsize=(10, 4.2), layout="constrained")
    FigureCanvasAgg(fig)
    a1, a2 = fig.subplots(1, 2)
    for axp, Z, title in (
        (a1, dev, "fitted deviation Δ(P, R) [um]"),
        (a2, U, f"expanded uncertainty U, k = {k:g} [um]"),
    ):
        cs = axp.contourf(PP, RR, Z, levels=15, cmap="viridis")
        fig.colorbar(cs, ax=axp)
        axp.plot(mdl.points[:, 0], mdl.points[:, 1], "k.", ms=3)
        axp.set_xlabel("P [mm]")
        axp.set_ylabel("R [mm]")
        axp.set_title(title)
    fig.savefig(path, dpi=130)


def write_plane_report(result: PlaneResult, out_dir, *, spacing_mm: float | None = None) -> Path:
    """Write ``PLANE_FILES`` into ``out_dir`` all-or-nothing (temporary folder + rename)."""
    if spacing_mm is not None and not (math.isfinite(spacing_mm) and spacing_mm > 0):
        raise InputError(
            f"{spacing_mm!r} is not allowed; expected a number > 0", source="option --spacing-mm"
        )
    check_out_dir(Path(out_dir).absolute(), PLANE_FILES, "volcal iso230-2 --plane")
    grid = result.grid_table(spacing_mm)

    def writer(tmp: Path) -> None:
        params = result.parameters_table()
        poly = result.polynomial_table()
        params.to_csv(tmp / "plane_parameters.csv", index=False)
        poly.to_csv(tmp / "plane_polynomial.csv", index=False)
        grid.to_csv(tmp / "plane_grid.csv", index=False)
        result.means_table().to_csv(tmp / "plane_means.csv", index=False)
        _plane_plot(result, tmp / "plane.png")
        from .report import _md_table

        md = [
            "# Positional deviation over a plane (paper 003, eq. 13)",
            "",
            f"Source: `{result.source}`.",
            "",
            "Δ(P, R) = a0 + Σ p_k P^k + Σ r_k R^k (no interaction terms), fitted by "
            "generalised least squares to the mean deviation at each point with covariance "
            "diag(u²(x̄_i)) + u²(instrument) 1 1ᵀ, u(instrument) = MPE / sqrt(3), type A "
            f"method {result.settings.get('type_a')}. Deviation = "
            "actual - target (an error); correction = -deviation.",
            "",
            "![plane plot](plane.png)",
            "",
            "## Parameters",
            "",
            _md_table(params.drop(columns=["description"])),
            "",
            "## Coefficients",
            "",
            _md_table(poly[["coefficient", "value", "u", "unit"]], fmt=lambda v: f"{v:.6g}"),
            "",
        ]
        if result.warnings:
            md += ["## Warnings", ""] + [f"- {w}" for w in result.warnings] + [""]
        (tmp / "report.md").write_text("\n".join(md), encoding="utf-8")

    return write_folder(out_dir, PLANE_FILES, "volcal iso230-2 --plane", writer)
