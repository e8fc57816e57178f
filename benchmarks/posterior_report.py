"""Posterior efficiency on the default data, the paper's Fig. 2 on the rig, and the design comparison.

1. Default data (data/paper_table2.csv): effective samples per second (bulk ESS of the slowest
   parameter / wall time, compiled beforehand: warm) of ``bayes.sample`` (4 independent emcee
   ensembles in lockstep, run to 50 autocorrelation times), of its peer measured in the same run
   (the textbook use of emcee: one ``EnsembleSampler`` per ensemble with the jitted log-density
   vectorised over walkers, the same steps and walkers), and of BlackJAX's NUTS
   (``ambfit.estimation.nuts``, 4 chains, when installed); the posterior mean and sd against
   least squares (target: within 5 %) and NUTS against emcee.
2. Fig. 2: the misfit map over gap 600-1000 µm and origin -100...100 µm at 1 µm steps
   (401 x 201), for (a) the paper's first iteration (pairs at ±20 µm in sensor coordinates,
   i.e. non-symmetric about the effective origin at -33.3 µm) with one unknown load per
   position, as Eq. 5-7 see the data, and (b) the ten iterations of the default data by
   least squares; posterior draws, the least-squares ellipses and the weakest Fisher
   direction drawn on them.  The evaluation time of one grid is recorded.
3. Design comparison (conditioning.compare_designs): condition number and CRLB of the
   gap and origin for current-only, position-only, symmetric, non-symmetric and rich
   designs, under both load assumptions.

    .venv/bin/python benchmarks/posterior_report.py

Writes reports/posterior/ (Markdown, JSON, PNG).
"""

import json
import os
import time
from pathlib import Path

import numpy as np
import pandas as pd

from ambfit import rig
from ambfit.data import read_csv
from ambfit.estimation import bayes, conditioning, fit
from ambfit.faces import plots
from ambfit.rig import protocol as P

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "reports" / "posterior"


def _markdown(df: pd.DataFrame) -> str:
    def cell(v):
        return f"{v:.3g}" if isinstance(v, (float, np.floating)) else str(v)
    lines = ["| " + " | ".join(df.columns) + " |", "|" + "---|" * len(df.columns)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join(lines)


def _textbook_emcee(ds, ls, n_walkers: int, n_steps: int, seed: int) -> tuple[float, float]:
    """The peer: emcee as its documentation uses it, one sampler per independent ensemble, the log-density jitted
    and vectorised over walkers (``vectorize=True``), the same start, walkers and steps as ambfit's run; seconds
    and the slowest bulk ESS of 4 ensembles (burn-in 2 tau, as ambfit's)."""
    import arviz as az
    import emcee
    import equinox as eqx
    import jax

    target = bayes.Target.of(ds, None, bayes.PAPER_BEARING, ls, {})
    logp = eqx.filter_jit(lambda post, zs: jax.vmap(post)(zs))
    rng = np.random.default_rng(seed)
    logp(target.post, np.zeros((n_walkers // 2, target.ndim)) + target.z_hat).block_until_ready()
    t0 = time.perf_counter()
    chains = []
    for _ in range(4):
        sampler = emcee.EnsembleSampler(n_walkers, target.ndim, lambda zs: np.asarray(logp(target.post, zs)),
                                        vectorize=True)
        sampler.random_state = np.random.RandomState(int(rng.integers(2**31))).get_state()
        sampler.run_mcmc(target.z_hat + 0.1 * rng.standard_normal((n_walkers, target.ndim)) @ target.chol.T,
                         n_steps, progress=False)
        chains.append(sampler)
    secs = time.perf_counter() - t0
    tau = max(float(np.max(s.get_autocorr_time(tol=0))) for s in chains)
    burn, thin = int(np.ceil(2 * tau)), max(1, int(tau / 2))
    draws = np.stack([s.get_chain()[burn::thin].reshape(-1, target.ndim) for s in chains])
    ess = az.ess(az.from_dict({"posterior": {f"p{j}": draws[..., j] for j in range(target.ndim)}}), method="bulk")
    return secs, float(min(float(ess[v]) for v in ess.data_vars))


def _nuts(ds, ls) -> dict:
    """NUTS (BlackJAX) on the same data, compiled first; its posterior against emcee's."""
    try:
        from ambfit.estimation.nuts import MissingSampler, sample_nuts
        sample_nuts(ds, ls=ls, n_chains=1)                  # compiles the chain of 1000 + 1000 steps
    except MissingSampler as exc:
        return {"skipped": str(exc)}
    t0 = time.perf_counter()
    n = sample_nuts(ds, ls=ls, seed=1)
    secs = time.perf_counter() - t0
    e = bayes.sample(ds, ls=ls, seed=2)
    ess = min(p["ess_bulk"] for p in n.to_json()["params"].values())
    ratios = [n.error(x) / e.error(x) for x in e.names]
    return {"seconds": secs, "ess_min": ess, "ess_per_second": ess / secs,
            "max_mean_diff_in_sd": max(abs(n.value(x) - e.value(x)) / e.error(x) for x in e.names),
            "sd_ratio_min": min(ratios), "sd_ratio_max": max(ratios),
            "divergent": int(n.datatree.sample_stats["diverging"].sum())}


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    md = ["# Posterior, solution space and design comparison", ""]
    report = {}

    # 1. efficiency on the default data
    ds = read_csv(ROOT / "data" / "paper_table2.csv")
    ls = fit.fit(ds)
    bayes.sample(ds, n_ensembles=4, n_steps=200, max_steps=200, ls=ls)          # compile outside the timing
    t0 = time.perf_counter()
    res = bayes.sample(ds, n_ensembles=4, n_steps=3000, seed=1, ls=ls)
    secs = time.perf_counter() - t0
    js = res.to_json()
    ess_min = min(p["ess_bulk"] for p in js["params"].values())
    peer_secs, peer_ess = _textbook_emcee(ds, ls, res.n_walkers, res.n_steps, seed=1)
    nuts = _nuts(ds, ls)
    rows = []
    for name, key in (("g_v0", "g_v0_um"), ("v0", "v0_um"), ("g_w0", "g_w0_um"), ("w0", "w0_um"),
                      ("k_v", "k_v_Nm2_per_A2"), ("k_w", "k_w_Nm2_per_A2")):
        sc = 1e6 if key.endswith("_um") else 1.0
        p = js["params"][key]
        m_ls, s_ls = ls.value(name) * sc, ls.error(name) * sc
        rows.append({"param": name, "post_mean": p["value"], "post_sd": p["std"], "ls_value": m_ls, "ls_std": s_ls,
                     "mean_diff_in_ls_sd": (p["value"] - m_ls) / s_ls, "sd_ratio": p["std"] / s_ls,
                     "hdi94": [p["hdi_low"], p["hdi_high"]], "r_hat": p["r_hat"], "ess_bulk": p["ess_bulk"]})
    report["efficiency"] = {"seconds": secs, "ess_min": ess_min, "ess_per_second": ess_min / secs,
                            "tau_max": float(np.max(res.tau)), "too_short": res.too_short, "rows": rows,
                            "n_walkers": res.n_walkers, "n_steps": res.n_steps,
                            "peer": {"what": "one emcee EnsembleSampler per ensemble, jitted vectorised log-density",
                                     "seconds": peer_secs, "ess_min": peer_ess,
                                     "ess_per_second": peer_ess / peer_secs},
                            "speedup_vs_peer": (ess_min / secs) / (peer_ess / peer_secs), "nuts": nuts,
                            "load_average": os.getloadavg()[0]}
    plots.save(plots.plot_pair(res), OUT / "pair.png")
    res.datatree.to_netcdf(OUT / "posterior_default.nc", engine="h5netcdf")
    eff = report["efficiency"]
    md += ["## 1. Posterior on the default data", "",
           f"Load average {eff['load_average']:.1f} (2 cores); every sampler compiled before its timing (warm).", "",
           "| sampler | walkers x steps per ensemble (or draws per chain) | seconds | slowest bulk ESS | ESS/s |",
           "|---|---|---|---|---|",
           f"| ambfit: 4 emcee ensembles in lockstep | {res.n_walkers} x {res.n_steps} | {secs:.1f} | {ess_min:.0f} "
           f"| **{ess_min / secs:.0f}** |",
           f"| peer: one emcee sampler per ensemble | {res.n_walkers} x {res.n_steps} | {peer_secs:.1f} | "
           f"{peer_ess:.0f} | {peer_ess / peer_secs:.0f} |"]
    if "seconds" in nuts:
        md.append(f"| NUTS (BlackJAX), 4 chains | 1000 draws after 1000 warm-up | {nuts['seconds']:.1f} | "
                  f"{nuts['ess_min']:.0f} | {nuts['ess_per_second']:.0f} |")
    md += ["", f"ambfit's emcee: **{eff['speedup_vs_peer']:.1f}x** the peer's ESS per second; max autocorrelation "
           f"time {np.max(res.tau):.0f} steps ({'too short' if res.too_short else 'long enough'}).", ""]
    if "seconds" in nuts:
        md += [f"NUTS against emcee: largest mean difference {nuts['max_mean_diff_in_sd']:.3f} posterior sd, sd "
               f"ratios {nuts['sd_ratio_min']:.3f}-{nuts['sd_ratio_max']:.3f}; {nuts['divergent']} divergent "
               "transitions.", ""]
    else:
        md += [f"NUTS: {nuts['skipped']}", ""]
    md += [
           "| param | posterior mean ± sd | least squares | (mean − LS)/sd_LS | sd / sd_LS | 94 % HDI | R-hat |",
           "|---|---|---|---|---|---|---|"]
    for r in rows:
        f = ".4g"
        md.append(f"| {r['param']} | {r['post_mean']:{f}} ± {r['post_sd']:.3g} | {r['ls_value']:{f}} ± {r['ls_std']:.3g} "
                  f"| {r['mean_diff_in_ls_sd']:+.3f} | {r['sd_ratio']:.3f} | {r['hdi94'][0]:{f}} – {r['hdi94'][1]:{f}} "
                  f"| {r['r_hat']:.3f} |")
    md += ["", "Pair plot: `pair.png`; the DataTree: `posterior_default.nc`.", ""]

    # 2. Fig. 2
    # The paper's setting: pairs at ±20 µm in sensor coordinates (the rotor at the back-up bearing centre),
    # i.e. 53.3 and 13.3 µm from the effective origin, never re-centred; one unknown load per position.
    parts = []
    for j, d in enumerate((20e-6, -20e-6)):
        lid = f"pos{j}"
        parts += [P.grid([(d, d)], [1.4, 1.6], load=lid, loads={lid: P.Load.gravity(1.0, known=False)}, iteration=i,
                         experiment="fig2") for i in range(1, 11)]
    first = rig.simulate(rig.PAPER_RIG, P.concat(*parts), seed=7).data
    sp_first = conditioning.solution_space(first, "v", weights_at=None, **conditioning.PAPER_FIG2)
    t0 = time.perf_counter()
    sp_first = conditioning.solution_space(first, "v", weights_at=None, **conditioning.PAPER_FIG2)
    t_grid = time.perf_counter() - t0
    try:
        ls_first = fit.fit(first)
    except fit.FitError as exc:
        ls_first = None
        report["fig2_first_fit_error"] = str(exc)
    samples = None
    if ls_first is not None:
        pr = bayes.sample(first, n_ensembles=2, n_steps=3000, seed=2, ls=ls_first)
        d = pr.draws.reshape(-1, pr.draws.shape[-1])
        samples = d[:, [pr.names.index("g_v0"), pr.names.index("v0")]]
    plots.save(plots.plot_solution_space(sp_first, result=ls_first, samples=samples), OUT / "fig2_first_iteration.png")
    sp_all = conditioning.solution_space(ds, "v", weights_at=ls)
    dv = res.draws.reshape(-1, res.draws.shape[-1])
    plots.save(plots.plot_solution_space(sp_all, result=ls, samples=dv[:, [res.names.index("g_v0"),
                                                                             res.names.index("v0")]]),
               OUT / "fig2_all_iterations.png")
    vdir = conditioning.weakest_direction(ls_first, "v") if ls_first is not None else None
    report["fig2"] = {"grid": list(sp_first.chi2.shape), "grid_seconds": t_grid,
                      "first_iteration_minimum_um": [m * 1e6 for m in sp_first.minimum],
                      "weakest_direction_gap_origin": None if vdir is None else vdir.tolist(),
                      "first_iteration_ls": None if ls_first is None else {
                          "g_v0_um": [ls_first.value("g_v0") * 1e6, ls_first.error("g_v0") * 1e6],
                          "v0_um": [ls_first.value("v0") * 1e6, ls_first.error("v0") * 1e6],
                          "corr": float(ls_first.corr[ls_first.names.index("g_v0"), ls_first.names.index("v0")])}}
    slope = None if vdir is None else vdir[1] / vdir[0]
    md += ["## 2. The paper's Fig. 2 on the rig", "",
           f"Grid 401 x 201 (gap 600–1000 µm, origin −100…100 µm, 1 µm) evaluated in {t_grid * 1e3:.0f} ms.", "",
           "`fig2_first_iteration.png`: 10 repetitions of pairs at ±20 µm in sensor coordinates with the rotor "
           "left at the back-up bearing centre (13.3 and 53.3 µm from the effective origin, i.e. not symmetric "
           "about it), one unknown load per position: the information Eq. 5–7 use. "
           + ("" if ls_first is None else
              f"Least squares: g_v0 = {ls_first.value('g_v0') * 1e6:.0f} ± {ls_first.error('g_v0') * 1e6:.0f} µm, "
              f"v0 = {ls_first.value('v0') * 1e6:.1f} ± {ls_first.error('v0') * 1e6:.1f} µm, correlation "
              f"{report['fig2']['first_iteration_ls']['corr']:+.3f}; the valley runs along the weakest Fisher "
              f"direction, {slope:+.3f} µm of origin per µm of gap."),
           "",
           "Why the valley: at one position, Eq. 6 fixes only the ratio (g0 − u)/(g0 + u) with "
           "u = (x0 + x) cos α, i.e. u/g0: every (gap, origin) on the line u = const · g0 fits. Each position "
           "adds such a line; two positions give two lines through the same point that meet at a small angle when "
           "the positions are close compared with their distance from the effective origin, and noise slides the "
           "solution along the narrow valley between them. Pairs symmetric about the effective origin make the two "
           "ratios move in opposite directions and the lines cross most steeply; that is why the paper moved to "
           "symmetric pairs after finding the valley. Least squares over all readings additionally uses that the "
           "same load is carried at every position (when it is), which collapses the valley (`fig2_all_iterations.png`).",
           ""]

    # 3. design comparison
    table = conditioning.compare_designs()
    plots.save(plots.plot_design_comparison(table), OUT / "design_comparison.png")
    report["designs"] = table.to_dict(orient="records")
    md += ["## 3. Designs compared (v axis, 0.6 mA / 0.1 µm noise, 10 repetitions each)", "",
           _markdown(table), "",
           "Current perturbation alone (one position) leaves the gap unbounded: only u/g0 is fixed. Position "
           "perturbation alone at one bias gives nothing when each position may carry its own load, and a badly "
           "conditioned system (condition ~4e3) when the load is shared. Current-position perturbation with two "
           "positions identifies both; the rich design (four biases, five positions) shrinks the gap's bound "
           "7x under per-position loads. `design_comparison.png`.", ""]
    (OUT / "README.md").write_text("\n".join(md) + "\n")
    (OUT / "report.json").write_text(json.dumps(report, indent=2, default=float))
    print("\n".join(md))


if __name__ == "__main__":
    main()
