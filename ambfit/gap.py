"""Sim-to-real gap diagnosis, first layer: where the ideal model and the data disagree.

Work in progress for the diagnosis issue: this module has the noise floor and the
*where* analysis.  The candidate-effect fits, held-out ranking, verdict and
``ambfit diagnose`` are still to come.

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

from ambfit.data import Dataset, approach_direction
from ambfit.fit import FitResult, fit
from ambfit.model import AXES, MU_0

DEFAULT_TURNS = 480.0
"""Turns per pole used for flux densities when no rig description is given (the paper rig preset)."""


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


def noise_floor(result: FitResult) -> NoiseFloor:
    z = result.residuals
    return NoiseFloor(source=result.noise_source, mean_z2=float(np.mean(z**2)),
                      expected_mean_z2=result.dof / len(z), n_rows=len(z), n_params=len(z) - result.dof)


def operating_variables(data: Dataset | pd.DataFrame, result: FitResult, turns: float = DEFAULT_TURNS) -> pd.DataFrame:
    """Per-row operating variables (SI units) for the residual analysis."""
    df = (data.frame if isinstance(data, Dataset) else data).reset_index(drop=True)
    ax = (df["axis"] == "w").to_numpy().astype(int)
    v, w = df["v_um"].to_numpy(float) * 1e-6, df["w_um"].to_numpy(float) * 1e-6
    x = np.where(ax == 0, v, w)
    y = np.where(ax == 0, w, v)
    vals = dict(zip(result.names, result.values))
    g = np.array([vals.get("g_v0", np.nan), vals.get("g_w0", np.nan)])[ax]
    x0 = np.array([vals.get("v0", 0.0), vals.get("w0", 0.0)])[ax]
    c = np.cos(np.deg2rad(22.5))
    gt, gb = g - (x0 + x) * c, g + (x0 + x) * c
    it, ib = df["i_top_A"].to_numpy(float), df["i_bottom_A"].to_numpy(float)
    out = pd.DataFrame({
        "axis": df["axis"].to_numpy(), "position_own_um": x * 1e6, "position_other_um": y * 1e6,
        "bias_A": df["bias_A"].to_numpy(float), "control_current_A": 0.5 * (it - ib),
        "b_top_T": MU_0 * turns * it / (2 * gt), "b_bottom_T": MU_0 * turns * ib / (2 * gb),
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


def where(data: Dataset | pd.DataFrame, result: FitResult | None = None, *, bins: int = 6, alpha: float = 0.01,
          turns: float = DEFAULT_TURNS) -> Where:
    """Where the baseline fit's standardized residuals are structured (see the module docstring)."""
    from scipy.stats import chi2, norm

    df = (data.frame if isinstance(data, Dataset) else data).reset_index(drop=True)
    result = result or fit(df)
    z = np.asarray(result.residuals)
    ov = operating_variables(df, result, turns)
    tests, cells = [], []
    for var in [c for c in ov.columns if c != "axis"]:
        for ax in AXES:
            m = (ov["axis"] == ax).to_numpy()
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
            tests.append({"variable": var, "axis": ax, "chi2": stat, "dof": dof, "p_value": float(chi2.sf(stat, dof))})
    threshold = float(norm.isf(alpha / (2 * max(len(cells), 1))))
    regions = sorted([c for c in cells if abs(c.z) > threshold], key=lambda r: -abs(r.z))
    return Where(tests=pd.DataFrame(tests).sort_values("p_value").reset_index(drop=True), regions=regions,
                 threshold=threshold)


# --- which effect, and how far the gap shrinks -----------------------------------------------------

def folds(data: pd.DataFrame) -> tuple[str, list]:
    """Block cross-validation folds over operating regions: leave one load out when there are three or more
    load groups, else leave one bias out, else alternate iterations.  Returns (name, [bool test masks])."""
    df = data.reset_index(drop=True)
    if "load_id" in df and df["load_id"].nunique() >= 3:
        return "leave-one-load-out", [(df["load_id"] == v).to_numpy() for v in df["load_id"].unique()]
    b = np.round(df["bias_A"].to_numpy(float), 6)
    if len(np.unique(b)) >= 3:
        return "leave-one-bias-out", [b == v for v in np.unique(b)]
    it = pd.to_numeric(df["iteration"], errors="coerce").fillna(0).to_numpy() if "iteration" in df else np.arange(len(df))
    return "alternate iterations", [(it % 2) == 0, (it % 2) == 1]


def _excess(z) -> float:
    return float(np.sqrt(max(np.mean(np.asarray(z) ** 2) - 1.0, 0.0)))


@dataclasses.dataclass(frozen=True)
class Diagnosis:
    """The contract section 3 record and what it was computed from."""

    record: dict

    def to_json(self) -> dict:
        return self.record


def diagnose(data: Dataset | pd.DataFrame, *, candidates=None, turns: float = DEFAULT_TURNS,
             floor_tolerance: float = 1.0, min_shrink: float = 0.5, nominal: NominalRig | None = None,
             pairs: bool = True, pair_verdict: bool = False, **noise) -> Diagnosis:
    """Where the ideal model fails, which candidate effect explains it on held-out data, how far the gap shrinks.

    For the baseline and for each candidate effect (default: every effect in
    :data:`ambfit.effects.EFFECTS`), the extended model is fitted with each fold held
    out and scored on it: ``excess = sqrt(max(mean(z^2) - 1, 0))`` of the pooled
    held-out standardized residuals.  Verdict: ``none`` when the baseline's held-out
    residuals sit on the noise floor (excess below ``floor_tolerance`` and no
    structured region); otherwise the best candidate if it removes at least
    ``min_shrink`` of the excess *and* leaves the held-out residuals within
    ``floor_tolerance`` of the floor; when no single effect does, the pairs of the three
    best (``pairs=True``) are tried the same way and a pair can be the verdict
    (``"a+b"``); otherwise ``unexplained``.  ``confounded_with``
    lists the candidates whose held-out score is statistically indistinguishable
    from the verdict's.
    """
    from ambfit.effects import EFFECTS
    from ambfit.extend import fit_extended, heldout_residuals

    df = (data.frame if isinstance(data, Dataset) else data).reset_index(drop=True)
    base = fit(df, **noise)
    nf = noise_floor(base)
    loc = where(df, base, turns=turns)
    fold_name, tests = folds(df)
    cands = list(candidates) if candidates is not None else [cls() for cls in EFFECTS.values()]

    def heldout(effects):
        zs, params = [], None
        for test in tests:
            ef = fit_extended(df, effects, start=base, mask=(~test).astype(float), turns=turns, **noise)
            zs.append(heldout_residuals(ef, df, test))
        full = fit_extended(df, effects, start=base, turns=turns, **noise)
        params = {n: (float(v), float(e)) for n, v, e in zip(full.names, full.values, full.std)}
        return np.concatenate(zs), params, full

    z0, p0, full0 = heldout(())
    before = _excess(z0)
    aic0 = float(np.sum(full0.residuals**2) + 2 * len(full0.names))
    n_out = len(z0)
    def entry(effects):
        z1, params, full = heldout(tuple(effects))
        after = _excess(z1)
        shrink = 1.0 - after / before if before > 0 else 0.0
        head = {k: v for k, v in params.items() if not k.startswith("load[")}
        z_in = full.residuals
        return {"effect": "+".join(type(e).name for e in effects),
                "heldout_rms_before": float(np.sqrt(np.mean(z0**2))),
                "heldout_rms_after": float(np.sqrt(np.mean(z1**2))), "heldout_excess_before": before,
                "heldout_excess_after": after, "shrink": shrink, "score": float(np.mean(z1**2)),
                "insample_mean_z2": float(np.mean(z_in**2)),
                # Akaike's criterion on the in-sample fit (chi2 + 2 p), relative to the ideal model
                "delta_aic": float(np.sum(z_in**2) + 2 * len(full.names) - aic0),
                "params": {k: v[0] for k, v in head.items() if "." in k},
                "params_std": {k: v[1] for k, v in head.items() if "." in k},
                "shift": {k: head[k][0] - p0[k][0] for k in ("g_v0", "v0", "g_w0", "w0", "k_v", "k_w")
                          if k in head and k in p0},
                # standard error of the extended estimate (the shift's reference, the ideal fit on the
                # same data, is strongly correlated with it; sqrt(var_ext - var_base) was negative here)
                "shift_std": {k: head[k][1] for k in ("g_v0", "v0", "g_w0", "w0", "k_v", "k_w")
                              if k in head and k in p0}}

    ranking = [entry([e]) for e in cands]
    ranking.sort(key=lambda r: r["score"])
    on_floor = before < floor_tolerance and not loc.regions

    def explains(r):
        return r["shrink"] >= min_shrink and r["heldout_excess_after"] < floor_tolerance

    if not on_floor and ranking and not explains(ranking[0]) and pairs:
        # no single effect removes the structure: forward selection, the best single plus each other candidate
        by_name = {type(e).name: e for e in cands}
        first = ranking[0]["effect"]
        ranking += [entry([by_name[first], e]) for e in cands if type(e).name != first]
    ranking.sort(key=lambda r: r["score"])
    pair_entries = [r for r in ranking if "+" in r["effect"]]
    best_pair = pair_entries[0] if pair_entries else None
    if not pair_verdict:
        singles = [r for r in ranking if "+" not in r["effect"]]
        best = singles[0] if singles else None
    else:
        best = ranking[0] if ranking else None
    if on_floor:
        verdict, ref = "none", float(np.mean(z0**2))
    elif best and explains(best):
        verdict, ref = best["effect"], best["score"]
    else:
        verdict, ref = "unexplained", None
    # sd of a mean of n squared standard normals is sqrt(2 / n); scaled by the level when above the floor
    se = np.sqrt(2.0 / n_out) * max(ref, 1.0) if ref is not None else np.inf
    confounded = [] if ref is None else [r["effect"] for r in ranking
                                         if r["effect"] != verdict and abs(r["score"] - ref) < 3 * se]
    record = {
        "baseline": "ideal", "noise_floor": nf.to_json(), "folds": fold_name,
        "where": [r.to_json() for r in loc.regions[:20]],
        "ranking": ranking, "verdict": verdict, "confounded_with": confounded,
        # for "unexplained" this is the best candidate's partial shrink; for "none" there is nothing to shrink
        "shrink": 0.0 if verdict == "none" or best is None else best["shrink"],
        "heldout_excess_before": before,
        "parameters_baseline": {k: v[0] for k, v in p0.items() if not k.startswith("load[")},
    }
    if best_pair is not None:
        record["best_pair"] = {"effect": best_pair["effect"], "heldout_excess_after": best_pair["heldout_excess_after"],
                               "shrink": best_pair["shrink"], "explains": bool(explains(best_pair))}
    if nominal is not None:
        record["parameter_gap"] = parameter_gap(base, nominal)
    return Diagnosis(record=record)


# --- parameter-level gap: identified effective parameters against the nominal rig -------------------

@dataclasses.dataclass(frozen=True)
class NominalRig:
    """A nominal rig description (from a small TOML file), SI units.

    TOML keys: ``nominal_gap_um``, ``turns``, ``pole_area_mm2``, ``lamination`` (default 1),
    ``alpha_deg`` (22.5), ``position_gain_tolerance`` (relative, e.g. 0.0025 for the paper's
    micrometer), ``current_gain_tolerance`` (relative), ``iron_path_mm`` (equivalent iron
    length, for the permeability an extra gap would imply; default 80).
    """

    gap: float
    turns: float | None = None
    pole_area: float | None = None
    lamination: float = 1.0
    alpha_deg: float = 22.5
    position_gain_tolerance: float = 0.0025
    current_gain_tolerance: float = 0.001
    iron_path: float = 0.08

    @classmethod
    def from_toml(cls, path) -> NominalRig:
        import tomllib

        with open(path, "rb") as f:
            d = tomllib.load(f)
        known = {"nominal_gap_um", "turns", "pole_area_mm2", "lamination", "alpha_deg", "position_gain_tolerance",
                 "current_gain_tolerance", "iron_path_mm"}
        bad = set(d) - known
        if bad:
            raise ValueError(f"{path}: unknown key(s) {sorted(bad)}; valid: {sorted(known)}")
        if "nominal_gap_um" not in d:
            raise ValueError(f"{path}: nominal_gap_um is required")
        return cls(gap=d["nominal_gap_um"] * 1e-6, turns=d.get("turns"),
                   pole_area=None if "pole_area_mm2" not in d else d["pole_area_mm2"] * 1e-6,
                   lamination=d.get("lamination", 1.0), alpha_deg=d.get("alpha_deg", 22.5),
                   position_gain_tolerance=d.get("position_gain_tolerance", 0.0025),
                   current_gain_tolerance=d.get("current_gain_tolerance", 0.001),
                   iron_path=d.get("iron_path_mm", 80.0) * 1e-3)

    @property
    def k(self) -> float | None:
        if self.turns is None or self.pole_area is None:
            return None
        from ambfit.model import force_constant

        return force_constant(self.pole_area, self.turns, np.deg2rad(self.alpha_deg), self.lamination)


def parameter_gap(result: FitResult, nominal: NominalRig, n_sigma: float = 3.0) -> list[dict]:
    """Identified effective parameters against the nominal rig, with the effects that could explain each
    difference (and the magnitude each would need) and the experiment that would separate them."""
    out = []
    for ax in AXES:
        name = f"g_{ax}0"
        if name not in result.names:
            continue
        g, sg = result.value(name), result.error(name)
        diff = g - nominal.gap
        entry = {"parameter": f"{name}_um", "identified": g * 1e6, "std": sg * 1e6, "nominal": nominal.gap * 1e6,
                 "difference": diff * 1e6, "z": diff / sg, "flagged": bool(abs(diff) > n_sigma * sg)}
        if entry["flagged"]:
            rel = diff / nominal.gap
            expl = []
            if diff > 0:
                mu = nominal.iron_path / (2 * diff)
                expl.append({"effect": "iron_reluctance", "needs": f"relative permeability {mu:.0f} over an "
                             f"equivalent iron length of {nominal.iron_path * 1e3:.0f} mm (b_th / mu_r = "
                             f"{2 * diff * 1e6:.1f} µm)", "plausible": bool(200 < mu < 20000)})
            expl.append({"effect": "position_gain", "needs": f"sensor gain error {rel * 100:+.2f} %",
                         "plausible": bool(abs(rel) <= 3 * nominal.position_gain_tolerance),
                         "note": f"calibration tolerance {nominal.position_gain_tolerance * 100:.2f} %"})
            expl.append({"effect": "fringing", "needs": "a gap-dependent pole area; shifts the effective gap by "
                         "a few per cent of the fringe width", "plausible": True})
            entry["could_be"] = expl
            entry["separate_by"] = [
                "a known-displacement calibration of the position sensor (moves only position_gain)",
                "a wider bias range up to saturation (iron reluctance grows with flux density; a sensor gain does not)",
                "repeating at a second air gap or rotor size (fringing scales with the gap; iron path does not)"]
        out.append(entry)
    k_nom = nominal.k
    if k_nom is not None:
        for ax in AXES:
            name = f"k_{ax}"
            if name not in result.names:
                continue
            k, sk = result.value(name), result.error(name)
            entry = {"parameter": f"{name}_Nm2_per_A2", "identified": k, "std": sk, "nominal": k_nom,
                     "ratio": k / k_nom, "z": (k - k_nom) / sk, "flagged": bool(abs(k - k_nom) > n_sigma * sk)}
            if entry["flagged"]:
                entry["could_be"] = ([{"effect": "leakage", "needs": f"{(1 - np.sqrt(k / k_nom)) * 100:.1f} % of "
                                       "the flux missing the gap"}] if k < k_nom else
                                     [{"effect": "fringing", "needs": f"effective pole area +{(k / k_nom - 1) * 100:.1f} %"}])
                entry["separate_by"] = ["a flux probe (Hall sensor) in one gap",
                                        "known loads at several gaps (fringing depends on the gap, leakage less)"]
            out.append(entry)
    return out
