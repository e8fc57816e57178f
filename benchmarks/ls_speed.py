"""Speed of the least-squares fit against scipy.optimize.least_squares on the same residuals.

1. One fit of ~1000 readings after compilation: our jitted LM (optimistix's iteration, written out in the core) vs
   scipy's MINPACK LM (``method="lm"``) given the same jitted residual and Jacobian
   functions and the same start.  Target: >= 5x faster.
2. 1000 data sets of the paper's Table 2 protocol (80 readings each), same
   closed-form seeds for both: our vmapped batch solve (and the jitted loop) vs
   a Python loop of scipy fits.  Target: >= 10x the throughput.  Ours runs
   ``FIRST_STEPS`` Levenberg-Marquardt steps per reweighting round (closed-form seeds make that
   enough: the fraction of data sets ending with EDM < 1e-6 is reported).
   And ``fit_many`` end to end (from the tables: problems, seeds, the solve, covariances, the outlier
   test, plausibility), with its default second-order bias correction and without it, against that vmapped
   solve alone.  Target: within 2x.  And the same study with one reading 20 mA off in every data set (each outlier
   test names it and refits, the refits batched), against the clean study.
3. Cold wall time of ``ambfit identify`` on the default data, in a fresh process:
   without and with the persistent compilation cache.  Target: <= 2 s.  And ``ambfit --help``
   (it must import nothing heavy).  Target: <= 0.5 s.
4. One data set of 200 000 readings (``--large-rows``): ``fit`` end to end, warm, against the same fit of a tenth
   of them.  Target: <= 12x, linear in the rows (a start that grew faster once took minutes).  And ``ambfit
   identify`` of that file, cold.

Times are medians of repeats measured in this run; ratios are what is reported.

    .venv/bin/python benchmarks/ls_speed.py [--datasets 1000]

Writes reports/benchmarks/ls_speed.{json,md}.
"""

import argparse
import gc
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import scipy
from scipy.optimize import least_squares

from ambfit import rig
from ambfit.estimation import batches, core, fit, lm, seeds
from ambfit.estimation.core import IDEAL
from ambfit.rig import protocol

ROOT = Path(__file__).resolve().parents[1]


def _median_time(fn, repeats):
    """Median wall time of ``repeats`` calls, with the cyclic garbage collector off while they run, as timeit does:
    a full collection triggered by one side's garbage would otherwise land in whichever call runs next."""
    ts = []
    gc.collect()
    gc.disable()
    try:
        for _ in range(repeats):
            t = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t)
    finally:
        gc.enable()
    return float(np.median(ts))


def single_fit(repeats):
    spec = rig.PAPER_RIG
    proto = protocol.rich(biases=(1.0, 1.1, 1.2, 1.3, 1.4, 1.5, 1.6), n_positions=9, masses_kg=(0.0, 0.5, 1.0, 1.5))
    df = rig.simulate(spec, proto, seed=1).data
    prob, meta = core.build_problem(df)
    theta0 = seeds.starts(df, [prob], [meta], [0, len(df)], [spec.bearing])[0][0]
    th0 = jnp.asarray(theta0)
    free = core.free_mask(prob, meta)
    res_j = jax.jit(lambda th: core.residuals(th, prob))
    jac_j = jax.jit(jax.jacfwd(lambda th: core.residuals(th, prob)))
    ours = lambda: jax.block_until_ready(lm.solve(th0, prob).theta)  # noqa: E731  (includes the EDM check)
    ours()  # compile
    fr = np.nonzero(free)[0]

    def full(x):
        th = np.array(theta0)
        th[fr] = x
        return jnp.asarray(th)

    sp = lambda: least_squares(lambda x: np.asarray(res_j(full(x))), theta0[fr],  # noqa: E731
                               jac=lambda x: np.asarray(jac_j(full(x)))[:, fr], method="lm", xtol=1e-10, ftol=1e-10)
    sp()
    t_ours, t_sp = _median_time(ours, repeats), _median_time(sp, repeats)
    a = np.asarray(lm.solve(th0, prob).theta)[fr]
    b = sp().x
    return {"rows": len(df), "ours_s": t_ours, "scipy_s": t_sp, "speedup": t_sp / t_ours,
            "max_rel_diff_of_solutions": float(np.max(np.abs(a - b) / np.abs(b)))}


def many_fits(n, repeats):
    spec = rig.PAPER_RIG
    proto = protocol.paper_table2(center=(-33.3e-6, 11.3e-6))
    data = [rig.simulate(spec, proto, seed=s).data for s in range(n)]
    built = [core.build_problem(d) for d in data]
    theta0 = np.stack([seeds.starts(d, [b[0]], [b[1]], [0, len(d)], [spec.bearing])[0][0]
                       for d, b in zip(data, built)])
    th0 = jnp.asarray(theta0)
    probs = batches.pad([b[0] for b in built], batches.row_bucket(len(data[0])))
    steps = lm.FIRST_STEPS
    settings = {"reweightings": np.asarray(lm.REWEIGHTINGS), "edm_round": np.asarray(lm.EDM_ROUND),
                "rtol": np.asarray(lm.RTOL)}
    vm = lambda: jax.block_until_ready(batches._vmapped(th0, probs, IDEAL, np.asarray(steps), settings).theta)  # noqa: E731
    converged = float(np.mean(np.asarray(batches._vmapped(th0, probs, IDEAL, np.asarray(steps), settings).edm)
                              < core.EDM_MAX))
    vm()

    def loop():
        return [jax.block_until_ready(lm.solve(th0[s], built[s][0], max_steps=steps).theta) for s in range(n)]

    loop()
    free = core.free_mask(built[0][0], built[0][1])
    fr = np.nonzero(free)[0]
    res_j = jax.jit(lambda th, p: core.residuals(th, p))
    jac_j = jax.jit(jax.jacfwd(lambda th, p: core.residuals(th, p)))

    def sp_loop():
        out = []
        for s in range(n):
            p, base = built[s][0], np.array(theta0[s])

            def full(x, base=base):
                th = base.copy()
                th[fr] = x
                return jnp.asarray(th)

            out.append(least_squares(lambda x: np.asarray(res_j(full(x), p)), base[fr],
                                     jac=lambda x: np.asarray(jac_j(full(x), p))[:, fr], method="lm").x)
        return out

    sp_loop()
    t_vm, t_loop, t_sp = (_median_time(f, repeats) for f in (vm, loop, sp_loop))
    fit.fit_many(data)                                   # compiles its buckets
    t_e2e = _median_time(lambda: fit.fit_many(data), repeats)
    fit.fit_many(data, debias="none")
    t_plain = _median_time(lambda: fit.fit_many(data, debias="none"), repeats)
    # the same data sets, each with one reading 20 mA off: every outlier test names it and refits
    bad = [d.copy() for d in data]
    for s, d in enumerate(bad):
        d.loc[d.index[s % len(d)], "i_top_A"] += 0.02
    first = fit.fit_many(bad)                   # (compiles what the timing then reuses)
    t_bad = _median_time(lambda: fit.fit_many(bad), min(repeats, 3))
    named = float(np.mean([isinstance(r, fit.FitResult) and [o.row for o in r.outliers] == [s % len(d) + 1]
                           for s, (r, d) in enumerate(zip(first, bad))]))
    return {"datasets": n, "rows_each": len(data[0]), "vmap_s": t_vm, "jit_loop_s": t_loop, "scipy_loop_s": t_sp,
            "throughput_ratio_vmap": t_sp / t_vm, "throughput_ratio_jit_loop": t_sp / t_loop,
            "fit_many_end_to_end_s": t_e2e, "fit_many_over_vmap": t_e2e / t_vm,
            "fit_many_plain_s": t_plain, "fit_many_plain_over_vmap": t_plain / t_vm,
            "vmap_converged_fraction": converged, "faster_method": "vmap" if t_vm < t_loop else "loop",
            "fit_many_outliers_s": t_bad, "fit_many_outliers_over_clean": t_bad / t_e2e,
            "outlier_named_fraction": named}


def _warm_fit_s(rows: int):
    """Wall time of a warm ``fit`` of one Table 2 data set of ``rows`` readings, the data and the fit."""
    df = rig.simulate(rig.PAPER_RIG, protocol.paper_table2(iterations=rows // 8, center=(-33.3e-6, 11.3e-6)),
                      seed=1).data
    fit.fit(df)                                         # compiles this length's solve
    return _median_time(lambda: fit.fit(df), 3), df, fit.fit(df)


def large_fit(rows: int):
    """``fit`` end to end (problem, start, solve, covariance, outlier test) on one data set of ``rows`` readings,
    warm, against the same fit of a tenth of them: a pipeline linear in the rows takes about 10x (less where fixed
    costs still show).  And ``ambfit identify`` of the large file in a fresh process."""
    t_small, _, _ = _warm_fit_s(rows // 10)
    t_large, df, res = _warm_fit_s(rows)
    exe = Path(sys.executable).with_name("ambfit")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "large.csv"
        df.to_csv(path, index=False)
        t = time.perf_counter()
        subprocess.run([str(exe), "identify", str(path)], capture_output=True, check=True)
        t_cli = time.perf_counter() - t
    return {"rows": len(df), "fit_s": t_large, "tenth_fit_s": t_small, "scaling": t_large / t_small,
            "identify_cold_s": t_cli, "converged": bool(res.converged)}


def cold_identify(repeats):
    exe = Path(sys.executable).with_name("ambfit")
    data = ROOT / "data" / "paper_table2.csv"
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        for label, env_cache in (("no_cache", "off"), ("persistent_cache", cache)):
            env = {**os.environ, "AMBFIT_JAX_CACHE": env_cache}
            subprocess.run([str(exe), "identify", str(data)], env=env, capture_output=True, check=True)  # fill
            ts = []
            for _ in range(repeats):
                t = time.perf_counter()
                subprocess.run([str(exe), "identify", str(data)], env=env, capture_output=True, check=True)
                ts.append(time.perf_counter() - t)
            out[label + "_s"] = float(np.median(ts))
    ts = []
    for _ in range(5):
        t = time.perf_counter()
        subprocess.run([str(exe), "--help"], capture_output=True, check=True)
        ts.append(time.perf_counter() - t)
    out["help_s"] = float(np.median(ts))
    return out


def main():
    ap = argparse.ArgumentParser(description="LS speed vs scipy")
    ap.add_argument("--datasets", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--large-rows", type=int, default=200_000)
    ap.add_argument("--out", type=Path, default=ROOT / "reports" / "benchmarks")
    args = ap.parse_args()
    load = os.getloadavg()[0]
    s1 = single_fit(args.repeats)
    s2 = many_fits(args.datasets, max(1, args.repeats // 2))
    s3 = cold_identify(3)
    s4 = large_fit(args.large_rows)
    out = {"versions": {"jax": jax.__version__, "scipy": scipy.__version__}, "cpu_count": os.cpu_count(),
           "load_average_at_start": load,
           "single_fit": s1, "batch": s2, "cold_identify": s3, "large": s4,
           "targets": {"single_speedup": 5.0, "batch_throughput_ratio": 10.0, "fit_many_over_vmap": 2.0,
                       "cold_identify_s": 2.0, "help_s": 0.5,
                       "large_scaling": 12.0}}
    t = out["targets"]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ls_speed.json").write_text(json.dumps(out, indent=2))
    md = ["# Least-squares speed vs scipy.optimize.least_squares (same residuals, same run)", "",
          "| measurement | ambfit | scipy | ratio | target |", "|---|---|---|---|---|",
          f"| one fit, {s1['rows']} readings (after compile) | {s1['ours_s'] * 1e3:.1f} ms | {s1['scipy_s'] * 1e3:.1f} ms "
          f"| {s1['speedup']:.1f}x | ≥ {t['single_speedup']:g}x |",
          f"| {s2['datasets']} data sets x {s2['rows_each']} readings, vmap | {s2['vmap_s']:.2f} s | "
          f"{s2['scipy_loop_s']:.2f} s | {s2['throughput_ratio_vmap']:.1f}x | ≥ {t['batch_throughput_ratio']:g}x |",
          f"| same, jitted loop | {s2['jit_loop_s']:.2f} s | {s2['scipy_loop_s']:.2f} s | "
          f"{s2['throughput_ratio_jit_loop']:.1f}x | |",
          f"| `fit_many` end to end (tables, seeds, solve, covariances, outlier test, second-order bias correction) "
          f"| {s2['fit_many_end_to_end_s']:.2f} s | vmapped solve {s2['vmap_s']:.2f} s | "
          f"{s2['fit_many_over_vmap']:.1f}x the solve | ≤ {t['fit_many_over_vmap']:g}x |",
          f"| same, `debias=\"none\"` | {s2['fit_many_plain_s']:.2f} s | vmapped solve {s2['vmap_s']:.2f} s | "
          f"{s2['fit_many_plain_over_vmap']:.1f}x the solve | ≤ {t['fit_many_over_vmap']:g}x |",
          f"| same data sets, one reading 20 mA off in each (that reading alone named and left out in {s2['outlier_named_fraction']:.0%}: "
          f"the outlier tests' refits batched) | {s2['fit_many_outliers_s']:.2f} s | clean `fit_many` "
          f"{s2['fit_many_end_to_end_s']:.2f} s | {s2['fit_many_outliers_over_clean']:.1f}x the clean study | |",
          f"| cold `ambfit identify` default data, no cache | {s3['no_cache_s']:.2f} s | | | ≤ {t['cold_identify_s']:g} s |",
          f"| cold `ambfit identify` default data, persistent cache | {s3['persistent_cache_s']:.2f} s | | | ≤ {t['cold_identify_s']:g} s |",
          f"| `ambfit --help` in a fresh process | {s3['help_s']:.2f} s | | | ≤ {t['help_s']:g} s |",
          f"| `fit` of one data set of {s4['rows']} readings, warm (problem, start, solve, covariance, outlier test) "
          f"| {s4['fit_s']:.2f} s | a tenth of the rows {s4['tenth_fit_s']:.2f} s | {s4['scaling']:.1f}x "
          f"| ≤ {t['large_scaling']:g}x (linear) |",
          f"| cold `ambfit identify` of that file (read, checks, fit, table) | {s4['identify_cold_s']:.1f} s | | | |",
          "", f"Solutions agree to {s1['max_rel_diff_of_solutions']:.1e} (relative). jax {jax.__version__}, "
          f"scipy {scipy.__version__}, {os.cpu_count()} cores, load average {load:.1f} at the start."]
    (args.out / "ls_speed.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
