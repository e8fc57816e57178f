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
from ambfit.physics.bearing import AXES, PAPER_BEARING, Bearing


@dataclasses.dataclass(frozen=True)
class Recommendation:
    """Steps to run next, in order, with the predicted standard error of the target after each."""

    steps: pd.DataFrame
    target: str
    std_now: float
    criterion: str

    def _unit(self) -> tuple[float, str]:
        return (1e6, "µm") if self.target[0] in "gvw" else (1.0, "N·m²/A²")

    @property
    def title(self) -> str:
        f, unit = self._unit()
        return f"next steps ({self.criterion}-optimal for {self.target}); now ± {self.std_now * f:.3g} {unit}"

    def display_rows(self) -> list[dict]:
        """One ``{column: text}`` row per recommended step."""
        f, unit = self._unit()
        return [{"#": str(i), "v set [µm]": f"{r.v_set_um:.0f}", "w set [µm]": f"{r.w_set_um:.0f}",
                 "bias [A]": f"{r.bias_A:.2f}", f"{self.target} std after [{unit}]": f"{r.predicted_std_after * f:.3g}"}
                for i, r in enumerate(self.steps.itertuples(), 1)]

    def to_json(self) -> dict:
        return {"target": self.target, "criterion": self.criterion, "std_now": self.std_now,
                "steps": self.steps.to_dict(orient="records")}

    def to_dataframe(self) -> pd.DataFrame:
        return self.steps.copy()

    def summary(self) -> str:
        return "\n".join([self.title] + ["  " + ", ".join(f"{k} {v}" for k, v in r.items())
                                          for r in self.display_rows()])

    __str__ = summary


def candidate_steps(center_um=(0.0, 0.0), offsets_um: Sequence[float] = tuple(range(-50, 51, 10)),
                    biases_A: Sequence[float] = (0.8, 1.0, 1.2, 1.4, 1.6, 1.8)) -> pd.DataFrame:
    """Candidate steps: set-points ``center + (dv, dw)`` for every pair of offsets [µm], at every bias [A]."""
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


def _information_rows(res: FitResult, df: pd.DataFrame) -> tuple[np.ndarray, list]:
    """Per-row Jacobian (SI parameter units) of the standardized residuals at the estimate, for ``df``."""
    from ambfit.estimation.debias import model_currents

    prob, meta = build_problem(df)
    model = Model.of((), res.bearing)
    vals = dict(zip(res.names, res.values))
    nominal = res.bearing.nominal_gap
    g = np.array([vals.get("g_v0", nominal), vals.get("g_w0", nominal)])
    x = np.array([vals.get("v0", 0.0), vals.get("w0", 0.0)])
    k = np.array([vals.get("k_v", K_REFERENCE), vals.get("k_w", K_REFERENCE)])
    loads = np.array([vals.get(f"load[{grp}]", 0.0) for grp in meta.load_groups])
    th = jnp.asarray(to_theta(g, x, k, loads))
    it, ib = model_currents(th, prob, prob.bias, model)
    prob = prob.with_readings(it, ib, prob.x)
    free = free_mask(prob, meta)
    j = np.asarray(jacobian(th, prob, model))[:, free] / param_scale(prob.n_loads)[free]
    return j, free_names(meta, free)


def recommend(data: Dataset | pd.DataFrame, *, n_steps: int = 8, candidates: pd.DataFrame | None = None,
              target: str = "g_v0", criterion: str = "A", result: FitResult | None = None,
              max_radius_um: float | None = None, bearing: Bearing = PAPER_BEARING) -> Recommendation:
    """Greedy A- (variance of ``target``) or D-optimal (log det of gap/origin information) next steps.

    ``candidates`` has columns ``v_set_um``, ``w_set_um``, ``bias_A``; default: a grid of
    ±50 µm around the estimated effective origin at biases 0.8-1.8 A.  Candidate rows
    carry the data's most common load group (its known value, or its fitted value).
    ``max_radius_um`` drops candidates farther than that from the sensor origin; by default the
    bearing's back-up clearance (60 µm on the paper's rig): a set-point beyond it would put the rotor
    on the back-up bearing.  Candidate biases at or above the bearing's coil current limit are
    dropped too.  The bearing is the fit's (``result``) when one is given.
    """
    df = (data.frame if isinstance(data, Dataset) else data).reset_index(drop=True)
    res = result or fit(df, bearing=bearing)
    bearing = res.bearing
    if max_radius_um is None:
        max_radius_um = bearing.backup_clearance * 1e6
    if target not in res.names:
        raise ValueError(f"target {target!r} is not estimated here; choose one of {res.names}")
    if candidates is None:
        centre = (-res.value("v0") * 1e6 if "v0" in res.names else 0.0,
                  -res.value("w0") * 1e6 if "w0" in res.names else 0.0)
        candidates = candidate_steps(tuple(round(c) for c in centre))
    # keep the rotor off the back-up bearing and the coils below their current limit
    r = np.hypot(candidates["v_set_um"], candidates["w_set_um"])
    candidates = candidates[(r <= max_radius_um) & (candidates["bias_A"] < bearing.max_current)].reset_index(drop=True)
    if candidates.empty:
        raise ValueError(f"no candidate set-point lies within {max_radius_um:g} µm of the sensor origin with a bias "
                         f"below the {bearing.max_current:g} A current limit")
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
    std = {"i": float(np.nanmedian(df["i_top_std_A"])) if "i_top_std_A" in df else 1e-3,
           "x_um": float(np.nanmedian(df["v_std_um"])) if "v_std_um" in df else 0.1}
    cand_rows = _rows_for(candidates, template, load_by_axis, std)
    both = pd.concat([df, cand_rows], ignore_index=True)
    j, names = _information_rows(res, both)
    n0 = len(df)
    info = j[:n0].T @ j[:n0]
    jc = j[n0:].reshape(len(candidates), 2, -1)          # one step = two rows (v, w)
    step_info = np.einsum("cri,crj->cij", jc, jc)
    t = names.index(target)
    sel_idx = [names.index(n) for n in names if n.startswith("g_") or n in ("v0", "w0")]

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
    return Recommendation(steps=pd.DataFrame(out), target=target, std_now=std_now, criterion=criterion)
