"""Where the model and the data disagree: the noise floor and structured residuals.

Noise floor: the standardized residuals ``z`` of the baseline least-squares fit
are N(0, 1) when the model is right and the declared (or column) noise levels
are true; ``mean(z^2)`` should be ``(n - p) / n``.  The floor is stated with its
source (std columns, declared, or estimated, in which case structure cannot be
told from noise by level alone, only by pattern).

Where: ``z`` against every operating variable the data hold or the model
implies (own and other-axis position, bias, control current, flux density in
each gap, load, time, temperature, sweep direction).  Each variable is cut into
quantile bins per axis; a bin's mean ``z`` times ``sqrt(n)`` is its size in noise
units; a variable's structure test is ``sum n_b zbar_b^2`` against χ² with as many
degrees of freedom as bins.  Regions are reported when their size exceeds the
Bonferroni-corrected threshold over all bins tested.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd

from ambfit.data import Dataset
from ambfit.estimation.fit import fit
from ambfit.estimation.results import FitResult
from ambfit.physics.bearing import AXES, PAPER_BEARING, Bearing
from ambfit.physics.model import pole_gaps
from ambfit.rows import approach_direction


@dataclasses.dataclass(frozen=True)
class NoiseFloor:
    """What the residuals would be if the model were right."""

    source: str
    mean_z2: float
    expected_mean_z2: float
    n_rows: int
    n_params: int

    @property
    def excess(self) -> float:
        """``sqrt(max(mean(z^2) - 1, 0))``: model error beyond the floor, in noise units."""
        return float(np.sqrt(max(self.mean_z2 - 1.0, 0.0)))

    def to_json(self) -> dict:
        return {"source": self.source, "mean_z2": self.mean_z2, "expected_mean_z2": self.expected_mean_z2,
                "excess": self.excess, "n_rows": self.n_rows, "n_params": self.n_params}


def noise_floor(result: FitResult, estimate=None) -> NoiseFloor:
    """``result``'s residuals against their noise; ``estimate`` (:class:`ambfit.diagnosis.noise.NoiseEstimate`): the
    current noise ``result`` was given came from neighbouring readings, which the source then says in place of the
    declared level; :class:`ambfit.diagnosis.noise.Unestimated`: too few readings had neighbours for it."""
    from ambfit.diagnosis.noise import NoiseEstimate

    z = result.residuals
    source = result.noise_source
    if estimate is not None:
        current, *rest = noise_parts(source)
        kept = [] if isinstance(estimate, NoiseEstimate) else [current]     # the unit level's own source stays
        source = "; ".join(kept + [estimate.describe(), *rest])
    return NoiseFloor(source=source, mean_z2=float(np.mean(z**2)),
                      expected_mean_z2=result.dof / len(z), n_rows=len(z), n_params=len(z) - result.dof)


def noise_parts(source: str) -> list[str]:
    """A noise source's parts (current, position): split at the ``"; "`` outside parentheses."""
    parts, depth, start = [], 0, 0
    for j, ch in enumerate(source):
        depth += (ch == "(") - (ch == ")")
        if depth == 0 and source.startswith("; ", j):
            parts.append(source[start:j])
            start = j + 2
    return parts + [source[start:]]


def operating_variables(data: Dataset | pd.DataFrame, result: FitResult) -> pd.DataFrame:
    """Per-row operating variables (SI units) for the residual analysis."""
    df = (data.frame if isinstance(data, Dataset) else data).reset_index(drop=True)
    ax = (df["axis"] == "w").to_numpy().astype(int)
    v, w = df["v_um"].to_numpy(float) * 1e-6, df["w_um"].to_numpy(float) * 1e-6
    x = np.where(ax == 0, v, w)
    y = np.where(ax == 0, w, v)
    vals = dict(zip(result.names, result.values))
    g = np.array([vals.get("g_v0", np.nan), vals.get("g_w0", np.nan)])[ax]
    x0 = np.array([vals.get("v0", 0.0), vals.get("w0", 0.0)])[ax]
    bearing = result.bearing
    gt, gb = pole_gaps(g, x0, x, bearing.cos_alpha)
    it, ib = df["i_top_A"].to_numpy(float), df["i_bottom_A"].to_numpy(float)
    out = pd.DataFrame({
        "axis": df["axis"].to_numpy(), "position_own_um": x * 1e6, "position_other_um": y * 1e6,
        "bias_A": df["bias_A"].to_numpy(float), "control_current_A": 0.5 * (it - ib),
        "b_top_T": bearing.flux_density(it, gt), "b_bottom_T": bearing.flux_density(ib, gb),
    })
    if "load_N" in df and df["load_N"].notna().any():
        out["load_N"] = df["load_N"].to_numpy(float)
    for col in ("time_s", "temperature_C"):
        if col in df and df[col].notna().any() and np.ptp(df[col].dropna().to_numpy(float)) > 0:
            out[col] = df[col].to_numpy(float)
    bias_dir = approach_direction(df.assign(_b=df["bias_A"]), "_b", threshold=1e-9)
    if len(np.unique(bias_dir)) > 1:
        out["sweep_direction"] = bias_dir
    return out


@dataclasses.dataclass(frozen=True)
class Region:
    variable: str
    axis: str
    low: float
    high: float
    rows: int
    z: float           # bin mean of z times sqrt(rows): size in noise units
    mean_z: float

    def describe(self) -> str:
        if self.variable == "sweep_direction":
            return f"bias approached {'rising' if self.low > 0 else 'falling'}, axis {self.axis}"
        return f"{self.variable} in [{self.low:.4g}, {self.high:.4g}], axis {self.axis}"

    def to_json(self) -> dict:
        return {"region": self.describe(), "rows": self.rows, "z": self.z, "mean_z": self.mean_z,
                "variable": self.variable}


@dataclasses.dataclass(frozen=True)
class Where:
    """Structure tests per (variable, axis) and the regions beyond the threshold, largest first."""

    tests: pd.DataFrame
    regions: list
    threshold: float


def where(data: Dataset | pd.DataFrame, result: FitResult | None = None, *, bins: int = 6,
          alpha: float = 0.01, bearing: Bearing = PAPER_BEARING, rows=None) -> Where:
    """Where the baseline fit's standardized residuals are structured (see the module docstring); ``rows`` (bool
    per row, default every row): the readings searched."""
    # chi2.sf and norm.isf from scipy.special: scipy.stats alone takes 0.6 s to import
    from scipy.special import chdtrc, ndtri

    df = (data.frame if isinstance(data, Dataset) else data).reset_index(drop=True)
    result = result or fit(df, bearing=bearing, debias="none")
    z = np.asarray(result.residuals)
    ov = operating_variables(df, result)
    tests, cells = [], []
    for var in [c for c in ov.columns if c != "axis"]:
        for ax in AXES:
            m = (ov["axis"] == ax).to_numpy() & (True if rows is None else np.asarray(rows, bool))
            if m.sum() < 2 * bins:
                continue
            vals, zz = ov.loc[m, var].to_numpy(float), z[m]
            if var == "sweep_direction":
                edges = np.array([-1.5, 0.0, 1.5])
            else:
                qs = np.unique(np.quantile(vals, np.linspace(0, 1, bins + 1)))
                if len(qs) < 3:
                    continue
                edges = qs
            idx = np.clip(np.searchsorted(edges, vals, side="right") - 1, 0, len(edges) - 2)
            stat, dof = 0.0, 0
            for b in range(len(edges) - 1):
                sel = idx == b
                n = int(sel.sum())
                if n == 0:
                    continue
                zbar = float(zz[sel].mean())
                stat += n * zbar**2
                dof += 1
                cells.append(Region(var, ax, float(vals[sel].min()), float(vals[sel].max()), n, zbar * np.sqrt(n),
                                    zbar))
            tests.append({"variable": var, "axis": ax, "chi2": stat, "dof": dof, "p_value": float(chdtrc(dof, stat))})
    threshold = float(-ndtri(alpha / (2 * max(len(cells), 1))))
    regions = sorted([c for c in cells if abs(c.z) > threshold], key=lambda r: -abs(r.z))
    table = pd.DataFrame(tests, columns=["variable", "axis", "chi2", "dof", "p_value"])   # none on tiny designs
    return Where(tests=table.sort_values("p_value").reset_index(drop=True), regions=regions,
                 threshold=threshold)
