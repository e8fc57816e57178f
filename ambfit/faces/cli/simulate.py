"""``ambfit simulate`` and ``ambfit origin-search``: the virtual test rig."""

from __future__ import annotations

import tomllib
from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from ambfit.faces.cli.app import (
    BearingOption,
    app,
    bearing_of,
    check_output,
    fail,
    note,
    pair,
    parse_effect,
    show_table,
    warn,
    write_json,
)
from ambfit.faces.cli.options import number, numbers, text

# Longest runs the rig is asked for: far beyond any experiment (the paper ran 10 iterations), short of a run that
# would fill the memory.
MAX_ITERATIONS = 10_000
MAX_SEARCH_ITERATIONS = 1_000
MAX_LEVELS = 100
"""Values of ``--biases-a`` or ``--offsets-um``: every bias meets every offset and iteration, so the steps grow as
their product."""
MAX_STEPS = 1_000_000
"""Steps one simulation may write (two readings each: 2 million rows, about 400 MB of CSV)."""


class Preset(str, Enum):
    table2 = "table2"
    rich = "rich"
    perturbation = "perturbation"


@app.command()
def simulate(
    out: Annotated[Path, typer.Option("--out", "-o", help="CSV file to write (contract format).")],
    preset: Annotated[Preset, typer.Option(help="Protocol: 'table2' (paper's Table 2: 1.4/1.6 A, ±20 µm, "
                                           "10 iterations), 'rich' (biases 1.0-1.6 A up and down on the paper's 3 A bearing, "
                                           "scaled to the --bearing's current limit, "
                                           "± two thirds of the back-up clearance (40 µm on the paper's rig), "
                                           "four known loads), or 'perturbation' (built from "
                                           "--biases-a/--offsets-um/--iterations); each centred on "
                                           "--center-um.")] = Preset.table2,
    protocol: Annotated[Path | None, typer.Option(help="TOML protocol description (overrides --preset): "
                                                   "[[block]] and [loads.NAME] tables as in "
                                                   "ambfit.rig.protocol.from_dict, plus optional [[effect]] "
                                                   "tables (name = ..., parameters in SI units).")] = None,
    biases_a: Annotated[str, typer.Option("--biases-a", callback=numbers(0, low_open=True),
                                          help="Bias currents [A], comma separated.")] = "1.4,1.6",
    offsets_um: Annotated[str, typer.Option(callback=numbers(0, low_open=True),
                                            help="Symmetric position offsets [µm], comma separated.")] = "20",
    center_um: Annotated[str, typer.Option(callback=numbers(count=(1, 2), also=("origin",)),
                                           help="Centre of the preset's set-points 'v,w' [µm, sensor "
                                           "coordinates], or 'origin': the rig's effective origin (-v0, -w0), "
                                           "where the paper's origin search puts them (its Table 2 ran there), "
                                           "so the rotor moves about the bearing centre.")] = "origin",
    iterations: Annotated[int, typer.Option(callback=number(1, MAX_ITERATIONS),
                                            help="Repetitions of the perturbation.")] = 10,
    effect: Annotated[list[str] | None, typer.Option(
        help="Unmodelled effect the rig applies, 'NAME' or 'NAME:param=value,...' in SI units "
             "(repeatable). Names: saturation, iron_reluctance, fringing, leakage, current_offset, "
             "current_gain, position_gain, cross_coupling, hysteresis, thermal_drift.")] = None,
    current_noise_ma: Annotated[float, typer.Option("--current-noise-ma", callback=number(0),
                                                    help="Std of each recorded current [mA].")] = 0.6,
    position_noise_um: Annotated[float, typer.Option(callback=number(0),
                                                     help="Std of each recorded position [µm].")] = 0.1,
    gap_um: Annotated[str | None, typer.Option(callback=numbers(0, low_open=True, count=(1, 2)),
                                               help="True effective gaps 'v,w' [µm] (default: the paper rig's "
                                               "775,763 on its 762 µm drawing, scaled to the bearing's nominal "
                                               "gap).")] = None,
    origin_um: Annotated[str | None, typer.Option(callback=numbers(count=(1, 2)),
                                                  help="True origins 'v,w' [µm] (default: 33.3,-11.3).")] = None,
    seed: Annotated[int, typer.Option(callback=number(0), help="Seed of the sensor noise.")] = 0,
    truth: Annotated[Path | None, typer.Option(help="Also write the truth (parameters, effects, noise) "
                                               "as JSON here.")] = None,
    temperature: Annotated[bool, typer.Option(
        "--temperature/--no-temperature", help="Record the bearing temperature (temperature_C). Without it a "
                                               "thermal_drift acts through time (its rates dg_dt, dx0_dt [m/s]), "
                                               "as on a rig with a clock but no thermometer.")] = True,
    allow_beyond_limits: Annotated[bool, typer.Option(
        "--allow-beyond-limits", help="Run steps that put the rotor beyond the bearing's back-up clearance (from "
                                      "the bearing centre: set-point plus the rig's true origin) or drive a coil "
                                      "beyond its current limit (--bearing); refused by default.")] = False,
    bearing: BearingOption = None,
):
    """Simulate a perturbation experiment on the virtual rig and write contract CSV.

    Refuses (exit 2, naming the step) a protocol that would put the rotor beyond the bearing's back-up clearance
    or drive a coil beyond its current limit, as an operator of a real rig would; --allow-beyond-limits runs it.
    """
    from ambfit import data as data_mod
    from ambfit import rig
    from ambfit.rig import protocol as proto_mod

    check_output(out, truth, inputs=(protocol, bearing))
    desc = bearing_of(bearing)
    effects = effects_of(effect, desc)
    try:
        spec = rig.RigSpec.for_bearing(desc).with_truth(g0=pair(gap_um, 1e-6), x0=pair(origin_um, 1e-6))
        center = spec.centre if center_um.strip().lower() == "origin" else pair(center_um, 1e-6)
        if protocol is not None:
            proto, more = protocol_of(protocol, desc)
            effects += more
        elif preset is Preset.table2:
            proto = proto_mod.paper_table2(iterations, center=center, loads=spec.loads)
        elif preset is Preset.rich:
            # ±40 µm on the paper's 60 µm clearance: two thirds of the bearing's, so the sweep stays within it
            # the biases scaled to the bearing's coil limit (1.0-1.6 A of the paper's 3 A: a third to over half)
            scale = desc.max_current / rig.PAPER_RIG.bearing.max_current
            proto = proto_mod.rich(biases=tuple(b * scale for b in (1.0, 1.2, 1.4, 1.6)), center=center,
                                   rotor_kg=desc.rotor_mass, span=desc.backup_clearance * 2 / 3)
        else:
            biases, offsets = biases_a.split(","), offsets_um.split(",")
            for option, values in (("--biases-a", biases), ("--offsets-um", offsets)):
                if len(values) > MAX_LEVELS:
                    fail(f"{option}: {len(values)} values; at most {MAX_LEVELS} (every one meets every other "
                         "option's value and every iteration: the steps grow as their product)")
            proto = proto_mod.perturbation(
                [float(b) for b in biases], [float(o) * 1e-6 for o in offsets],
                center=center, iterations=iterations, loads=spec.loads)
        if (n := len(proto.v_set)) > MAX_STEPS:
            fail(f"the protocol has {n:,} steps ({2 * n:,} readings, about {n * 400 / 1e6:,.0f} MB of CSV); at most "
                 f"{MAX_STEPS:,}: fewer iterations, biases or offsets")
        within_limits(spec, proto, effects, allow_beyond_limits)
        sim = rig.simulate(spec, proto, effects, rig.Noise(current_noise_ma * 1e-3, position_noise_um * 1e-6),
                           seed=seed, thermometer=temperature)
        within_limits(spec, proto, effects, allow_beyond_limits, sim.physical_currents)
    except (ValueError, OSError, tomllib.TOMLDecodeError, rig.RigError) as exc:
        fail(str(exc))
    data_mod.write_csv(sim.data, out)
    if truth is not None:
        rig.write_truth(sim.truth, truth)
    note(f"wrote {len(sim.data)} rows to {out}")


def effects_of(texts: list[str] | None, bearing=None) -> list:
    """The ``--effect`` options as effects (facts of the bearing, the iron path, from ``bearing``); a bad one exits
    2 naming it."""
    out = []
    for t in texts or []:
        try:
            out.append(parse_effect(t, bearing))
        except ValueError as exc:
            fail(f"--effect {t}: {exc}")
    return out


def protocol_of(path: Path, bearing):
    """The ``--protocol`` TOML as a protocol (loads from ``bearing``'s rotor mass) and its ``[[effect]]`` tables
    (facts of the bearing from it); a bad file exits 2 naming it."""
    from ambfit.physics.effects import effect_by_name
    from ambfit.rig import protocol as proto_mod

    try:
        with open(path, "rb") as f:
            desc = tomllib.load(f)
    except OSError as exc:
        fail(f"--protocol {path}: cannot be read ({exc.strerror})")
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        fail(f"--protocol {path}: not a TOML file ({exc})")
    except RecursionError:
        fail(f"--protocol {path}: not a protocol (its tables or arrays nest too deeply to read)")
    except ValueError as exc:                 # an integer beyond sys.get_int_max_str_digits
        fail(f"--protocol {path}: not a protocol ({str(exc).split(';')[0]})")
    try:
        effects = []
        for e in desc.pop("effect", []):
            e = dict(e)
            effects.append(effect_by_name(e.pop("name", ""), bearing=bearing, **e))
        return proto_mod.from_dict(desc, rotor_kg=bearing.rotor_mass), effects
    except KeyError as exc:
        fail(f"--protocol {path}: a table lacks the key {exc} (see ambfit.rig.protocol.from_dict for the keys)")
    except (ValueError, TypeError, AttributeError) as exc:    # (AttributeError: a table where a value belongs)
        fail(f"--protocol {path}: {exc}; a table or a value of the wrong kind (see ambfit.rig.protocol.from_dict)")


def within_limits(spec, proto, effects, allow: bool, currents=None):
    """Refuse (exit 2) a protocol beyond the bearing's back-up clearance or coil current limit, naming the first
    step, its set-point and how far it goes; with ``allow``, warn instead."""
    from ambfit.rig.limits import limit_violations

    found = limit_violations(spec, proto, effects, currents)
    if currents is not None:       # the set-points and biases were judged before the run
        found = [v for v in found if v.kind == "current"]
    if not found:
        return
    steps = sorted({v.step for v in found})
    limits = {"clearance": "the back-up clearance", "bias": "the coil current limit", "current": "the coil current limit"}
    kinds = " and ".join(dict.fromkeys(limits[v.kind] for v in found))
    text = (f"{found[0]}; {len(steps)} of {len(proto)} steps go beyond {kinds} of the bearing "
            f"({spec.bearing.name})")
    if allow:
        warn(f"{text}; run anyway (--allow-beyond-limits)")
        return
    hint = ("centre the set-points on the effective origin (--center-um origin, the default), use smaller offsets, "
            if any(v.kind == "clearance" for v in found) else "use lower biases or loads, ")
    fail(f"{text}. A real rig would put the rotor on its back-up bearing or overload its coils: {hint}give the "
         "bearing's real limits (--bearing), or run it anyway with --allow-beyond-limits")


@app.command("origin-search")
def origin_search(
    biases_a: Annotated[str, typer.Option("--biases-a", callback=numbers(0, low_open=True, count=(2,)),
                                          help="The two bias currents [A].")] = "1.4,1.6",
    offset_um: Annotated[float, typer.Option(callback=number(0, low_open=True),
                                             help="Half-distance of the symmetric position pair [µm].")] = 20.0,
    start_um: Annotated[str, typer.Option(callback=numbers(count=(1, 2)),
                                          help="Initial set-point centre 'v,w' [µm].")] = "0,0",
    tolerance_um: Annotated[float, typer.Option(callback=number(0, low_open=True),
                                                help="Converged when both effective offsets are below "
                                                "this [µm].")] = 1.0,
    iterations: Annotated[int, typer.Option(callback=number(1, MAX_SEARCH_ITERATIONS),
                                            help="Largest number of iterations.")] = 10,
    stop_at_tolerance: Annotated[bool, typer.Option(help="Stop once converged instead of running all "
                                                    "iterations.")] = False,
    effect: Annotated[list[str] | None, typer.Option(help="Unmodelled effect on the rig (see simulate).")] = None,
    current_noise_ma: Annotated[float, typer.Option("--current-noise-ma", callback=number(0),
                                                    help="Current noise std [mA].")] = 0.6,
    position_noise_um: Annotated[float, typer.Option(callback=number(0), help="Position noise std [µm].")] = 0.1,
    seed: Annotated[int, typer.Option(callback=number(0), help="Noise seed.")] = 0,
    experiment: Annotated[str, typer.Option(callback=text,
                                            help="Experiment label written to the data.")] = "origin_search",
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Write all readings as contract CSV.")] = None,
    truth: Annotated[Path | None, typer.Option(help="Write the rig's truth as JSON here.")] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the trajectory as JSON.")] = None,
    allow_beyond_limits: Annotated[bool, typer.Option(
        "--allow-beyond-limits", help="Start even when the first position pair puts the rotor beyond the "
                                      "bearing's back-up clearance or a bias beyond its coil current limit.")] = False,
    bearing: BearingOption = None,
):
    """Run the paper's effective-origin search on the virtual rig and print its trajectory.

    Refuses (exit 2) a first position pair beyond the bearing's back-up clearance (the search then moves
    towards the bearing centre) unless --allow-beyond-limits.
    """
    from ambfit import data as data_mod
    from ambfit import rig
    from ambfit.estimation import closed_form
    from ambfit.faces.cli.progress import progress_bar
    from ambfit.rig import protocol as proto_mod
    from ambfit.studies import origin

    check_output(out, truth, json_out, inputs=(bearing,))
    biases = tuple(float(b) for b in biases_a.split(","))
    if biases[0] == biases[1]:
        fail(f"--biases-a {biases_a}: the two biases must differ (Eq. 6 compares them)")
    spec = rig.RigSpec.for_bearing(bearing_of(bearing))
    effects = effects_of(effect, spec.bearing)
    try:
        first = proto_mod.perturbation(biases, (offset_um * 1e-6,), center=pair(start_um, 1e-6))
        within_limits(spec, first, effects, allow_beyond_limits)
        with progress_bar() as bar:
            res = origin.search(
                spec, biases=biases, offset=offset_um * 1e-6, start=pair(start_um, 1e-6),
                tolerance=tolerance_um * 1e-6, iterations=iterations, run_all=not stop_at_tolerance,
                effects=effects, noise=rig.Noise(current_noise_ma * 1e-3, position_noise_um * 1e-6), seed=seed,
                experiment=experiment, progress=bar)
    except (ValueError, rig.RigError, closed_form.ClosedFormError) as exc:
        fail(str(exc))
    show_table(res.display_rows(), res.title)
    if out is not None:
        data_mod.write_csv(res.data, out)
        note(f"wrote {len(res.data)} rows to {out}")
    if json_out is not None:
        write_json(res.to_json(), json_out)
    if truth is not None:
        rig.write_truth(res.truth, truth)
    if not res.converged:
        raise typer.Exit(1)


