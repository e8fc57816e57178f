"""The ``ambfit`` command line: simulate, identify, origin-search.

Thin by design: it parses options (units in their names and help), calls the
public API and writes files.  Errors in the data or the fit end in a one-line
message and a non-zero exit code, never a traceback.
"""

from __future__ import annotations

import json
import sys
import tomllib
from enum import Enum
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

app = typer.Typer(
    help="Identify active magnetic bearing parameters (effective gap, origin, force constant) from "
    "current-position perturbation data, and simulate a virtual test rig.",
    no_args_is_help=True, add_completion=False, rich_markup_mode=None,  # keep "[mA]" literal in help texts
)
# Wide enough for the identification tables when output is piped (CI logs, files).
console = Console(width=None if sys.stdout.isatty() else 140)
err = Console(stderr=True, width=None if sys.stderr.isatty() else 140)


def _enable_compilation_cache():
    """Persist JAX's compiled fits between runs (``$AMBFIT_JAX_CACHE``, default ``~/.cache/ambfit/jax``):
    a cold ``ambfit identify`` then skips most of its compile time."""
    import os

    import jax

    path = os.environ.get("AMBFIT_JAX_CACHE", os.path.join(os.path.expanduser("~"), ".cache", "ambfit", "jax"))
    if path.lower() in ("", "0", "off", "none"):
        return
    try:
        os.makedirs(path, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", path)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    except OSError:  # read-only home: run without the cache
        pass


def _fail(msg: str, code: int = 2):
    err.print(f"[bold red]error:[/] {msg}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def _parse_effect(text: str):
    """``NAME`` or ``NAME:param=value,param=value`` (SI units) -> Effect."""
    from ambfit.physics.effects import effect_by_name

    name, _, rest = text.partition(":")
    params = {}
    for item in filter(None, rest.split(",")):
        key, sep, val = item.partition("=")
        if not sep:
            raise ValueError(f"effect option {text!r}: expected param=value, got {item!r}")
        params[key.strip()] = float(val)
    return effect_by_name(name.strip(), **params)


BearingOption = Annotated[Path | None, typer.Option(
    "--bearing", help="Bearing description TOML (pole angle, turns, pole area, nominal gap, clearance, current "
                      "limit, ...; DATA-CONTRACT.md section 4). Default: the seed paper's rig.")]


def _bearing(path: Path | None):
    """The bearing description from ``--bearing`` (the paper's rig when not given)."""
    from ambfit.physics.bearing import PAPER_BEARING, Bearing, BearingError

    if path is None:
        return PAPER_BEARING
    try:
        return Bearing.from_toml(path)
    except BearingError as exc:
        _fail(str(exc))


def _pair(text: str | None, scale: float):
    if text is None:
        return None
    parts = [float(p) * scale for p in text.split(",")]
    if len(parts) == 1:
        parts = parts * 2
    if len(parts) != 2:
        raise ValueError(f"expected one value or 'v,w', got {text!r}")
    return tuple(parts)


class Preset(str, Enum):
    table2 = "table2"
    rich = "rich"
    perturbation = "perturbation"


@app.command()
def simulate(
    out: Annotated[Path, typer.Option("--out", "-o", help="CSV file to write (contract format).")],
    preset: Annotated[Preset, typer.Option(help="Protocol: 'table2' (paper's Table 2: 1.4/1.6 A, ±20 µm, "
                                           "10 iterations), 'rich' (biases 1.0-1.6 A up and down, "
                                           "±40 µm, four known loads), or 'perturbation' (built from "
                                           "--biases-a/--offsets-um/--center-um/--iterations).")] = Preset.table2,
    protocol: Annotated[Path | None, typer.Option(help="TOML protocol description (overrides --preset): "
                                                   "[[block]] and [loads.NAME] tables as in "
                                                   "ambfit.rig.protocol.from_dict, plus optional [[effect]] "
                                                   "tables (name = ..., parameters in SI units).")] = None,
    biases_a: Annotated[str, typer.Option("--biases-a", help="Bias currents [A], comma separated.")] = "1.4,1.6",
    offsets_um: Annotated[str, typer.Option(help="Symmetric position offsets [µm], comma separated.")] = "20",
    center_um: Annotated[str, typer.Option(help="Centre of the position pairs 'v,w' [µm].")] = "0,0",
    iterations: Annotated[int, typer.Option(help="Repetitions of the perturbation.")] = 10,
    effect: Annotated[list[str] | None, typer.Option(
        help="Unmodelled effect the rig applies, 'NAME' or 'NAME:param=value,...' in SI units "
             "(repeatable). Names: saturation, iron_reluctance, fringing, leakage, current_offset, "
             "current_gain, position_gain, cross_coupling, hysteresis, thermal_drift.")] = None,
    current_noise_ma: Annotated[float, typer.Option("--current-noise-ma", help="Std of each recorded "
                                                    "current [mA].")] = 0.6,
    position_noise_um: Annotated[float, typer.Option(help="Std of each recorded position [µm].")] = 0.1,
    gap_um: Annotated[str | None, typer.Option(help="True effective gaps 'v,w' [µm] (default: 775,763).")] = None,
    origin_um: Annotated[str | None, typer.Option(help="True origins 'v,w' [µm] (default: 33.3,-11.3).")] = None,
    seed: Annotated[int, typer.Option(help="Seed of the sensor noise.")] = 0,
    truth: Annotated[Path | None, typer.Option(help="Also write the truth (parameters, effects, noise) "
                                               "as JSON here.")] = None,
):
    """Simulate a perturbation experiment on the virtual rig and write contract CSV."""
    from ambfit import data as data_mod
    from ambfit.rig import protocol as proto_mod
    from ambfit import rig

    from ambfit.physics.effects import effect_by_name

    try:
        effects = [_parse_effect(e) for e in (effect or [])]
        spec = rig.PAPER_RIG.with_truth(g0=_pair(gap_um, 1e-6), x0=_pair(origin_um, 1e-6))
        if protocol is not None:
            with open(protocol, "rb") as f:
                desc = tomllib.load(f)
            for e in desc.pop("effect", []):
                e = dict(e)
                effects.append(effect_by_name(e.pop("name", ""), **e))
            proto = proto_mod.from_dict(desc)
        elif preset is Preset.table2:
            proto = proto_mod.paper_table2(iterations)
        elif preset is Preset.rich:
            proto = proto_mod.rich()
        else:
            proto = proto_mod.perturbation(
                [float(b) for b in biases_a.split(",")], [float(o) * 1e-6 for o in offsets_um.split(",")],
                center=_pair(center_um, 1e-6), iterations=iterations)
        sim = rig.simulate(spec, proto, effects, rig.Noise(current_noise_ma * 1e-3, position_noise_um * 1e-6),
                           seed=seed)
    except (ValueError, OSError, tomllib.TOMLDecodeError, rig.RigError) as exc:
        _fail(str(exc))
    data_mod.write_csv(sim.data, out)
    if truth is not None:
        rig.write_truth(sim.truth, truth)
    console.print(f"wrote {len(sim.data)} rows to {out}")


class Method(str, Enum):
    least_squares = "least-squares"
    closed_form = "closed-form"


class By(str, Enum):
    none = "none"
    experiment = "experiment"


def _pm(v, s, fmt):
    return f"{v:{fmt}} ± {s:{fmt}}" if s == s else f"{v:{fmt}}"


def _closed_form_table(result, title: str) -> Table:
    t = Table(title=title)
    for col in ("experiment", "axis", "iterations", "gap [µm]", "origin [µm]", "k [N·m²/A²]", "rejected"):
        t.add_column(col, justify="right" if col not in ("experiment", "axis") else "left")
    for (exp, ax), e in result.estimates.items():
        k = _pm(e.k, e.k_sem, ".3e") if e.k == e.k else "–"
        t.add_row(exp, ax, str(e.n), _pm(e.g0 * 1e6, e.g0_sem * 1e6, ".2f"), _pm(e.x0 * 1e6, e.x0_sem * 1e6, ".2f"),
                  k, str(len(e.rejected)))
    return t


def _ls_table(results: dict, title: str) -> Table:
    """One row per experiment (or 'all'): gap, origin, k of both axes, value ± std; failures say why."""
    from ambfit.estimation.core import FitError

    t = Table(title=title)
    cols = ("experiment", "g_v0 [µm]", "v0 [µm]", "g_w0 [µm]", "w0 [µm]", "k_v [N·m²/A²]", "k_w [N·m²/A²]", "χ²/dof")
    for c in cols:
        t.add_column(c, justify="left" if c == "experiment" else "right")
    for key, res in results.items():
        if isinstance(res, FitError):
            t.add_row(key, f"failed: {res}", *[""] * (len(cols) - 2))
            continue
        cells = []
        for name, scale, fmt in (("g_v0", 1e6, ".2f"), ("v0", 1e6, ".2f"), ("g_w0", 1e6, ".2f"), ("w0", 1e6, ".2f"),
                                 ("k_v", 1.0, ".4e"), ("k_w", 1.0, ".4e")):
            cells.append(_pm(res.value(name) * scale, res.error(name) * scale, fmt) if name in res.names else "–")
        t.add_row(key, *cells, f"{res.reduced_chi2:.2f}")
    return t


@app.command()
def identify(
    data: Annotated[Path, typer.Argument(help="Perturbation data, contract CSV.")],
    method: Annotated[Method, typer.Option(help="Estimator: 'least-squares' (all readings, weighted by their "
                                           "propagated noise; k from known loads) or 'closed-form' (the "
                                           "paper's Eq. 5-7 per iteration, averaged).")] = Method.least_squares,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the contract JSON here.")] = None,
    by: Annotated[By, typer.Option(help="'experiment': one estimate per experiment (like the paper's "
                                   "tables); 'none': one estimate from all rows.")] = By.none,
    current_noise_ma: Annotated[float | None, typer.Option(
        "--current-noise-ma", help="Declared current noise std [mA] (default: the std columns, else "
                                   "estimated from the residuals).")] = None,
    position_noise_um: Annotated[float | None, typer.Option(
        help="Declared position noise std [µm] (default: the std columns, else 0).")] = None,
    require_k: Annotated[bool, typer.Option(help="Fail unless k can be calibrated on every axis "
                                            "(needs known loads).")] = False,
    debias: Annotated[int, typer.Option(help="Subtract the estimator's second-order bias, estimated from this "
                                        "many synthetic data sets of the fitted model (0: off; 2000 is "
                                        "plenty).")] = 0,
    max_position_um: Annotated[float, typer.Option(help="Reject positions at least this large [µm] "
                                                   "(unit check).")] = 762.0,
    bearing: BearingOption = None,
):
    """Identify effective gap, origin (and k when loads are known) for each axis.

    least-squares: value ± standard error from the fit's covariance; exits 3 with the
    reason when the fit does not converge or the design does not identify the
    parameters.  closed-form: mean over iterations ± standard error of that mean.
    """
    from ambfit.data import DataError, read_csv

    _enable_compilation_cache()
    desc = _bearing(bearing)
    try:
        ds = read_csv(data, max_position_um=max_position_um)
    except DataError as exc:
        _fail(str(exc))
    if method is Method.closed_form:
        from ambfit.estimation import closed_form

        try:
            result = closed_form.identify(ds, by_experiment=by is By.experiment, bearing=desc)
        except closed_form.ClosedFormError as exc:
            _fail(str(exc), 3)
        console.print(_closed_form_table(result, f"closed form (Eq. 5-7), {data.name}, {result.n_rows} rows"))
        for (exp, ax), e in result.estimates.items():
            for it, why in e.rejected.items():
                err.print(f"rejected {exp}/{ax} iteration {it}: {why}", highlight=False)
        record = result.to_json()
    else:
        record = _identify_ls(ds, data.name, by, current_noise_ma, position_noise_um, require_k, debias, desc)
    if json_out is not None:
        with open(json_out, "w") as f:
            json.dump(record, f, indent=2)
        console.print(f"wrote {json_out}")
    if not record["converged"]:
        raise typer.Exit(3)


def _identify_ls(ds, name, by, current_noise_ma, position_noise_um, require_k, debias, bearing) -> dict:
    from ambfit.estimation import fit

    kw = dict(sigma_i=None if current_noise_ma is None else current_noise_ma * 1e-3,
              sigma_x=None if position_noise_um is None else position_noise_um * 1e-6, require_k=require_k,
              debias=debias, bearing=bearing)
    try:
        pooled = fit.fit(ds, **kw)
    except fit.FitError as exc:
        if by is By.none:
            _fail(str(exc), 3)
        pooled = exc
    results = {"all": pooled}
    if by is By.experiment:
        results = fit.fit_by(ds, "experiment", **kw)
    console.print(_ls_table(results, f"least squares, {name}, {len(ds)} rows"))
    if not isinstance(pooled, fit.FitError):
        console.print(f"noise: {pooled.noise_source}; start: {pooled.start}; condition {pooled.condition:.3g}; "
                      f"{pooled.weak_direction}", highlight=False)
        if pooled.bias_correction:
            bc = pooled.bias_correction
            console.print("bias correction subtracted (µm): " + ", ".join(
                f"{n} {bc[n]['subtracted'] * 1e6:+.3f} ± {bc[n]['mc_error'] * 1e6:.3f}" for n in ("g_v0", "v0", "g_w0", "w0")
                if n in bc) + f" ({bc['n']} synthetic sets)", highlight=False)
        for ax, ok in pooled.k_identified.items():
            if not ok:
                console.print(f"k_{ax} not identified: no known load on axis {ax} (gap and origin do not need it)",
                              highlight=False)
        for problem in pooled.health():
            err.print(f"[bold yellow]warning:[/] {problem}", highlight=False, soft_wrap=True)
        record = pooled.to_json()
    else:
        record = {"method": "least_squares", "params": {}, "converged": False, "n_rows": len(ds),
                  "error": str(pooled)}
    if by is By.experiment:
        record["experiments"] = {k: (r.to_json() if not isinstance(r, fit.FitError) else
                                     {"converged": False, "error": str(r)}) for k, r in results.items()}
        record["converged"] = record["converged"] and all(not isinstance(r, fit.FitError) for r in results.values())
    return record


@app.command()
def sample(
    data: Annotated[Path, typer.Argument(help="Perturbation data, contract CSV.")],
    out: Annotated[Path | None, typer.Option(help="Write the ArviZ DataTree (posterior, log_likelihood, "
                                             "sample_stats, observed_data) as NetCDF here.")] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the contract JSON (method 'bayes', "
                                                  "94 % HDI, R-hat, ESS) here.")] = None,
    pair_png: Annotated[Path | None, typer.Option(help="Write a pair plot of gap, origin and k here.")] = None,
    steps: Annotated[int, typer.Option(help="Steps per ensemble (at least 50 autocorrelation times).")] = 3000,
    ensembles: Annotated[int, typer.Option(help="Independent emcee ensembles (R-hat compares them).")] = 4,
    walkers: Annotated[int | None, typer.Option(help="Walkers per ensemble (default max(32, 4 x parameters)).")] = None,
    nominal_gap_um: Annotated[float | None, typer.Option(help="Centre the gap prior on this nominal gap [µm] "
                                                          "(log-sd --gap-prior-log-sd).")] = None,
    gap_prior_log_sd: Annotated[float, typer.Option(help="Log-sd of the gap prior [-].")] = 0.3,
    seed: Annotated[int, typer.Option(help="Seed.")] = 0,
    progress: Annotated[bool, typer.Option(help="Show a progress bar.")] = True,
    bearing: BearingOption = None,
):
    """Sample the posterior of gap, origin (and k with known loads) with emcee; summarise with ArviZ.

    Exits 3 when the run is too short for its autocorrelation time (and says how long it
    should be) or R-hat across the ensembles exceeds 1.01.
    """
    from ambfit.estimation import bayes, fit
    from ambfit.data import DataError, read_csv

    _enable_compilation_cache()
    try:
        ds = read_csv(data)
        prior = bayes.Prior(gap=nominal_gap_um * 1e-6 if nominal_gap_um else _bearing(bearing).nominal_gap,
                            gap_log_sd=gap_prior_log_sd)
        res = bayes.sample(ds, prior=prior, n_ensembles=ensembles, n_walkers=walkers, n_steps=steps, seed=seed,
                           progress=progress and sys.stderr.isatty())
    except DataError as exc:
        _fail(str(exc))
    except fit.FitError as exc:
        _fail(str(exc), 3)
    console.print(res.summary().to_string(), highlight=False)
    console.print(res.message, highlight=False)
    record = res.to_json()
    if out is not None:
        res.datatree.to_netcdf(out, engine="h5netcdf")
        console.print(f"wrote {out}")
    if json_out is not None:
        with open(json_out, "w") as f:
            json.dump(record, f, indent=2)
        console.print(f"wrote {json_out}")
    if pair_png is not None:
        from ambfit.faces import plots

        plots.save(plots.plot_pair(res), pair_png)
        console.print(f"wrote {pair_png}")
    if not record["converged"]:
        raise typer.Exit(3)


@app.command("solution-space")
def solution_space_cmd(
    data: Annotated[Path, typer.Argument(help="Perturbation data, contract CSV.")],
    png: Annotated[Path, typer.Option(help="Write the map here (PNG).")],
    axis: Annotated[str, typer.Option(help="Axis: v or w.")] = "v",
    gap_um: Annotated[str, typer.Option(help="Gap range 'low,high' [µm] (the paper's Fig. 2: 600,1000).")] = "600,1000",
    origin_um: Annotated[str, typer.Option(help="Origin range 'low,high' [µm] (Fig. 2: -100,100).")] = "-100,100",
    step_um: Annotated[float, typer.Option(help="Grid step [µm].")] = 1.0,
):
    """Map the misfit over a (gap, origin) grid (the paper's Fig. 2), with the least-squares ellipse
    and the weakest Fisher direction drawn on it."""
    from ambfit.estimation import conditioning, fit
    from ambfit.faces import plots
    from ambfit.data import DataError, read_csv

    try:
        ds = read_csv(data)
        g = _pair(gap_um, 1e-6)
        o = _pair(origin_um, 1e-6)
        sub = ds.frame[ds.frame["axis"] == axis]
        try:
            res = fit.fit(sub)
        except fit.FitError as exc:
            err.print(f"least squares not shown: {exc}", highlight=False)
            res = None
        space = conditioning.solution_space(ds, axis, gap=g, origin=o, step=step_um * 1e-6, weights_at=res)
    except (DataError, ValueError) as exc:
        _fail(str(exc))
    plots.save(plots.plot_solution_space(space, result=res), png)
    gm, xm = space.minimum
    console.print(f"grid {space.chi2.shape[0]} x {space.chi2.shape[1]}; minimum at gap {gm * 1e6:.1f} µm, origin "
                  f"{xm * 1e6:.1f} µm; wrote {png}", highlight=False)


@app.command()
def design(
    data: Annotated[Path, typer.Argument(help="Perturbation data so far, contract CSV.")],
    steps: Annotated[int, typer.Option(help="How many next steps to recommend.")] = 8,
    target: Annotated[str, typer.Option(help="Parameter whose variance to minimise (A-optimal): g_v0, g_w0, "
                                        "v0, w0, k_v, k_w.")] = "g_v0",
    criterion: Annotated[str, typer.Option(help="'A' (variance of the target) or 'D' (log det of gap and "
                                           "origin covariance).")] = "A",
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the recommendation as JSON.")] = None,
    max_radius_um: Annotated[float | None, typer.Option(help="Only set-points within this distance of the "
                                                        "sensor origin [µm] (back-up bearing clearance "
                                                        "less a margin; the paper's rig: 60 µm).")] = None,
):
    """Recommend the next perturbations (set-points [µm], bias [A]) that most reduce the target's uncertainty."""
    from ambfit.estimation import design as design_mod
    from ambfit.estimation import fit
    from ambfit.data import DataError, read_csv

    try:
        rec = design_mod.recommend(read_csv(data), n_steps=steps, target=target, criterion=criterion,
                                   max_radius_um=max_radius_um)
    except DataError as exc:
        _fail(str(exc))
    except (fit.FitError, ValueError) as exc:
        _fail(str(exc), 3)
    unit = 1e6 if target[0] in "gvw" else 1.0
    t = Table(title=f"next steps ({criterion}-optimal for {target}); now ± {rec.std_now * unit:.3g}")
    for c in ("#", "v set [µm]", "w set [µm]", "bias [A]", f"{target} std after"):
        t.add_column(c, justify="right")
    for i, r in enumerate(rec.steps.itertuples(), 1):
        t.add_row(str(i), f"{r.v_set_um:.0f}", f"{r.w_set_um:.0f}", f"{r.bias_A:.2f}",
                  f"{r.predicted_std_after * unit:.3g}")
    console.print(t)
    if json_out is not None:
        with open(json_out, "w") as f:
            json.dump({"target": target, "criterion": criterion, "std_now": rec.std_now,
                       "steps": rec.steps.to_dict(orient="records")}, f, indent=2)


@app.command()
def diagnose(
    data: Annotated[Path, typer.Argument(help="Perturbation data, contract CSV.")],
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the contract section 3 JSON here.")] = None,
    bearing: BearingOption = None,
    pair_verdict: Annotated[bool, typer.Option(help="Let a pair of effects be the verdict when no single one "
                                               "explains the data (off: the pair is reported as best_pair).")] = False,
    report: Annotated[Path | None, typer.Option(help="Write figures here: ranking.png and residuals.png "
                                                "(residuals against the most structured variable, before and "
                                                "after adding the verdict effect).")] = None,
):
    """Where the ideal force model and the data disagree, which unmodelled effect explains it on held-out
    data, how far the gap shrinks, and how the identified parameters differ from the bearing as drawn."""
    from ambfit.data import DataError, read_csv
    from ambfit.diagnosis import diagnose as run_diagnosis
    from ambfit.estimation.core import FitError

    _enable_compilation_cache()
    desc = _bearing(bearing)
    try:
        ds = read_csv(data)
        dg = run_diagnosis(ds, bearing=desc, pair_verdict=pair_verdict)
    except (DataError, ValueError, OSError) as exc:
        _fail(str(exc))
    except FitError as exc:
        _fail(str(exc), 3)
    console.print(dg.summary().split("\n")[0], highlight=False)
    t = Table(title="where the model fails (largest first)")
    for c in ("region", "rows", "z"):
        t.add_column(c, justify="left" if c == "region" else "right")
    for w in dg.where.regions[:8]:
        t.add_row(w.describe(), str(w.rows), f"{w.z:.1f}")
    console.print(t)
    t = Table(title="candidate effects, held-out (best first)")
    for c in ("effect", "held-out excess after", "shrink", "in-sample mean z²"):
        t.add_column(c, justify="left" if c == "effect" else "right")
    for r in dg.to_dataframe().itertuples():
        t.add_row(r.effect, f"{r.heldout_excess_after:.2f}", f"{r.shrink:.3f}", f"{r.insample_mean_z2:.2f}")
    console.print(t)
    console.print(dg.verdict_text(), highlight=False)
    for line in dg.flagged_parameters():
        console.print(line, highlight=False)
    if json_out is not None:
        with open(json_out, "w") as f:
            json.dump(dg.to_json(), f, indent=2)
        console.print(f"wrote {json_out}")
    if report is not None:
        from ambfit.faces import plots

        report.mkdir(parents=True, exist_ok=True)
        plots.save(plots.plot_ranking(dg), report / "ranking.png")
        plots.save(plots.plot_diagnosis_residuals(dg), report / "residuals.png")
        console.print(f"wrote {report / 'ranking.png'} and {report / 'residuals.png'}")


@app.command("origin-search")
def origin_search(
    biases_a: Annotated[str, typer.Option("--biases-a", help="The two bias currents [A].")] = "1.4,1.6",
    offset_um: Annotated[float, typer.Option(help="Half-distance of the symmetric position pair [µm].")] = 20.0,
    start_um: Annotated[str, typer.Option(help="Initial set-point centre 'v,w' [µm].")] = "0,0",
    tolerance_um: Annotated[float, typer.Option(help="Converged when both effective offsets are below "
                                                "this [µm].")] = 1.0,
    iterations: Annotated[int, typer.Option(help="Largest number of iterations.")] = 10,
    stop_at_tolerance: Annotated[bool, typer.Option(help="Stop once converged instead of running all "
                                                    "iterations.")] = False,
    effect: Annotated[list[str] | None, typer.Option(help="Unmodelled effect on the rig (see simulate).")] = None,
    current_noise_ma: Annotated[float, typer.Option("--current-noise-ma", help="Current noise std [mA].")] = 0.6,
    position_noise_um: Annotated[float, typer.Option(help="Position noise std [µm].")] = 0.1,
    seed: Annotated[int, typer.Option(help="Noise seed.")] = 0,
    experiment: Annotated[str, typer.Option(help="Experiment label written to the data.")] = "origin_search",
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Write all readings as contract CSV.")] = None,
    truth: Annotated[Path | None, typer.Option(help="Write the rig's truth as JSON here.")] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the trajectory as JSON.")] = None,
):
    """Run the paper's effective-origin search on the virtual rig and print its trajectory."""
    from ambfit.estimation import closed_form
    from ambfit.rig import origin
    from ambfit import rig
    from ambfit import data as data_mod

    try:
        res = origin.search(
            rig.PAPER_RIG, biases=tuple(float(b) for b in biases_a.split(",")), offset=offset_um * 1e-6,
            start=_pair(start_um, 1e-6), tolerance=tolerance_um * 1e-6, iterations=iterations,
            run_all=not stop_at_tolerance, effects=[_parse_effect(e) for e in (effect or [])],
            noise=rig.Noise(current_noise_ma * 1e-3, position_noise_um * 1e-6), seed=seed, experiment=experiment)
    except (ValueError, rig.RigError, closed_form.ClosedFormError) as exc:
        _fail(str(exc))
    t = Table(title=f"effective-origin search ({'converged at iteration ' + str(res.converged_at) if res.converged else 'not converged'})")
    for col in ("it", "v centre", "v offset", "g_v0", "w centre", "w offset", "g_w0"):
        t.add_column(col + (" [µm]" if col != "it" else ""), justify="right")
    for j in range(res.n_iterations):
        t.add_row(str(j + 1), *(f"{a * 1e6:.2f}" for a in (res.centers[j, 0], res.offsets[j, 0], res.g0[j, 0],
                                                           res.centers[j, 1], res.offsets[j, 1], res.g0[j, 1])))
    console.print(t)
    if out is not None:
        data_mod.write_csv(res.data, out)
        console.print(f"wrote {len(res.data)} rows to {out}")
    if json_out is not None:
        with open(json_out, "w") as f:
            json.dump(res.to_json(), f, indent=2)
    if truth is not None:
        rig.write_truth(res.truth, truth)
    if not res.converged:
        raise typer.Exit(1)


@app.command()
def report(
    data: Annotated[Path, typer.Argument(help="Perturbation data, contract CSV.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for index.html (self-contained, figures "
                                      "embedded) and report.json.")],
    steps: Annotated[int, typer.Option(help="emcee steps per ensemble for the posterior.")] = 3000,
    ensembles: Annotated[int, typer.Option(help="Independent emcee ensembles (R-hat across them).")] = 4,
    design_steps: Annotated[int, typer.Option(help="How many next perturbations to recommend.")] = 8,
    max_radius_um: Annotated[float | None, typer.Option(help="Recommend only set-points within this distance "
                                                        "of the sensor origin [µm] (back-up bearing clearance "
                                                        "less a margin).")] = 50.0,
    bearing: BearingOption = None,
    posterior: Annotated[bool, typer.Option(help="Sample the posterior (the slowest section).")] = True,
    diagnosis: Annotated[bool, typer.Option(help="Run the sim-to-real gap diagnosis.")] = True,
    seed: Annotated[int, typer.Option(help="Sampler seed.")] = 0,
):
    """One self-contained HTML page: identification table, posterior summary and pair plot, solution-space
    map, design recommendation and diagnosis."""
    from ambfit.faces import report as report_mod
    from ambfit.data import DataError

    _enable_compilation_cache()
    try:
        path, rec = report_mod.data_report(
            data, out, steps=steps, ensembles=ensembles, design_steps=design_steps, bearing=_bearing(bearing),
            max_radius_um=max_radius_um, do_posterior=posterior, do_diagnosis=diagnosis, seed=seed,
            command="ambfit report " + " ".join(sys.argv[2:]))
    except (DataError, OSError) as exc:
        _fail(str(exc))
    console.print(f"wrote {path}")
    if "error" in rec["least_squares"]:   # the page says why; the exit code says it to scripts
        raise typer.Exit(3)


@app.command()
def paper(
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the reproduction report.")] = Path(
        "reports/paper"),
    replicates: Annotated[int, typer.Option(help="Repetitions of every experiment for the predicted spreads "
                                            "(about 1.3 s each).")] = 200,
    seed: Annotated[int, typer.Option(help="Seed of the reproduction and the replicates.")] = 0,
    demonstration: Annotated[bool, typer.Option(help="Also simulate which effect explains the paper's gap "
                                                "excess and what separates the candidates (about 25 s).")] = True,
):
    """Rerun the seed paper's Tables 1-4 and Figs. 2, 3 and 5 on the virtual rig; write the side-by-side
    report (index.html, README.md, comparison.csv, spread.csv, reproduction.json, PNG figures)."""
    from ambfit.faces import report as report_mod

    _enable_compilation_cache()
    path = report_mod.paper_report(out, replicates=replicates, seed=seed, demonstration=demonstration,
                                   command="ambfit paper " + " ".join(sys.argv[2:]), progress=sys.stderr.isatty())
    console.print(f"wrote {path}")
    # the summary and the spread table (paper vs prediction); every row of Tables 1-4 is in the report
    console.print((Path(out) / "README.md").read_text().split("## Table 1")[0], highlight=False)


def main():  # pragma: no cover - entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
