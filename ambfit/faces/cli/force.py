"""``ambfit force``: force measurement with a fitted model, the paper's end goal."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from ambfit.faces.cli.app import (
    AcceptOption,
    BearingOption,
    app,
    bearing_of,
    check_output,
    fail,
    judge,
    note,
    show_table,
    warn,
    write_json,
)
from ambfit.faces.cli.explore import Axis
from ambfit.faces.cli.options import number


@app.command()
def force(
    model: Annotated[Path, typer.Argument(help="Fitted model: the JSON of ambfit identify --json (its model_state) "
                                          "or of ambfit diagnose --json (the verdict's model).")],
    data: Annotated[Path | None, typer.Option(help="Readings to measure: contract CSV (axis, i_top_A, i_bottom_A, "
                                              "v_um, w_um; time_s pairs the axes for models that need both "
                                              "axes' currents).")] = None,
    axis: Annotated[Axis | None, typer.Option(help="One reading instead of --data: its axis.")] = None,
    i_top: Annotated[float | None, typer.Option("--i-top", help="Top-coil current [A].")] = None,
    i_bottom: Annotated[float | None, typer.Option("--i-bottom", help="Bottom-coil current [A].")] = None,
    x_um: Annotated[float, typer.Option(help="Position on the reading's axis [µm], sensor coordinates.")] = 0.0,
    y_um: Annotated[float, typer.Option(help="Position on the other axis [µm].")] = 0.0,
    i_top_other: Annotated[float | None, typer.Option("--i-top-other", help="The other axis' top-coil current [A] "
                                                      "(models coupling the axes).")] = None,
    i_bottom_other: Annotated[float | None, typer.Option("--i-bottom-other", help="The other axis' bottom-coil "
                                                         "current [A].")] = None,
    current_noise_ma: Annotated[float, typer.Option("--current-noise-ma", help="Noise of the given currents [mA], "
                                                    "added to the model's error (default: the file's "
                                                    "i_*_std_A columns, else 0).")] = 0.0,
    position_noise_um: Annotated[float, typer.Option(help="Noise of the given positions [µm] (default: the file's "
                                                     "v_std_um/w_std_um, else 0).")] = 0.0,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Write the readings with force_N and "
                                             "force_std_N as CSV here.")] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the forces as JSON here.")] = None,
    use: Annotated[str | None, typer.Option("--use", help="Which model of a diagnose JSON: verdict, discrepancy "
                                            "(with the model-discrepancy correction) or ideal; default: the "
                                            "verdict's, else the discrepancy model, else the ideal law.")] = None,
    accept_implausible: AcceptOption = False,
    bearing: BearingOption = None,
):
    """Force [N] the bearing applies along each reading's axis, with its standard error, from a fitted model.

    The error propagates the model's parameter covariance (every parameter, effects included) and, if
    given, the noise of the readings.  Needs k, i.e. a model fitted with known loads.  The model and the
    readings are judged against the bearing as identify judges them (a k or gap the bearing cannot have,
    currents in mA or beyond the coil limit): exit 3 unless --accept-implausible.
    """
    import numpy as np

    check_output(out, json_out, inputs=(model, data, bearing))
    record, desc, fm = _judged_model(model, bearing, use, accept_implausible)
    from ambfit.estimation import model_file, plausibility

    frame = _readings_frame(data, axis, i_top, i_bottom, x_um, y_um, i_top_other, i_bottom_other)
    flags = plausibility.check_data(frame, desc, str(data) if data is not None else "the reading given")
    if data is None:       # one reading: its position is any number of µm; its currents and load are judged
        flags = [f for f in flags if f.column not in ("v_um", "w_um")]
    judge(flags, accept_implausible, f"{data.name if data is not None else 'the reading'}: the data are")

    try:
        missing_k = model_file.unfitted_k(fm.file, frame["axis"], record)
    except model_file.ModelFileError as exc:
        fail(str(exc))
    if missing_k:
        fail(f"{model}: k_{' and k_'.join(missing_k)} not identified in this model (it was fitted without known "
             "loads on that axis): it gives gap and origin, not forces", 3)
    from ambfit.rows import readings

    if any(getattr(e, "needs_other_axis", False) for e in fm.effects):
        r = readings(frame)
        if not np.isfinite(np.asarray(r.i_top_other)).all():
            fail(f"the {fm.model} model needs both axes' currents at each moment: give rows of both axes sharing "
                 "time_s (or --i-top-other/--i-bottom-other)")
    st, sb, sx = _reading_noise(frame, current_noise_ma, position_noise_um)
    f, s = fm.force(readings(frame), sigma_i=st, sigma_i_bottom=sb, sigma_x=sx)
    if not np.all(np.isfinite(f)):
        bad = int(np.argmax(~np.isfinite(f))) + 1
        fail(f"the model gives no finite force for reading {bad} (a pole gap closed, or a current out of its range)",
             3)
    result = frame.assign(force_N=f, force_std_N=s)
    if data is None:                     # one reading (a second row only carried the other axis' currents)
        result, f, s = result.iloc[:1], f[:1], s[:1]
    shown = result.head(20)
    made = fm.file.provenance()
    version = made["model_ambfit_version"] or "no version recorded"
    show_table([{"#": str(j + 1), "axis": r.axis, "force [N]": _pm(r.force_N, r.force_std_N)}
                for j, r in enumerate(shown.itertuples())], f"force from the {fm.model} model of {model} "
               f"(ambfit {version}), {len(result)} reading(s){', first 20' if len(result) > 20 else ''}")
    if out is not None:
        from ambfit.data import write_csv

        write_csv(result.assign(model_file=str(model), model_ambfit_version=made["model_ambfit_version"]), out)
        note(f"wrote {out}")
    if json_out is not None:
        from ambfit import __version__

        write_json({"model": fm.model, "source": str(model), **made, "bearing": desc.name,
                    "ambfit_version": __version__, "n": len(result),
                    "force_N": [float(v) for v in f], "force_std_N": [float(v) for v in s]}, json_out)


def _judged_model(model: Path, bearing: Path | None, use: str | None, accept: bool):
    """The model file read, checked value by value (exit 2 naming file, key and value), its warnings said and its
    parameters judged against the bearing (exit 3 unless ``accept``): ``(record, bearing, FittedModel)``."""
    import numpy as np

    from ambfit.estimation import plausibility
    from ambfit.estimation.measure import FittedModel, ModelFileError

    record = _read_record(model)
    desc = _bearing(model, record, bearing, use)
    try:
        fm = FittedModel.from_json(record, desc, str(model), use=use)
    except ModelFileError as exc:
        fail(str(exc))
    for line in fm.file.warnings:
        warn(line)
    judge(plausibility.check_result(dict(zip(fm.names, np.asarray(fm.values, float))), desc), accept,
          f"{model.name}: the model is")
    return record, desc, fm


def _read_record(model: Path):
    """The model file's JSON (exit 2 when it cannot be read as JSON)."""
    try:
        return json.loads(Path(model).read_text(encoding="utf-8"))
    except FileNotFoundError:
        fail(f"{model}: no such file")
    except IsADirectoryError:
        fail(f"{model}: is a directory, not a model JSON")
    except UnicodeDecodeError:
        fail(f"{model}: not a model JSON (not UTF-8 text: a binary file?)")
    except (OSError, RecursionError) as exc:
        fail(f"{model}: not a model JSON ({exc})")
    except ValueError as exc:         # bad JSON, or an integer beyond sys.get_int_max_str_digits
        fail(f"{model}: not a model JSON ({str(exc).split(';')[0]})")


def _bearing(model: Path, record, bearing: Path | None, use: str | None):
    """The bearing to measure with: --bearing when given (it must be the one the model was fitted with), else
    the description the model file records, else the paper's rig."""
    from ambfit.estimation import model_file
    from ambfit.physics.bearing import PAPER_BEARING

    try:
        mf = model_file.read(record, str(model), use)
        recorded = model_file.recorded_bearing(mf)
    except model_file.ModelFileError as exc:
        fail(str(exc))
    except ValueError as exc:
        fail(f"--use: {exc}")
    desc = bearing_of(bearing) if bearing is not None else recorded or PAPER_BEARING
    fitted_with = mf.state.get("bearing")
    if fitted_with is not None and fitted_with != desc.name:
        fail(f"{model}: the model was fitted with the bearing {fitted_with!r}, this run describes {desc.name!r}; "
             "give the same --bearing as the fit (forces depend on its turns, pole face and iron)")
    if recorded is not None and (key := model_file.differing_key(recorded, desc)) is not None:
        fail(f"{model}: {mf.key}.bearing_description.{key} = {recorded.to_dict().get(key)!r}, the --bearing "
             f"{bearing} gives {desc.to_dict().get(key)!r}: the model was fitted with another description of "
             "this bearing; give the one it was fitted with")
    return desc


def _reading_noise(frame, current_noise_ma: float, position_noise_um: float):
    """Each reading's noise std [A, A, m]: the options when given, else the file's std columns, else 0."""
    import numpy as np

    n = len(frame)

    def column(name: str, scale: float):
        return np.nan_to_num(frame[name].to_numpy(float) * scale, nan=0.0) if name in frame.columns else np.zeros(n)

    if current_noise_ma:
        st = sb = np.full(n, current_noise_ma * 1e-3)
    else:
        st, sb = column("i_top_std_A", 1.0), column("i_bottom_std_A", 1.0)
    if position_noise_um:
        sx = np.full(n, position_noise_um * 1e-6)
    else:
        sx = np.where(frame["axis"].to_numpy() == "v", column("v_std_um", 1e-6), column("w_std_um", 1e-6))
    return st, sb, sx


def _pm(v, s):
    from ambfit.estimation.units import pm

    return pm(float(v), float(s), 2)


def _readings_frame(data, axis, i_top, i_bottom, x_um, y_um, i_top_other, i_bottom_other):
    """The readings as a contract table: from --data, or one row from the options."""
    import pandas as pd

    from ambfit.data import DataError, check

    if data is not None:
        if axis is not None or i_top is not None:
            fail("give either --data or one reading (--axis, --i-top, --i-bottom, ...), not both")
        from ambfit.data import _read_raw

        try:
            raw = _read_raw(data)
            if "bias_A" not in raw.columns:      # the bias is not needed to measure a force
                raw["bias_A"] = "0"
            return check(raw, source=str(data)).frame
        except DataError as exc:
            fail(str(exc))
    if axis is None or i_top is None or i_bottom is None:
        fail("give --data FILE, or one reading with --axis, --i-top and --i-bottom (and --x-um, --y-um)")
    own, other = ("v", "w") if axis.value == "v" else ("w", "v")
    rows = [{"axis": own, "bias_A": 0.0, "i_top_A": i_top, "i_bottom_A": i_bottom, f"{own}_um": x_um,
             f"{other}_um": y_um, "time_s": 0.0}]
    if i_top_other is not None and i_bottom_other is not None:
        rows.append({"axis": other, "bias_A": 0.0, "i_top_A": i_top_other, "i_bottom_A": i_bottom_other,
                     f"{own}_um": x_um, f"{other}_um": y_um, "time_s": 0.0})
    try:
        return check(pd.DataFrame(rows)).frame
    except DataError as exc:
        fail(str(exc))


@app.command()
def linearise(
    model: Annotated[Path, typer.Argument(help="Fitted model: the JSON of ambfit identify --json or of ambfit "
                                          "diagnose --json (the verdict's model), fitted with known loads.")],
    bias_a: Annotated[float, typer.Option("--bias-a", callback=number(0, low_open=True),
                                          help="The operating bias current [A].")],
    axis: Annotated[Axis | None, typer.Option(help="One axis (default: both).")] = None,
    position_um: Annotated[float | None, typer.Option(help="Where on the axis [µm, sensor coordinates] (default: "
                                                      "the bearing centre, minus the identified origin).")] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write k_i, k_s and their errors as JSON "
                                                  "here.")] = None,
    use: Annotated[str | None, typer.Option("--use", help="Which model of a diagnose JSON: verdict or ideal "
                                            "(default: the verdict's, else the ideal law).")] = None,
    seed: Annotated[int, typer.Option(callback=number(0), help="Seed of the parameter draws behind the "
                                      "errors.")] = 0,
    accept_implausible: AcceptOption = False,
    bearing: BearingOption = None,
):
    """The identified bearing linearised for a rotor model: current gain k_i [N/A] and position stiffness k_s
    [N/m] at a bias, from the model with its effects (saturation lowers both), with their standard errors.

    k_i is the force per control current (top coil at bias + i, bottom at bias - i); k_s the force per
    displacement at the bearing centre (positive: towards the nearer pole; ROSS's MagneticBearingElement ks is
    -k_s).  A rotor model in ROSS: ambfit.rotordynamics.bearing_element (pip install 'ambfit[ross]').
    """
    from ambfit.rotordynamics import linearise as linearised

    check_output(json_out, inputs=(model, bearing))
    if use == "discrepancy":
        fail("--use discrepancy: the discrepancy term is a correction to readings, not a law to differentiate; "
             "use verdict or ideal")
    _, desc, fm = _judged_model(model, bearing, use, accept_implausible)
    if fm.discrepancy is not None:
        note(f"{model}: its discrepancy term is left out (a correction fitted to readings, not a law with "
             "derivatives): k_i and k_s are those of its law")
    if bias_a > desc.max_current:
        fail(f"--bias-a {bias_a:g}: beyond the coil current limit of {desc.max_current:g} A of the bearing "
             f"({desc.name})")
    out = []
    for ax in [axis.value] if axis is not None else ["v", "w"]:
        try:
            out.append(linearised(fm, ax, bias_a, position=None if position_um is None else position_um * 1e-6,
                                  seed=seed))
        except ValueError as exc:
            fail(f"{model}: {exc}", 3)
    show_table([lin.display_row() for lin in out], f"the {out[0].model} model of {model} linearised")
    if json_out is not None:
        from ambfit import __version__

        write_json({"model": out[0].model, "source": str(model), "bearing": desc.name, "ambfit_version": __version__,
                    "axes": [lin.to_json() for lin in out]}, json_out)
