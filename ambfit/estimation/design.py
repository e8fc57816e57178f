"""Experiment design: which perturbations to run next to shrink the gap's uncertainty fastest.

Given the readings so far, the least-squares optimum and its Fisher information
(:mod:`ambfit.estimation.information`), each candidate step (set-points ``(v, w)`` and a bias,
one reading per axis, under the data's load) adds the information of its two
predicted readings, computed at the estimate with the data's noise levels.  A
greedy search picks steps one at a time, each maximising the reduction of the
target: the variance of one parameter (A-optimal for the gap, the default) or the
log-determinant of the information of gap and origin (D-optimal).

The predicted readings come from the ideal model at the estimate
(:func:`ambfit.estimation.debias.model_currents`); the recommendation is only as good as the
model, and says so (it is local to the current estimate).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np
import pandas as pd

from ambfit.data import Dataset, load_groups
from ambfit.estimation.core import (
    K_REFERENCE,
    Model,
    build_problem,
    free_mask,
    free_names,
    jacobian,
    param_scale,
    to_theta,
)
from ambfit.estimation.fit import FitResult, fit
from ambfit.estimation.units import FORCE_CONSTANTS, GAPS, ORIGINS
from ambfit.physics.bearing import AXES, PAPER_BEARING, Bearing


@dataclasses.dataclass(frozen=True)
class Recommendation:
    """Steps to run next, in order, with the predicted standard error of the target after each.

    ``candidates``: the steps chosen from (within the bearing's limits); ``centre_um``: the estimated bearing
    centre in sensor coordinates [µm]; ``radius_um``: how far from it a set-point may lie [µm];
    ``margin_reason``: why the steps were also kept among the positions already run (None when they were not:
    :func:`model_margin_reason`) and ``remedy``, what would show the effect; ``limits``: where the steps were
    kept, in words.
    """

    steps: pd.DataFrame
    target: str
    std_now: float
    criterion: str
    candidates: pd.DataFrame | None = None
    centre_um: tuple[float, float] | None = None
    radius_um: float | None = None
    margin_reason: str | None = None
    remedy: str | None = None
    limits: str = ""

    def _unit(self) -> tuple[float, str]:
        return (1e6, "µm") if self.target[0] in "gvw" else (1.0, "N·m²/A²")

    @property
    def title(self) -> str:
        f, unit = self._unit()
        return f"next steps ({self.criterion}-optimal for {self.target}); now ± {self.std_now * f:.3g} {unit}"

    def display_rows(self) -> list[dict]:
        """One ``{column: text}`` row per recommended step."""
        f, unit = self._unit()
        return [{"#": str(i), "v set [µm]": f"{r.v_set_um:.1f}", "w set [µm]": f"{r.w_set_um:.1f}",
                 "bias [A]": f"{r.bias_A:.2f}", f"{self.target} std after [{unit}]": f"{r.predicted_std_after * f:.3g}"}
                for i, r in enumerate(self.steps.itertuples(), 1)]

    def to_json(self) -> dict:
        out = {"target": self.target, "criterion": self.criterion, "std_now": self.std_now,
               "steps": self.steps.to_dict(orient="records")}
        if self.centre_um is not None:      # where the limits were measured from, and how far a set-point may go
            out |= {"bearing_centre_um": list(self.centre_um), "max_distance_um": self.radius_um,
                    "kept_among_positions_run": self.margin_reason}
        return out

    def to_dataframe(self) -> pd.DataFrame:
        return self.steps.copy()

    def summary(self) -> str:
        return "\n".join([self.title] + ["  " + ", ".join(f"{k} {v}" for k, v in r.items())
                                          for r in self.display_rows()])

    __str__ = summary


OFFSET_FRACTIONS = tuple(k / 6 for k in range(-5, 6))
"""Candidate set-point offsets on each axis as fractions of the back-up clearance: on the paper's rig (60 µm)
the ±50 µm grid in 10 µm steps."""

BIAS_FRACTIONS = tuple(k / 15 for k in range(4, 10))
"""Candidate biases as fractions of the coil current limit: 0.8-1.8 A in 0.2 A steps on the paper's 3 A rig,
leaving the control current 40 % of the limit."""

ORIGIN_MARGIN_SIGMAS = 3.0
"""Candidates keep this many standard errors of the estimated origin (in its worst direction) inside the
back-up clearance: the clearance is measured from the bearing centre, which the design knows only through the
estimated origin, the rig through the true one."""

VISITED_TOLERANCE = 0.5e-6
"""How far [m] a set-point may lie outside the region the rotor has already visited (the readings' positions) and
still count as inside it: the positions' noise, not a step."""


def inside_visited(points: np.ndarray, visited: np.ndarray, tol: float = VISITED_TOLERANCE) -> np.ndarray:
    """Whether each of ``points [n, 2]`` lies in the convex hull of ``visited [m, 2]`` (within ``tol``, all [m]).
    The back-up clearance is a disc and every visited position lies in it, so their hull does too: a set-point in
    it is safe whatever the origin.  A hull of collinear positions (Table 2's diagonal pairs) is their segment."""
    from scipy.spatial import Delaunay

    pts = np.asarray(points, float).reshape(-1, 2)
    vis = np.unique(np.round(np.asarray(visited, float).reshape(-1, 2), 9), axis=0)
    centre = vis.mean(axis=0)
    _, sv, vt = np.linalg.svd(vis - centre, full_matrices=False)
    if len(vis) >= 3 and sv[-1] > tol * np.sqrt(len(vis)):
        # (points within tol of the hull: shrink them towards the centre by tol first)
        d = pts - centre
        r = np.hypot(*d.T)
        pulled = centre + d * np.clip(1 - tol / np.maximum(r, 1e-30), 0, None)[:, None]
        return Delaunay(vis).find_simplex(pulled) >= 0
    along, across = (pts - centre) @ vt[0], (pts - centre) @ np.array([-vt[0, 1], vt[0, 0]])
    span = (vis - centre) @ vt[0]
    return (np.abs(across) <= tol) & (along >= span.min() - tol) & (along <= span.max() + tol)


MIN_BIASES = 3
"""Bias settings an axis needs for the force law's bend with flux density (saturation, iron reluctance, leakage) to
show: with fewer such an effect is absorbed into gap, origin and k (the diagnosis' blind spot says the same)."""


def bias_settings(frame: pd.DataFrame) -> dict[str, np.ndarray]:
    """The distinct bias settings [A] each axis of ``frame`` ran (columns ``axis`` and ``bias_A``)."""
    return {ax: np.unique(np.round(frame.loc[frame["axis"] == ax, "bias_A"].to_numpy(float), 9)) for ax in AXES}


def model_margin_reason(df: pd.DataFrame, res: FitResult) -> tuple[str, str] | None:
    """Why the estimated origin may be biased beyond its standard error, and what would show it (None when nothing
    says so): the ideal law does not fit its data, or an axis ran fewer than :data:`MIN_BIASES` biases, too few for
    the force law's bend with flux density to show, so such an effect is absorbed into the origin."""
    if res.adequate is False:
        return (f"the ideal law does not fit these data (χ²/dof {res.reduced_chi2:.3g})",
                "a model that fits them (ambfit diagnose names the effect; identify --effect fits it) gives an "
                "origin to trust, and a design on it reaches further")
    if "bias_A" in df:
        few = {ax: len(b) for ax, b in bias_settings(df).items() if 0 < len(b) < MIN_BIASES}
        if few:
            return (", ".join(f"axis {ax} ran {n} bias{'es' if n > 1 else ''}" for ax, n in few.items())
                    + ": too few for a bend of the force law with flux density (saturation) to show, and such "
                    "an effect moves the origin unseen",
                    f"a sweep of {MIN_BIASES} or more biases towards the coil limit shows it (these steps add "
                    "biases), and a design on those data reaches further")
    return None


def candidate_steps(center_um=(0.0, 0.0), offsets_um: Sequence[float] | None = None,
                    biases_A: Sequence[float] | None = None, *, bearing: Bearing = PAPER_BEARING) -> pd.DataFrame:
    """Candidate steps: set-points ``center + (dv, dw)`` for every pair of offsets [µm], at every bias [A].

    Defaults scale with the bearing: offsets :data:`OFFSET_FRACTIONS` of its back-up clearance (rounded to
    0.1 µm), biases :data:`BIAS_FRACTIONS` of its coil current limit (rounded to 0.01 A).
    """
    if offsets_um is None:
        offsets_um = [round(bearing.backup_clearance * 1e6 * f, 1) for f in OFFSET_FRACTIONS]
    if biases_A is None:
        biases_A = [round(bearing.max_current * f, 2) for f in BIAS_FRACTIONS]
    rows = [{"v_set_um": center_um[0] + dv, "w_set_um": center_um[1] + dw, "bias_A": b}
            for dv in offsets_um for dw in offsets_um for b in biases_A]
    return pd.DataFrame(rows)


def _rows_for(steps: pd.DataFrame, template: pd.Series, load_by_axis: dict, std: dict) -> pd.DataFrame:
    """Contract rows (currents filled in later) for candidate steps under the template's load."""
    out = []
    for _, s in steps.iterrows():
        for ax in AXES:
            out.append({"axis": ax, "bias_A": s["bias_A"], "i_top_A": s["bias_A"], "i_bottom_A": s["bias_A"],
                        "v_um": s["v_set_um"], "w_um": s["w_set_um"], "load_N": load_by_axis[ax][0],
                        "load_id": template["load_id"], "experiment": "_candidate", "iteration": 1,
                        "i_top_std_A": std["i"], "i_bottom_std_A": std["i"], "v_std_um": std["x_um"],
                        "w_std_um": std["x_um"]})
    return pd.DataFrame(out)


def _information_rows(res: FitResult, df: pd.DataFrame, **noise) -> tuple[np.ndarray, list, np.ndarray]:
    """Per-row Jacobian (SI parameter units) of the standardized residuals at the estimate, for ``df``, and the
    model's coil currents there, array[n, 2] (top, bottom) [A]."""
    from ambfit.estimation.debias import model_currents

    prob, meta = build_problem(df, **noise)
    model = Model.of((), res.bearing)
    vals = dict(zip(res.names, res.values))
    nominal = res.bearing.nominal_gap
    g = np.array([vals.get(n, nominal) for n in GAPS])
    x = np.array([vals.get(n, 0.0) for n in ORIGINS])
    k = np.array([vals.get(n, K_REFERENCE) for n in FORCE_CONSTANTS])
    loads = np.array([vals.get(f"load[{grp}]", 0.0) for grp in meta.load_groups])
    th = jnp.asarray(to_theta(g, x, k, loads))
    it, ib = model_currents(th, prob, prob.bias, model)
    prob = prob.with_readings(it, ib, prob.x)
    free = free_mask(prob, meta)
    j = np.asarray(jacobian(th, prob, model))[:, free] / param_scale(prob.n_loads)[free]
    return j, free_names(meta, free), np.stack([np.asarray(it), np.asarray(ib)], axis=-1)


def recommend(data: Dataset | pd.DataFrame, *, n_steps: int = 8, candidates: pd.DataFrame | None = None,
              target: str = "g_v0", criterion: str = "A", result: FitResult | None = None,
              max_radius_um: float | None = None, bearing: Bearing = PAPER_BEARING, sigma_i: float | None = None,
              sigma_x: float | None = None) -> Recommendation:
    """Greedy A- (variance of ``target``) or D-optimal (log det of gap/origin information) next steps.

    ``candidates`` has columns ``v_set_um``, ``w_set_um``, ``bias_A``; default: :func:`candidate_steps` of the
    bearing (offsets a fraction of its back-up clearance, biases a fraction of its coil current limit) around
    the estimated bearing centre ``(-v0, -w0)``.  Candidate rows carry the data's most common load group (its
    known value, or its fitted value).  Only candidates within the bearing's limits are chosen from
    (:func:`ambfit.rig.limits.step_limits`, the rule ``ambfit simulate`` applies): the rotor within the back-up
    clearance of the bearing centre (the estimated one, less :data:`ORIGIN_MARGIN_SIGMAS` standard errors of the
    origin; ``max_radius_um`` [µm] tightens the clearance), the bias and the coil currents the model predicts
    at the estimate within the coil current limit.  When the origin may be biased by an effect the data cannot
    show (:func:`model_margin_reason`: fewer than three biases on an axis, or a law that does not fit), the
    set-points are also kept among the positions already run (:func:`inside_visited`), which are safe whatever
    the origin, and the positions run are candidates themselves.  The bearing is the fit's (``result``) when one is given.
    ``sigma_i`` [A] and ``sigma_x`` [m] declare the readings' noise (as in :func:`ambfit.estimation.fit.fit`)
    for the fit and the candidates.
    """
    from ambfit.rig.limits import step_limits

    df = (data.frame if isinstance(data, Dataset) else data).reset_index(drop=True)
    res = result or fit(df, bearing=bearing, sigma_i=sigma_i, sigma_x=sigma_x, debias="none")
    bearing = res.bearing
    if target not in res.names:
        raise ValueError(f"target {target!r} is not estimated here; choose one of {res.names}")
    origin = np.array([res.value(n) if n in res.names else 0.0 for n in ORIGINS])
    idx = [res.names.index(n) for n in ORIGINS if n in res.names]
    cov = np.asarray(res.cov)[np.ix_(idx, idx)]
    margin = ORIGIN_MARGIN_SIGMAS * float(np.sqrt(max(np.linalg.eigvalsh(cov).max(), 0.0))) if idx else 0.0
    reason = model_margin_reason(df, res)
    why, remedy = reason if reason else (None, None)
    if max_radius_um is not None:
        bearing = bearing.with_(backup_clearance=min(bearing.backup_clearance, max_radius_um * 1e-6))
    visited = df[["v_um", "w_um"]].to_numpy(float) * 1e-6
    if candidates is None:
        candidates = candidate_steps(tuple(round(-c * 1e6) for c in origin), bearing=bearing)
        if why:           # the positions already run (one per VISITED_TOLERANCE), and their centre, are candidates
            step = VISITED_TOLERANCE * 1e6
            run = np.unique(np.round(visited * 1e6 / step) * step, axis=0)                       # [µm]
            run = np.vstack([run, run.mean(axis=0)])
            biases = candidates["bias_A"].unique()
            candidates = pd.concat([candidates, pd.DataFrame(
                [{"v_set_um": v, "w_set_um": w, "bias_A": b} for v, w in run for b in biases])], ignore_index=True)
    # keep the rotor off the back-up bearing and the coils below their current limit
    set_points = candidates[["v_set_um", "w_set_um"]].to_numpy(float) * 1e-6
    limits = step_limits(set_points, candidates["bias_A"].to_numpy(float), origin, bearing, margin=margin)
    ok = limits.ok & (inside_visited(set_points, visited) if why else True)
    candidates = candidates[ok].reset_index(drop=True)
    within = (f"within {(bearing.backup_clearance - margin) * 1e6:.3g} µm of the estimated bearing centre "
              f"({-origin[0] * 1e6:.1f}, {-origin[1] * 1e6:.1f}) µm (the back-up clearance of "
              f"{bearing.backup_clearance * 1e6:.3g} µm less {margin * 1e6:.2g} µm for the origin's uncertainty)"
              + (f" and among the positions already run (their convex hull, which the rotor has visited): the "
                 f"origin may be biased by an effect these data cannot show ({why}); {remedy}" if why else "")
              + f", with a bias within the {bearing.max_current:g} A coil current limit")
    if candidates.empty:
        raise ValueError(f"no candidate set-point lies {within}")
    groups = load_groups(df)
    main = groups.str.rsplit("|", n=1).str[0].mode().iloc[0]
    template = df[groups.str.startswith(main + "|")].iloc[0].copy()
    if "load_id" not in df.columns:
        df = df.assign(load_id=main)
        template["load_id"] = main
    load_by_axis = {}
    for ax in AXES:
        sel = (groups == f"{main}|{ax}") if "load_id" in df.columns else (df["axis"] == ax)
        known = df.loc[sel, "load_N"].dropna() if "load_N" in df.columns else pd.Series(dtype=float)
        load_by_axis[ax] = (float(known.iloc[0]) if len(known) else np.nan, len(known) > 0)
    std = {"i": sigma_i if sigma_i is not None else
           float(np.nanmedian(df["i_top_std_A"])) if "i_top_std_A" in df else 1e-3,
           "x_um": sigma_x * 1e6 if sigma_x is not None else
           float(np.nanmedian(df["v_std_um"])) if "v_std_um" in df else 0.1}
    cand_rows = _rows_for(candidates, template, load_by_axis, std)
    both = pd.concat([df, cand_rows], ignore_index=True)
    j, names, currents = _information_rows(res, both, sigma_i=sigma_i, sigma_x=sigma_x)
    n0 = len(df)
    # the coil currents the model predicts for each candidate step, array[c, 2 axes, 2 coils]
    predicted = step_limits(candidates[["v_set_um", "w_set_um"]].to_numpy(float) * 1e-6,
                            candidates["bias_A"].to_numpy(float), origin, bearing,
                            currents[n0:].reshape(len(candidates), 2, 2), margin=margin)
    keep = np.flatnonzero(predicted.ok)
    if keep.size == 0:
        raise ValueError(f"no candidate step keeps the predicted coil currents {within}")
    candidates = candidates.iloc[keep].reset_index(drop=True)
    j = np.concatenate([j[:n0], j[n0:].reshape(-1, 2, j.shape[1])[keep].reshape(-1, j.shape[1])])
    info = j[:n0].T @ j[:n0]
    jc = j[n0:].reshape(len(candidates), 2, -1)          # one step = two rows (v, w)
    step_info = np.einsum("cri,crj->cij", jc, jc)
    t = names.index(target)
    sel_idx = [names.index(n) for n in names if n in GAPS + ORIGINS]

    def score(m):
        if criterion == "A":
            return np.linalg.pinv(m)[t, t]
        sub = np.linalg.pinv(m)[np.ix_(sel_idx, sel_idx)]
        return np.linalg.slogdet(sub)[1]

    std_now = float(np.sqrt(np.linalg.pinv(info)[t, t]))
    chosen, out = [], []
    for _ in range(n_steps):
        scores = np.array([score(info + step_info[c]) for c in range(len(candidates))])
        c = int(np.argmin(scores))
        info = info + step_info[c]
        chosen.append(c)
        out.append({**candidates.iloc[c].to_dict(), "predicted_std_after": float(np.sqrt(np.linalg.pinv(info)[t, t]))})
    return Recommendation(steps=pd.DataFrame(out), target=target, std_now=std_now, criterion=criterion,
                          candidates=candidates, centre_um=(-origin[0] * 1e6, -origin[1] * 1e6),
                          radius_um=(bearing.backup_clearance - margin) * 1e6, margin_reason=why, remedy=remedy,
                          limits=f"every step {within}")
