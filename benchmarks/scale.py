"""Throughput of a Monte Carlo study of mixed designs: in this process vs a LocalCluster of worker processes.

Each of ``--n`` items (default 10 000) is one simulated data set of its own design, drawn from the item's
seed: bias pair (1.0-1.6 A), pair offset (±15-40 µm) around a set-point near the effective origin,
iterations (1-10), current noise (0.3-1.2 mA), position noise (0.05-0.2 µm), the known rotor load or
an unknown static load, and the rig's true gaps (740-790 µm) and origins (±40 µm).  A task simulates
its chunk of items on the virtual rig (:mod:`ambfit.rig`) and fits them as one mixed batch
(:func:`ambfit.estimation.fit.fit_many`, plain least squares without the outlier test); only the estimates
travel back.

The same items and chunks run twice through :class:`ambfit.engine.Engine`: in this process, and on
``--workers`` local worker processes (one thread each).  Each engine first warms up every process
(compiles the batch solves of every bucket, the rig for every protocol length, then a study of ``--warmup``
items: compilation is a per-process start-up cost; the persistent compilation cache is on for both), then
runs the timed study.  Reported: wall time, data sets per second
per core, the speed-up (target >= 1.7 x with 2 workers), the largest difference between the two
engines' estimates (the same seeds must give the same numbers), CPU seconds by phase (simulate, fit)
and the peak resident memory of the driver and of every worker.  The machine's load average is
recorded before and after: on a shared machine the speed-up is depressed by the other work.

    .venv/bin/python benchmarks/scale.py [--n 10000] [--workers 2] [--chunk 250]

Writes reports/benchmarks/scale.{json,md}.
"""

import argparse
import functools
import json
import os
import platform
import resource
import time
from pathlib import Path

import numpy as np

from ambfit._jaxcache import enable_compilation_cache
from ambfit.engine import Engine
from ambfit.estimation import batches, fit
from ambfit.rig import protocol as P
from ambfit.rig import virtual as rig

ROOT = Path(__file__).resolve().parents[1]
BIASES = ((1.0, 1.2), (1.2, 1.4), (1.4, 1.6), (1.2, 1.6), (1.0, 1.4))
OFFSETS_UM = (15.0, 20.0, 30.0, 40.0)
UNKNOWN_LOAD = P.Load(5.0, 4.0, known=False)
QUANTITIES = ("g_v0", "v0", "g_w0", "w0")


def draw(seed: np.random.SeedSequence) -> dict:
    """One item's design, noise and truth (SI units), from its own seed."""
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(-40e-6, 40e-6, 2)
    return {"biases": BIASES[rng.integers(len(BIASES))], "offset": OFFSETS_UM[rng.integers(len(OFFSETS_UM))] * 1e-6,
            "iterations": int(rng.integers(1, 11)), "current": rng.uniform(0.3e-3, 1.2e-3),
            "position": rng.uniform(0.05e-6, 0.2e-6), "unknown_load": bool(rng.random() < 0.3),
            "g0": rng.uniform(740e-6, 790e-6, 2), "x0": x0, "center": -x0 + rng.uniform(-5e-6, 5e-6, 2),
            "noise_seed": int(rng.integers(2**31))}


def simulate(d: dict):
    loads = {"u": UNKNOWN_LOAD} if d["unknown_load"] else None
    proto = P.perturbation(d["biases"], (d["offset"],), center=tuple(d["center"]), iterations=d["iterations"],
                           experiment="mc", **({"load": "u", "loads": loads} if loads else {}))
    spec = rig.PAPER_RIG.with_truth(g0=d["g0"], x0=d["x0"])
    return rig.simulate(spec, proto, noise=rig.Noise(d["current"], d["position"]), seed=d["noise_seed"]).data


def study_chunk(items, seeds) -> list:
    """One task: simulate the chunk's data sets and fit them as one mixed batch.  Per item: the estimates and
    standard errors of ``QUANTITIES`` [m], converged, rows, outliers named; the task's CPU seconds by phase ride
    on its first item."""
    t0 = time.process_time()
    designs = [draw(s) for s in seeds]
    data = [simulate(d) for d in designs]
    t1 = time.process_time()
    fits = fit.fit_many(data, name_outliers=False)     # a Monte Carlo study's plain least squares
    t2 = time.process_time()
    out = []
    for j, (d, res) in enumerate(zip(data, fits)):
        if isinstance(res, Exception):
            row = np.full(11, np.nan)
            row[9] = len(d)
        else:
            row = np.array([res.value(q) for q in QUANTITIES] + [res.error(q) for q in QUANTITIES]
                           + [float(res.converged), float(len(d)), 0.0])
        out.append((row, {"simulate_cpu_s": t1 - t0, "fit_cpu_s": t2 - t1, "pid": os.getpid()} if j == 0 else None))
    return out


def peak_rss_mb() -> float:
    """Peak resident memory of this process [MB] (Linux reports ru_maxrss in kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def warm(n: int, chunk: int, seed: int) -> int:
    """Compile in this process what the timed study needs: the batch solves of every bucket its designs fall in
    (:func:`ambfit.estimation.batches.precompile`), the rig for every protocol length, then a small study."""
    batches.precompile([8 * it for it in range(1, 11)], [0, 2])
    for it in range(1, 11):
        simulate({**draw(np.random.SeedSequence([seed, 2, it])), "iterations": it})
    kids = np.random.SeedSequence([seed, 1]).spawn(n)
    for lo in range(0, n, chunk):
        study_chunk(list(range(lo, min(lo + chunk, n))), kids[lo:lo + chunk])
    return os.getpid()


def run(engine: Engine, n: int, chunk: int, seed: int, warmup: int) -> tuple[dict, np.ndarray]:
    """Warm up every process of ``engine``, then time the study; its record and the estimates, array[n, 11]."""
    with engine:
        t0 = time.perf_counter()
        engine.on_every_worker(functools.partial(warm, warmup, chunk, seed))
        warm_s = time.perf_counter() - t0
        load_before = os.getloadavg()
        cpu0 = resource.getrusage(resource.RUSAGE_SELF)
        t0 = time.perf_counter()
        out = engine.map_batches(study_chunk, range(n), seed=seed, chunk_size=chunk)
        wall = time.perf_counter() - t0
        cpu1 = resource.getrusage(resource.RUSAGE_SELF)
        load_after = os.getloadavg()
        peaks = engine.on_every_worker(peak_rss_mb)
        cores = engine.n_workers
    rows = np.array([r for r, _ in out])
    tasks = [m for _, m in out if m is not None]
    driver_cpu = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    return {"engine": repr(engine), "cores": cores, "n": n, "chunk": chunk, "tasks": len(tasks),
            "warmup_s": warm_s, "wall_s": wall, "datasets_per_s": n / wall, "datasets_per_s_per_core": n / wall / cores,
            "driver_cpu_s": driver_cpu, "simulate_cpu_s": sum(t["simulate_cpu_s"] for t in tasks),
            "fit_cpu_s": sum(t["fit_cpu_s"] for t in tasks), "processes": len({t["pid"] for t in tasks}),
            "peak_rss_mb": {"driver": peak_rss_mb(), **({} if engine.in_process else peaks)},
            "load_average_before": load_before, "load_average_after": load_after,
            "converged_fraction": float(np.nanmean(rows[:, 8])), "failed": int(np.isnan(rows[:, 0]).sum()),
            "rows_min_max": [int(rows[:, 9].min()), int(rows[:, 9].max())]}, rows


def _timed_copy(n: int, chunk: int, seed: int, barrier) -> float:
    """One plain process of the capacity control: warm up, wait for the others, time ``n`` items."""
    enable_compilation_cache()
    warm(chunk, chunk, seed)
    kids = np.random.SeedSequence([seed, 3]).spawn(n)

    def items():
        for lo in range(0, n, chunk):
            study_chunk(list(range(lo, min(lo + chunk, n))), kids[lo:lo + chunk])

    items()                                  # the timed items once untimed: every design's first call is paid
    barrier.wait()
    t0 = time.perf_counter()
    items()
    return time.perf_counter() - t0


def capacity(copies: int, n: int, chunk: int, seed: int) -> dict:
    """What this machine gives ``copies`` processes doing the same work at once, without Dask: the throughput of
    ``copies`` simultaneous plain processes over that of one alone (the ceiling of any engine's speed-up here)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    ctx = mp.get_context("spawn")
    walls = {}
    with ctx.Manager() as manager:
        for k in (1, copies):
            barrier = manager.Barrier(k)
            with ProcessPoolExecutor(max_workers=k, mp_context=ctx) as pool:
                walls[k] = list(pool.map(_timed_copy, [n] * k, [chunk] * k, [seed] * k, [barrier] * k))
    alone, together = walls[1][0], walls[copies]
    return {"copies": copies, "items_each": n, "wall_alone_s": alone, "wall_together_s": together,
            "capacity": copies * alone / max(together)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=10_000, help="data sets (items) in the timed study")
    ap.add_argument("--workers", type=int, default=2, help="worker processes of the LocalCluster")
    ap.add_argument("--chunk", type=int, default=None, help="items per task (default: n / (4 workers))")
    ap.add_argument("--warmup", type=int, default=None, help="items of the warm-up study on every process "
                                                               "(default: one chunk)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=ROOT / "reports" / "benchmarks")
    ap.add_argument("--control", type=int, default=1000, help="items per process of the capacity control "
                    "(plain processes without Dask; 0 skips it)")
    args = ap.parse_args()
    enable_compilation_cache()               # as the command line does; the workers enable it themselves
    chunk = args.chunk or max(1, -(-args.n // (4 * args.workers)))
    warmup = args.warmup if args.warmup is not None else chunk
    load_start = os.getloadavg()
    # the cluster first: the driver's peak memory then belongs to it alone (the in-process run's peak is larger)
    there, rows_there = run(Engine(workers=args.workers), args.n, chunk, args.seed, warmup)
    here, rows_here = run(Engine(), args.n, chunk, args.seed, warmup)
    control = capacity(args.workers, args.control, min(chunk, args.control), args.seed) if args.control else None
    same = np.isfinite(rows_here[:, :8]) & np.isfinite(rows_there[:, :8])
    diff = np.abs(rows_here[:, :8] - rows_there[:, :8])[same]
    values = np.abs(rows_here[:, :4][same[:, :4]])
    record = {
        "n": args.n, "workers": args.workers, "chunk": chunk, "warmup_items": warmup, "seed": args.seed,
        "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
                    "load_average_at_start": load_start},
        "in_process": here, "local_cluster": there,
        "speedup": here["wall_s"] / there["wall_s"], "target_speedup": 1.7, "control": control,
        "identical": {"max_abs_difference_um": float(diff.max() * 1e6) if diff.size else 0.0,
                      "max_relative_difference": float(np.max(np.abs(rows_here[:, :4] - rows_there[:, :4])[same[:, :4]]
                                                              / values)) if values.size else 0.0,
                      "bitwise_equal_fraction": float(np.mean(diff == 0.0)) if diff.size else 1.0,
                      "same_failures": bool(np.array_equal(np.isnan(rows_here[:, 0]), np.isnan(rows_there[:, 0])))},
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "scale.json").write_text(json.dumps(record, indent=2))
    md = markdown(record)
    (args.out / "scale.md").write_text(md)
    print(md)


def markdown(r: dict) -> str:
    a, b = r["in_process"], r["local_cluster"]
    ident = r["identical"]

    def la(x):
        return "/".join(f"{v:.2f}" for v in x)

    lines = [
        "# Scale: a Monte Carlo study of mixed designs, in-process vs local worker processes", "",
        f"{r['n']} simulated data sets, each its own design (bias pair, offset, 1-10 iterations, noise, known or "
        f"unknown load, true gap and origin drawn from its seed; {a['rows_min_max'][0]}-{a['rows_min_max'][1]} "
        f"rows), simulated on the virtual rig and fitted by `fit.fit_many` (plain least squares) in tasks of "
        f"{r['chunk']} data sets; {r['warmup_items']} warm-up items on every process first (compilation). "
        f"Machine: {r['machine']['cpu_count']} cores, load average at start {la(r['machine']['load_average_at_start'])} "
        "(1/5/15 min; the machine is shared, so a load above 0 takes cores from this benchmark).", "",
        "| engine | cores | wall [s] | data sets/s | data sets/s/core | simulate CPU [s] | fit CPU [s] | "
        "peak RSS [MB] | load avg before → after |", "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, x in (("in-process", a), (f"LocalCluster, {r['workers']} workers", b)):
        rss = ", ".join(f"{v:.0f}" for v in x["peak_rss_mb"].values())
        lines.append(f"| {name} | {x['cores']} | {x['wall_s']:.1f} | {x['datasets_per_s']:.0f} | "
                     f"{x['datasets_per_s_per_core']:.0f} | {x['simulate_cpu_s']:.1f} | {x['fit_cpu_s']:.1f} | "
                     f"{rss} | {la(x['load_average_before'])} → {la(x['load_average_after'])} |")
    verdict = "meets" if r["speedup"] >= r["target_speedup"] else "misses"
    lines += [
        "", f"Speed-up {r['speedup']:.2f} x with {r['workers']} workers ({verdict} the {r['target_speedup']} x target "
        f"on this machine at this load). Warm-up: {a['warmup_s']:.1f} s in-process, {b['warmup_s']:.1f} s on the "
        "workers (in parallel).",
    ]
    if r.get("control"):
        c = r["control"]
        lines += ["", f"Control without Dask: {c['copies']} plain processes doing {c['items_each']} items each at once "
                  f"take {max(c['wall_together_s']):.1f} s against {c['wall_alone_s']:.1f} s for one alone: this machine "
                  f"gives {c['copies']} processes {c['capacity']:.2f} x the throughput of one, the ceiling of any "
                  f"engine here; the LocalCluster reaches {r['speedup'] / c['capacity']:.0%} of it."]
    lines += [
        "", f"Same seeds, same numbers: largest difference between the engines' estimates and standard errors "
        f"{ident['max_abs_difference_um']:.3g} µm (relative {ident['max_relative_difference']:.3g}); "
        f"{100 * ident['bitwise_equal_fraction']:.1f} % bitwise equal; same failed sets: {ident['same_failures']}.",
        f"Converged: {100 * a['converged_fraction']:.2f} %; fits that raised: {a['failed']} (outlier test off: "
        "plain least squares for every data set).",
        "", "Peak RSS: the driver (in-process: it ran the study itself), then each worker. CPU seconds are summed "
        "over the tasks (`time.process_time` in each task).",
        "", "Rerun: `.venv/bin/python benchmarks/scale.py --n " + str(r["n"]) + f" --workers {r['workers']}`.",
    ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
