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
    console,
    fail,
    pair,
    parse_effect,
    show_table,
    write_json,
)


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
    bearing: BearingOption = None,
):
    """Simulate a perturbation experiment on the virtual rig and write contract CSV."""
    from ambfit import data as data_mod
    from ambfit import rig
    from ambfit.physics.effects import effect_by_name
    from ambfit.rig import protocol as proto_mod

    check_output(out, truth)

    try:
        effects = [parse_effect(e) for e in (effect or [])]
        spec = rig.RigSpec(bearing=bearing_of(bearing)).with_truth(g0=pair(gap_um, 1e-6), x0=pair(origin_um, 1e-6))
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
                center=pair(center_um, 1e-6), iterations=iterations)
        sim = rig.simulate(spec, proto, effects, rig.Noise(current_noise_ma * 1e-3, position_noise_um * 1e-6),
                           seed=seed)
    except (ValueError, OSError, tomllib.TOMLDecodeError, rig.RigError) as exc:
        fail(str(exc))
    data_mod.write_csv(sim.data, out)
    if truth is not None:
        rig.write_truth(sim.truth, truth)
    console.print(f"wrote {len(sim.data)} rows to {out}")




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
    bearing: BearingOption = None,
):
    """Run the paper's effective-origin search on the virtual rig and print its trajectory."""
    from ambfit import data as data_mod
    from ambfit import rig
    from ambfit.estimation import closed_form
    from ambfit.rig import origin

    check_output(out, truth, json_out)
    try:
        res = origin.search(
            rig.RigSpec(bearing=bearing_of(bearing)), biases=tuple(float(b) for b in biases_a.split(",")),
            offset=offset_um * 1e-6,
            start=pair(start_um, 1e-6), tolerance=tolerance_um * 1e-6, iterations=iterations,
            run_all=not stop_at_tolerance, effects=[parse_effect(e) for e in (effect or [])],
            noise=rig.Noise(current_noise_ma * 1e-3, position_noise_um * 1e-6), seed=seed, experiment=experiment)
    except (ValueError, rig.RigError, closed_form.ClosedFormError) as exc:
        fail(str(exc))
    show_table(res.display_rows(), res.title)
    if out is not None:
        data_mod.write_csv(res.data, out)
        console.print(f"wrote {len(res.data)} rows to {out}")
    if json_out is not None:
        write_json(res.to_json(), json_out)
    if truth is not None:
        rig.write_truth(res.truth, truth)
    if not res.converged:
        raise typer.Exit(1)


