"""How long `ambfit diagnose` takes on ~800 readings, and where the time goes.

The data: the rig's rich design enlarged (15 positions, biases 1.0-1.6 A up and down, known and unknown
loads; 840 readings) with iron saturation, as in ``benchmarks/gap_report.py``.  Four timings:

1. ``ambfit diagnose`` in a new process without the compilation cache (``AMBFIT_JAX_CACHE=off``): imports,
   tracing and compiling every candidate model, the fits;
2. the same with the persistent compilation cache filled by a run before (what a second command on this
   machine pays: tracing is not cached, XLA's compilation is);
3. ``ambfit.diagnose`` in this process, first call (compiles) and again (warm: everything compiled), with
   two fits at a time (the default) and with one.

Then where a warm diagnosis spends its time, and how many compiled solves a cold one builds (one per model and
step budget: the ideal law and each candidate).

Then the hard cases (issue "Fast on a real bearing from the first run"), the data of
``tests/test_diagnosis_golden.py``: a magnetic-circuit verdict on the finite-element development data
(``../shared/fem``), a law widened by its signature, a pair, an undecided verdict.  Each: a new
process without and with the compilation cache, a first call in this process, a warm call, the warm call by
phase (the circuit families' refits on their own), the least-squares solves of a warm call by kind of model (the
magnetic circuit's, which solve per reading, and the others': calls, steps, seconds), and where a cold call's time
goes (a new process without the cache: importing ambfit, then the diagnosis' compiling, tracing and the rest).

    .venv/bin/python benchmarks/diagnose_speed.py

Writes reports/benchmarks/diagnose_speed.{json,md}.  Targets (issue "Sim-to-real on physics nobody here
wrote"): <= 10 s from a cold process, <= 1 s warm.
"""

import argparse
import collections
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ambfit import rig
from ambfit.data import read_csv
from ambfit.diagnosis import attribution
from ambfit.estimation import batches
from ambfit.physics import effects as E
from ambfit.rig import protocol

ROOT = Path(__file__).resolve().parents[1]
TARGET_COLD_S, TARGET_WARM_S = 10.0, 1.0


class _Compiles(logging.Handler):
    """JAX's 'Finished XLA compilation of jit(name) in t sec' and 'Finished tracing name for jit in t sec'
    messages (``jax_log_compiles``): counts and seconds by name."""

    def __init__(self):
        super().__init__()
        self.seconds = collections.defaultdict(float)
        self.count = collections.Counter()
        self.tracing = collections.defaultdict(float)

    @classmethod
    def listening(cls) -> "_Compiles":
        """A counter attached to JAX's loggers, with ``jax_log_compiles`` on."""
        import jax

        counter = cls()
        jax.config.update("jax_log_compiles", True)
        for name in ("jax._src.dispatch", "jax._src.interpreters.pxla", "jax"):
            lg = logging.getLogger(name)
            lg.addHandler(counter)
            lg.propagate = False
        return counter

    def emit(self, record):
        msg = record.getMessage()
        if " in " not in msg:
            return
        seconds = float(msg.rsplit(" in ", 1)[1].split()[0])
        if msg.startswith("Finished XLA compilation of "):
            name = msg.removeprefix("Finished XLA compilation of ").split(" in ")[0]
            self.count[name] += 1
            self.seconds[name] += seconds
        elif msg.startswith("Finished tracing "):
            self.tracing[msg.split()[2]] += seconds


def cli_seconds(path: Path, cache: str, bearing: Path | None = None) -> float:
    exe = Path(sys.executable).with_name("ambfit")
    env = {**os.environ, "AMBFIT_JAX_CACHE": cache}
    more = ["--bearing", str(bearing)] if bearing is not None else []
    t0 = time.perf_counter()
    subprocess.run([str(exe), "diagnose", str(path), "--json", str(path.with_suffix(".json")), *more], check=True,
                   capture_output=True, env=env)
    return time.perf_counter() - t0


def phases(data, **kw) -> dict:
    """Seconds of one warm diagnosis by phase, as wall-clock spans of the main thread (the fits run two at a time
    in worker threads): the force checks, the discrepancy, the magnetic circuit's families, and the rest (the ideal
    fit, every candidate's fits and held-out refits, the residual structure)."""
    spent = collections.defaultdict(float)
    wrapped = {}
    for name, label in (("force_checks", "force checks"), ("ceiling", "discrepancy"),
                        ("circuit_families", "circuit families")):
        f = getattr(attribution, name)
        wrapped[name] = f

        def timed(*a, _f=f, _label=label, **k):
            t = time.perf_counter()
            try:
                return _f(*a, **k)
            finally:
                spent[_label] += time.perf_counter() - t

        setattr(attribution, name, timed)
    try:
        t0 = time.perf_counter()
        attribution.diagnose(data, **kw)
        total = time.perf_counter() - t0
    finally:
        for name, f in wrapped.items():
            setattr(attribution, name, f)
    return {"total_s": total, "fits of the ideal law and the candidates": total - sum(spent.values()), **spent}


def one_thread(data, n: int = 3) -> float:
    """Median seconds of a warm diagnosis with one fit at a time (``threads=1``), for comparison."""
    runs = []
    for _ in range(n):
        t0 = time.perf_counter()
        attribution.diagnose(data, threads=1)
        runs.append(time.perf_counter() - t0)
    return float(np.median(runs))


SOLVE_KINDS = ("the magnetic circuit (a solve per reading)", "the other models")


def solves(data, **kw) -> dict:
    """One warm diagnosis with one fit at a time (``threads=1``), its least-squares solves timed by kind of model:
    those that solve per reading (the magnetic circuit) and the others.  Per kind: calls, Levenberg-Marquardt steps
    and the solves' seconds (the compiled program and its dispatch, not the Python of the fit around it)."""
    import jax

    from ambfit.estimation import debias, lm

    spent = {k: {"calls": 0, "steps": 0, "seconds": 0.0} for k in SOLVE_KINDS}
    original = lm.solve

    def timed(theta0, prob, model=lm.IDEAL, *a, **k):
        t = time.perf_counter()
        sol = original(theta0, prob, model, *a, **k)
        jax.block_until_ready(sol.theta)
        s = spent[SOLVE_KINDS[0] if model.flux_width else SOLVE_KINDS[1]]
        s["calls"] += 1
        s["steps"] += int(np.sum(sol.steps))
        s["seconds"] += time.perf_counter() - t
        return sol

    modules = (lm, batches, debias)
    for m in modules:
        m.solve = timed
    try:
        t0 = time.perf_counter()
        attribution.diagnose(data, threads=1, **kw)
        total = time.perf_counter() - t0
    finally:
        for m in modules:
            m.solve = original
    return {"total_s": total, **spent}


def fold_routes(data, n: int = 3) -> dict:
    """Warm median seconds of one model's fold refits by the two routes the core offers: one fit per fold (what
    the diagnosis runs, two at a time on threads) and one batched ``fit_many`` over the fold masks (padded and
    vmapped as a study's data sets are), both without the bias correction as the diagnosis' folds; and the largest
    relative difference of their estimates."""
    from ambfit.diagnosis.heldout import folds
    from ambfit.estimation.fit import fit, fit_many

    df = data.frame.reset_index(drop=True)
    _, tests = folds(df)
    effects = (E.Saturation(),)
    full = fit(df, effects, start_from=fit(df), max_steps=60, throw=False)
    masks = [(~t & full.fitted_rows).astype(float) for t in tests]
    single = lambda: [fit(df, effects, mask=m, start_from=full, max_steps=60, throw=False, alpha=0.0,  # noqa: E731
                          debias="none") for m in masks]
    batched = lambda: fit_many([df] * len(masks), effects, mask=masks, start_from=[full] * len(masks),  # noqa: E731
                               max_steps=60, alpha=0.0, debias="none")
    out = {"folds": len(masks)}
    for name, route in (("one fit per fold", single), ("fit_many over fold masks", batched)):
        route()                                                                     # compiles
        runs = []
        for _ in range(n):
            t0 = time.perf_counter()
            fits = route()
            runs.append(time.perf_counter() - t0)
        out[name] = {"seconds": float(np.median(runs)), "fits": fits}
    a, b = out["one fit per fold"].pop("fits"), out["fit_many over fold masks"].pop("fits")
    out["largest_relative_difference"] = float(max(np.max(np.abs(x.values - y.values) / np.abs(x.values))
                                                   for x, y in zip(a, b)))
    return out


_COLD = """
import sys, time
t0 = time.perf_counter()
from ambfit.diagnosis import attribution
imports = time.perf_counter() - t0
sys.path.insert(0, {here!r})
import json, diagnose_speed
print(json.dumps(diagnose_speed._cold_breakdown({path!r}, {bearing!r}, imports)))
"""


def _cold_breakdown(path: str, bearing: str | None, imports_s: float) -> dict:
    """One diagnosis of ``path`` in this (new) process: its seconds, and the seconds of XLA's compiling and JAX's
    tracing within it (summed over the threads that did them); ``imports_s`` the seconds importing ambfit took
    before."""
    import ambfit

    kw = {"bearing": ambfit.Bearing.from_toml(bearing)} if bearing else {}
    data = read_csv(path)
    counter = _Compiles.listening()
    t0 = time.perf_counter()
    attribution.diagnose(data, **kw)
    return {"imports_s": imports_s, "diagnose_s": time.perf_counter() - t0,
            "compiling_s": sum(counter.seconds.values()), "tracing_s": sum(counter.tracing.values()),
            "compilations": sum(counter.count.values())}


def cold_breakdown(path: Path, bearing: Path | None) -> dict:
    """:func:`_cold_breakdown` in a new process without the compilation cache, importing ambfit timed first."""
    env = {**os.environ, "AMBFIT_JAX_CACHE": "off"}
    code = _COLD.format(here=str(Path(__file__).parent), path=str(path), bearing=None if bearing is None else str(bearing))
    done = subprocess.run([sys.executable, "-c", code], check=True, env=env, capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def hard_cases(tmp: Path) -> dict:
    """Each hard case (the golden diagnoses' data): cold without and with the compilation cache, a cold run's
    breakdown (:func:`cold_breakdown`), first call in this process, warm (median of 3) and its phases."""
    import gzip

    import ambfit

    sys.path.insert(0, str(ROOT / "tests"))
    from test_diagnosis_golden import CASES

    out = {}
    for case, label in (("fem_dev", "magnetic circuit, FEM development data"),
                        ("signature", "a law widened by its signature"), ("pair", "a pair of laws"),
                        ("undecided", "undecided")):
        data_path, bearing_path = CASES[case]
        if not data_path.exists():
            out[case] = {"label": label, "skipped": f"{data_path} is not here"}
            continue
        if data_path.suffix == ".gz":
            plain = tmp / data_path.stem
            plain.write_bytes(gzip.decompress(data_path.read_bytes()))
            data_path = plain
        kw = {"bearing": ambfit.Bearing.from_toml(bearing_path)} if bearing_path is not None else {}
        rec = {"label": label, "cli_no_cache_s": cli_seconds(data_path, "off", bearing_path),
               "cold": cold_breakdown(data_path, bearing_path)}
        cache = str(tmp / f"jax-cache-{case}")
        cli_seconds(data_path, cache, bearing_path)
        rec["cli_filled_cache_s"] = cli_seconds(data_path, cache, bearing_path)
        data = read_csv(data_path)
        t0 = time.perf_counter()
        dg = attribution.diagnose(data, **kw)
        rec["in_process_first_s"] = time.perf_counter() - t0
        rec |= {"rows": len(data.frame), "verdict": dg.verdict}
        runs = sorted((phases(data, **kw) for _ in range(3)), key=lambda r: r["total_s"])
        rec["warm"] = runs[1]
        rec["solves"] = solves(data, **kw)
        out[case] = rec
    return out


def render(out: dict) -> list[str]:
    """The Markdown report of a run's record."""
    c, w = out["compiled"], out["warm"]
    met = lambda v, t: "meets" if v <= t else "misses"  # noqa: E731
    md = ["# `ambfit diagnose` on 840 readings: time and where it goes", "",
          f"Rig data (rich design enlarged, iron saturation; {out['rows']} readings). Verdict {out['verdict']}. "
          f"Load average at start {out['load_average_at_start'][0]:.2f} (2 cores; the machine is shared).", "",
          "| run | seconds | target |", "|---|---|---|",
          f"| `ambfit diagnose`, new process, no compilation cache | {out['cli_no_cache_s']:.1f} | ≤ {TARGET_COLD_S:.0f} "
          f"({met(out['cli_no_cache_s'], TARGET_COLD_S)}) |",
          f"| `ambfit diagnose`, new process, cache filled by an earlier run | {out['cli_filled_cache_s']:.1f} | ≤ "
          f"{TARGET_COLD_S:.0f} ({met(out['cli_filled_cache_s'], TARGET_COLD_S)}) |",
          f"| `ambfit.diagnose`, first call in a process | {out['in_process_first_s']:.1f} | |",
          f"| `ambfit.diagnose`, again (warm, median of 3) | {out['in_process_warm_s']:.2f} | ≤ {TARGET_WARM_S:.0f} "
          f"({met(out['in_process_warm_s'], TARGET_WARM_S)}) |", "",
          f"A cold diagnosis in this process ran {c['all compilations']} XLA compilations ({c['seconds compiling']:.1f} s "
          f"compiling, {c['seconds tracing']:.1f} s tracing); the least-squares solve is one program for the ideal "
          "law and every candidate (`core.compiled_together`: the model evaluated in one place, a switch over the "
          "models, the step budget a traced number).", "",
          "Warm, by phase (wall-clock spans; the fits run two at a time): "
          + ", ".join(f"{k} {v:.2f} s" for k, v in w.items() if k != "total_s")
          + f" (total {w['total_s']:.2f} s). With one fit at a time (`threads=1`): "
          f"{out['in_process_warm_one_thread_s']:.2f} s.", "",
          f"One model's {out['fold_routes']['folds']} fold refits (saturation, warm, median of 3): one fit per fold "
          f"{out['fold_routes']['one fit per fold']['seconds']:.3f} s, one batched `fit_many` over the fold masks "
          f"{out['fold_routes']['fit_many over fold masks']['seconds']:.3f} s (largest relative difference of the "
          f"estimates {out['fold_routes']['largest_relative_difference']:.1e}): the diagnosis runs one fit per fold; "
          f"a batch pads its rows to the next power of two, and its data sets too when they are fewer than "
          f"{batches.BATCH}.", "",
          "## The hard cases", "",
          "The golden diagnoses' data (`tests/test_diagnosis_golden.py`), each in a new process without and with "
          "the compilation cache, first in this process (after the cases above it: some programs are compiled "
          f"already) and warm; targets ≤ {TARGET_COLD_S:.0f} s cold, ≤ 2 s warm.", "",
          "| case | readings | verdict | new process, no cache [s] | with cache [s] | first in process [s] | warm [s] "
          "| warm: fits / circuit families / discrepancy / force checks [s] |", "|---|---|---|---|---|---|---|---|"]
    for case, h in out["hard_cases"].items():
        if "skipped" in h:
            md.append(f"| {h['label']} | – | skipped: {h['skipped']} | | | | | |")
            continue
        hw = h["warm"]
        md.append(f"| {h['label']} | {h['rows']} | {h['verdict']} | {h['cli_no_cache_s']:.1f} | "
                  f"{h['cli_filled_cache_s']:.1f} | {h['in_process_first_s']:.1f} | {hw['total_s']:.2f} | "
                  f"{hw['fits of the ideal law and the candidates']:.2f} / {hw.get('circuit families', 0.0):.2f} / "
                  f"{hw.get('discrepancy', 0.0):.2f} / {hw.get('force checks', 0.0):.2f} |")
    timed = {case: h["solves"] for case, h in out["hard_cases"].items() if "solves" in h}
    if timed:
        md += ["", "Where a warm diagnosis' solves go: one diagnosis with one fit at a time (`threads=1`), its "
               "least-squares solves (the compiled program and its dispatch) timed by kind of model; the rest of "
               "its time is the Python and NumPy around them (problems, outlier tests, held-out scores, the "
               "discrepancy).", "",
               "| case | one fit at a time [s] | " + " | ".join(f"{k}: calls / steps / s / ms per step"
                                                          for k in SOLVE_KINDS) + " |",
               "|---|---|" + "---|" * len(SOLVE_KINDS)]
        for case, t in timed.items():
            cells = [f"{t[k]['calls']} / {t[k]['steps']} / {t[k]['seconds']:.2f} / "
                     f"{1e3 * t[k]['seconds'] / max(t[k]['steps'], 1):.1f}" for k in SOLVE_KINDS]
            md.append(f"| {out['hard_cases'][case]['label']} | {t['total_s']:.2f} | " + " | ".join(cells) + " |")
    cold = {case: h["cold"] for case, h in out["hard_cases"].items() if "cold" in h}
    if cold:
        md += ["", "Where a cold diagnosis' time goes: a new process without the compilation cache, importing ambfit "
               "and then one diagnosis, its XLA compiling and JAX tracing measured within it (seconds summed over the "
               "threads: the fits run two at a time; the rest runs the fits and pays the first calls' dispatch).",
               "",
               "| case | importing [s] | diagnosis [s] | compiling [s] | tracing [s] | the rest [s] | compilations |",
               "|---|---|---|---|---|---|---|"]
        for case, c in cold.items():
            rest = c["diagnose_s"] - c["compiling_s"] - c["tracing_s"]
            md.append(f"| {out['hard_cases'][case]['label']} | {c['imports_s']:.2f} | {c['diagnose_s']:.2f} | "
                      f"{c['compiling_s']:.2f} | {c['tracing_s']:.2f} | {rest:.2f} | {c['compilations']} |")
    md += ["", "Rerun: `.venv/bin/python benchmarks/diagnose_speed.py`."]
    return md


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "reports" / "benchmarks")
    ap.add_argument("--render", action="store_true", help="only rewrite the Markdown from the JSON of a run")
    args = ap.parse_args()
    if args.render:
        md = render(json.loads((args.out / "diagnose_speed.json").read_text()))
        (args.out / "diagnose_speed.md").write_text("\n".join(md) + "\n")
        return
    spec = rig.PAPER_RIG         # the set-points around the bearing's centre, within the back-up clearance
    design = protocol.rich(biases=(1.0, 1.2, 1.4, 1.6), n_positions=15, center=spec.centre)
    sim = rig.simulate(spec, design, [E.Saturation(b_sat=np.asarray(1.15))], seed=5).data
    out = {"rows": len(sim), "load_average_at_start": os.getloadavg()}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "big.csv"
        sim.to_csv(path, index=False)
        out["cli_no_cache_s"] = cli_seconds(path, "off")
        cache = str(Path(tmp) / "jax-cache")
        cli_seconds(path, cache)                                   # fills the cache
        out["cli_filled_cache_s"] = cli_seconds(path, cache)
        data = read_csv(path)

    import jax

    counter = _Compiles.listening()
    t0 = time.perf_counter()
    dg = attribution.diagnose(data)
    out["in_process_first_s"] = time.perf_counter() - t0
    jax.config.update("jax_log_compiles", False)
    out["verdict"] = dg.verdict
    out["compiled"] = {
                       "all compilations": sum(counter.count.values()),
                       "seconds compiling": sum(counter.seconds.values()),
                       "seconds tracing": sum(counter.tracing.values())}
    runs = sorted((phases(data) for _ in range(3)), key=lambda r: r["total_s"])
    out["warm_runs_s"] = [r["total_s"] for r in runs]
    out["warm"] = runs[1]                     # the median of three (the machine is shared)
    out["in_process_warm_s"] = out["warm"]["total_s"]
    out["in_process_warm_one_thread_s"] = one_thread(data)
    out["fold_routes"] = fold_routes(data)
    with tempfile.TemporaryDirectory() as tmp:           # (after the case above: its first call is a first call)
        out["hard_cases"] = hard_cases(Path(tmp))
    out["targets"] = {"cold_s": TARGET_COLD_S, "warm_s": TARGET_WARM_S}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "diagnose_speed.json").write_text(json.dumps(out, indent=2, default=float))

    md = render(out)
    (args.out / "diagnose_speed.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
