"""Force measurement as a product: the fitted model's JSON, ``ambfit force``, leave-one-load-out checks,
and the axis pairing and magnetic circuit the force needs on a real bearing."""

import dataclasses
import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

import ambfit
from ambfit.data import read_csv
from ambfit.estimation.core import Model
from ambfit.estimation.measure import FittedModel, force_check, predict
from ambfit.faces.cli import app
from ambfit.physics.effects import MagneticCircuit, Saturation
from ambfit.physics.model import BearingParams, Readings, evaluate, ideal_force
from ambfit.rows import other_axis_currents, readings

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT / "data" / "paper_table2.csv"
runner = CliRunner()


@pytest.fixture(scope="module")
def table2():
    return read_csv(DEFAULT)


@pytest.fixture(scope="module")
def table2_fit(table2):
    return ambfit.fit(table2)


def test_rows_of_both_axes_read_at_one_moment_are_paired():
    df = pd.DataFrame({"axis": ["v", "w", "v", "w", "v"], "i_top_A": [1.0, 2.0, 3.0, 4.0, 5.0],
                       "i_bottom_A": [0.1, 0.2, 0.3, 0.4, 0.5], "time_s": [1.0, 1.0, 2.0, 2.0, 3.0],
                       "experiment": ["a", "a", "a", "a", "a"]})
    it, ib = other_axis_currents(df)
    np.testing.assert_array_equal(it[:4], [2.0, 1.0, 4.0, 3.0])
    np.testing.assert_array_equal(ib[:4], [0.2, 0.1, 0.4, 0.3])
    assert np.isnan(it[4]) and np.isnan(ib[4])                    # no w row at t = 3
    df["experiment"] = ["a", "b", "a", "a", "a"]                  # another experiment's row is not a partner
    assert np.isnan(other_axis_currents(df)[0][0])


def test_shared_effect_parameters_are_one_number_for_both_axes():
    m = Model.of([MagneticCircuit(), Saturation()])
    names = m.names()
    assert names[:4] == ["magnetic_circuit.fringe_depth", "magnetic_circuit.leakage", "magnetic_circuit.iron_scale",
                         "magnetic_circuit.pole_area_ratio"]
    assert names[4:] == ["saturation.b_sat[v]", "saturation.b_sat[w]", "saturation.sharpness[v]",
                         "saturation.sharpness[w]"]
    mec = m.build(np.eye(m.n)[0])[0]                                   # q = 1 on the first parameter only
    lo, hi = MagneticCircuit.RANGES["fringe_depth"]
    np.testing.assert_allclose(np.asarray(mec.fringe_depth), [0.5 * (lo + hi) + (hi - lo)] * 2)
    # a piece switched off keeps the parameter vector (one compiled fit for every variant) and says so
    off = MagneticCircuit().without("fringing").without("coupling")
    assert Model.of([off]).names() == Model.of([MagneticCircuit()]).names()
    assert off.off == ("fringing", "coupling")


def test_the_circuit_with_every_piece_off_is_the_ideal_law():
    b = ambfit.PAPER_BEARING
    mec = MagneticCircuit()
    for piece in MagneticCircuit.PIECES:
        mec = mec.without(piece)
    r = Readings.build(axis=[0, 1, 0], i_top=[1.6, 1.5, 2.0], i_bottom=[1.2, 1.4, 0.5], x=[20e-6, -10e-6, 0.0],
                       y=[-5e-6, 20e-6, 30e-6], i_top_other=[1.5, 1.6, 1.4], i_bottom_other=[1.4, 1.2, 1.4])
    params = BearingParams.from_values([775e-6, 763e-6], [33e-6, -11e-6], b.force_constant())
    f = np.asarray(evaluate(params, r, [mec], bearing=b)[0])
    ref = np.asarray(ideal_force(np.array([775e-6, 763e-6, 775e-6]), np.array([33e-6, -11e-6, 33e-6]),
                                 b.force_constant(), np.asarray(r.i_top), np.asarray(r.i_bottom), np.asarray(r.x),
                                 b.cos_alpha))
    np.testing.assert_allclose(f, ref, rtol=1e-8)


def test_fitted_model_round_trip_gives_the_fits_force_and_error(table2, table2_fit):
    state = json.loads(json.dumps(table2_fit.to_json()))            # through JSON, as ambfit force reads it
    fm = FittedModel.from_json(state, ambfit.PAPER_BEARING)
    f, s = fm.force(readings(table2))
    np.testing.assert_allclose(f, predict(table2_fit, table2), rtol=1e-12)
    row = table2.frame.iloc[0]
    f1, s1 = ambfit.force(table2_fit, "v", row.i_top_A, row.i_bottom_A, row.v_um * 1e-6, y=row.w_um * 1e-6)
    assert f[0] == pytest.approx(float(f1), rel=1e-12) and s[0] == pytest.approx(float(s1), rel=1e-9)
    # the force reproduces the known load within its error (the data are equilibria at that load)
    assert abs(f[0] - row.load_N) < 4 * np.hypot(s[0], 0.01)


def test_force_check_leaves_each_known_load_out():
    from ambfit.rig import protocol
    from ambfit.rig import virtual as rig

    sim = rig.simulate(rig.PAPER_RIG, protocol.rich(), seed=4)
    fc = force_check(sim.data)
    assert fc["method"] == "leave-one-load-out" and fc["n_loads"] == len(fc["loads"]) >= 4
    # the ideal law on ideal-rig data: the force of readings the fit never saw, to a fraction of a percent
    assert fc["rms_rel"] < 0.005 and fc["max_rel"] < 0.03
    # the right model: the per-reading error is the readings' noise, nothing beyond it to speak of; the model's
    # own error is what is left of the RMS over that floor in quadrature
    assert 0.8 * fc["noise_floor_rel"] < fc["rms_rel"] < 1.2 * fc["noise_floor_rel"]
    assert fc["model_error_rel"] == pytest.approx(np.sqrt(max(fc["rms_rel"] ** 2 - fc["noise_floor_rel"] ** 2, 0)))
    assert fc["model_error_rel"] < 0.6 * fc["noise_floor_rel"]
    one = sim.data.assign(load_N=np.where(sim.data["axis"] == "v", 5.0, 2.0))
    assert force_check(one[one.axis == "v"]) is None                   # one known load: nothing to leave out


def test_force_check_over_threads_is_the_same_check():
    # A diagnosis spreads the left-out loads over its threads (each): the same refits, in the loads' order
    from concurrent.futures import ThreadPoolExecutor

    from ambfit.rig import protocol
    from ambfit.rig import virtual as rig

    sim = rig.simulate(rig.PAPER_RIG, protocol.rich(), seed=4)
    base = ambfit.fit(sim.data)
    with ThreadPoolExecutor(2) as pool:
        spread = force_check(sim.data, base=base, each=lambda fn, items: list(pool.map(fn, items)))
    assert spread == force_check(sim.data, base=base)          # per-load records too, in the loads' order


def test_force_command_single_reading_and_file(tmp_path, table2_fit):
    model = tmp_path / "m.json"
    model.write_text(json.dumps(table2_fit.to_json()))
    r = runner.invoke(app, ["force", str(model), "--axis", "v", "--i-top", "1.6", "--i-bottom", "1.2",
                            "--x-um", "10", "--json", str(tmp_path / "f.json")])
    assert r.exit_code == 0, r.output
    f, s = ambfit.force(table2_fit, "v", 1.6, 1.2, 10e-6)
    js = json.loads((tmp_path / "f.json").read_text())
    assert js["force_N"][0] == pytest.approx(float(f), rel=1e-12)
    assert js["force_std_N"][0] == pytest.approx(float(s), rel=1e-9)
    out = tmp_path / "forces.csv"
    r = runner.invoke(app, ["force", str(model), "--data", str(DEFAULT), "--out", str(out)])
    assert r.exit_code == 0, r.output
    got = pd.read_csv(out)
    assert len(got) == 80 and {"force_N", "force_std_N", "load_N", "experiment"} <= set(got.columns)
    # the error uses the file's std columns: against the known load the pulls are about unit (only the
    # parameters' covariance gave pulls of ~11 on the FEM file)
    pull = (got.force_N - got.load_N) / got.force_std_N
    assert 0.6 < np.sqrt(np.mean(pull**2)) < 1.6
    other = tmp_path / "other.toml"
    other.write_text('name = "another bearing"\nturns_per_pole = 160\n')
    r = runner.invoke(app, ["force", str(model), "--axis", "v", "--i-top", "1.6", "--i-bottom", "1.2",
                            "--bearing", str(other)])
    assert r.exit_code == 2 and "fitted with the bearing 'paper rig'" in r.output


def test_force_command_errors(tmp_path, table2):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    r = runner.invoke(app, ["force", str(bad), "--axis", "v", "--i-top", "1", "--i-bottom", "1"])
    assert r.exit_code == 2 and "not a model JSON" in r.output
    no_k = tmp_path / "nok.json"
    nok = ambfit.fit(table2.frame.drop(columns=["load_N"]))
    no_k.write_text(json.dumps(nok.to_json()))
    r = runner.invoke(app, ["force", str(no_k), "--axis", "w", "--i-top", "1.6", "--i-bottom", "1.2"])
    assert r.exit_code == 3 and "k_w not identified" in r.output
    r = runner.invoke(app, ["force", str(no_k)])
    assert r.exit_code == 2 and "give --data FILE" in r.output


# --- the magnetic circuit on data from a bearing nobody here wrote (tests/data/README.md) -------------------------

FEM_SLICE = ROOT / "tests" / "data" / "fem_slice.csv"
FEM_BEARING = ROOT / "tests" / "data" / "fem_dev.toml"


def test_the_circuit_is_a_candidate_only_with_a_b_h_curve_and_paired_axes():
    from ambfit.diagnosis.attribution import default_candidates

    df = read_csv(FEM_SLICE).frame
    fem = ambfit.Bearing.from_toml(FEM_BEARING)
    assert any(isinstance(c, MagneticCircuit) for c in default_candidates(df, fem))
    assert not any(isinstance(c, MagneticCircuit) for c in default_candidates(df, ambfit.PAPER_BEARING))
    assert not any(isinstance(c, MagneticCircuit) for c in default_candidates(df.drop(columns=["time_s"]), fem))


def test_the_circuit_fits_the_fem_bearing_and_moves_gap_and_origin_to_the_drawing():
    # The FEM's rotor centre sits at the sensor offsets (-15, +30) µm and its air gap is the drawn 762 µm;
    # the ideal law reads the slice as a ~700 µm gap at chi2/dof in the hundreds.
    ds = read_csv(FEM_SLICE)
    fem = ambfit.Bearing.from_toml(FEM_BEARING)
    ideal = ambfit.fit(ds, bearing=fem, throw=False)
    mec = ambfit.fit(ds, [MagneticCircuit()], bearing=fem, start_from=ideal, throw=False)
    assert ideal.reduced_chi2 > 50 and mec.reduced_chi2 < 3 and mec.converged
    for ax, offset in (("v", -15e-6), ("w", 30e-6)):
        assert ideal.value(f"g_{ax}0") < 715e-6 and mec.value(f"g_{ax}0") > 740e-6
        assert abs(mec.value(f"{ax}0") - offset) < 0.5e-6
    # one stator: the circuit's parameters are shared by both axes, and saturation matters on this bearing
    assert "magnetic_circuit.iron_scale" in mec.names
    linear = ambfit.fit(ds, [mec.effects[0].without("saturation")], bearing=fem, start_from=mec, throw=False)
    assert linear.chi2 - mec.chi2 > 3 * np.sqrt(2 * mec.dof)


def test_the_circuit_families_decide_each_piece_as_refits_run_to_the_end_do():
    # Each piece switched off, the circuit refitted with the full model's noise held (the same weights for every
    # χ²), stopping as soon as the piece's significance is decided.  Refits run far longer, to their settled χ²,
    # must land inside the reported bounds and give the same decisions.
    from ambfit.diagnosis.circuit_families import SETTLED_EDM, circuit_families
    from ambfit.estimation.measure import force_noise

    ds = read_csv(FEM_SLICE)
    fem = ambfit.Bearing.from_toml(FEM_BEARING)
    ideal = ambfit.fit(ds, bearing=fem, throw=False)
    mec = ambfit.fit(ds, [MagneticCircuit()], bearing=fem, start_from=ideal, throw=False)
    fams = {f.piece: f for f in circuit_families(ds.frame, mec, fem)}
    threshold = 3 * np.sqrt(2 * mec.dof)
    assert set(fams) == set(MagneticCircuit.PIECES)
    assert fams["saturation"].significant and fams["saturation"].decided
    held, keep = force_noise(mec, ds.frame), mec.fitted_rows.astype(float)
    long = {}
    for piece in ("saturation", "iron", "fringing", "leakage", "coupling"):
        start = long["saturation"] if piece == "iron" else mec
        # (χ² at the minimum, as the families' refits measure it: the plain estimate)
        long[piece] = ambfit.fit(ds, [mec.effects[0].without(piece)], bearing=fem, start_from=start, max_steps=1000,
                                 throw=False, mask=keep, loss="linear", alpha=0.0, held_noise=held, debias="none")
        assert long[piece].edm < SETTLED_EDM * threshold           # settled: its χ² is the refit's minimum
    for piece, f in fams.items():
        ref = long["saturation"].chi2 if piece == "iron" else mec.chi2
        rise = long[piece].chi2 - ref
        lo, hi = f.delta_chi2_bounds
        assert lo - 1.0 <= rise <= hi + 1.0, (piece, lo, rise, hi)       # 1: χ² round-off of refits run apart
        if f.decided:
            assert f.significant == (rise > threshold), piece
        else:                                                            # undecided is not called significant
            assert not f.significant and lo <= threshold < hi, piece
    # the pieces' refits run two at a time (as a diagnosis runs them) give the same families
    from ambfit.diagnosis.threads import _Each

    with _Each(2) as each:
        assert circuit_families(ds.frame, mec, fem, each=each) == sorted(fams.values(), key=lambda f: -f.delta_chi2)


@pytest.mark.parametrize("loss", ["linear", "cauchy"])
def test_a_force_check_reads_a_refits_force_and_noise_as_predicting_them_gives(loss):
    # A left-out load's forces and noise floor come from the refit's own solve (F = load + s z) unless the refit
    # held its noise: the same numbers as predicting the force and propagating the noise anew
    from ambfit.estimation.measure import _at_known_loads, force_noise

    df = read_csv(FEM_SLICE).frame
    fem = ambfit.Bearing.from_toml(FEM_BEARING)
    known = df["load_N"].notna().to_numpy() & (df["load_N"].abs() > 0).to_numpy()
    out = known & (df["load_N"] == df.loc[known, "load_N"].iloc[0]).to_numpy()
    res = ambfit.fit(df, [Saturation()], bearing=fem, mask=(~out).astype(float), loss=loss, throw=False,
                     debias="none")
    rows = readings(df)
    force, noise = _at_known_loads(res, df, rows, {})
    np.testing.assert_allclose(force[known], predict(res, df, rows=rows)[known], rtol=1e-10)
    np.testing.assert_allclose(noise, force_noise(res, df), rtol=1e-10)
    # a refit with its noise held: the noise floor is the propagated one, not the held
    held = 2.0 * noise
    res_held = ambfit.fit(df, [Saturation()], bearing=fem, mask=(~out).astype(float), loss=loss, throw=False,
                          debias="none", held_noise=held)
    force, noise = _at_known_loads(res_held, df, rows, {"held_noise": held})
    np.testing.assert_allclose(force[known], predict(res_held, df, rows=rows)[known], rtol=1e-10)
    np.testing.assert_allclose(noise, force_noise(res_held, df), rtol=1e-10)
    assert not np.allclose(noise, held)


def test_a_force_check_reuses_a_refit_whose_left_out_rows_are_a_fold():
    # A diagnosis has already refitted each model with each fold held out; where a fold is exactly one known
    # load's rows (the FEM's load ids are per axis), the force check takes that refit instead of repeating it.
    from ambfit.diagnosis.heldout import folds

    df = read_csv(FEM_SLICE).frame
    fem = ambfit.Bearing.from_toml(FEM_BEARING)
    base = ambfit.fit(df, bearing=fem, throw=False)
    plain = force_check(df, (), bearing=fem, base=base, max_steps=60)
    # (refitted as the diagnosis does: the full fit's outliers left out, not tested again)
    refits = [(test, ambfit.fit(df, bearing=fem, mask=(~test & base.fitted_rows).astype(float), start_from=base,
                                max_steps=60, alpha=0.0, throw=False), None) for test in folds(df)[1]]
    assert force_check(df, (), bearing=fem, base=base, max_steps=60, fitted=refits) == plain
    # it does take them: another fold's refit in the first fold's place changes the figures
    swapped = [(refits[0][0], refits[1][1], None)] + refits[1:]
    assert force_check(df, (), bearing=fem, base=base, max_steps=60, fitted=swapped)["rms_rel"] != plain["rms_rel"]


def test_a_model_file_keeps_held_parameters_and_reads_older_files_that_estimated_them():
    # IronReluctance holds l_fe (it enters only as l_fe / mu_r); the model file records the held value, and a
    # file written when l_fe was estimated still gives its forces.
    from ambfit.physics import effects as E

    b = ambfit.PAPER_BEARING
    r = Readings.build(axis=[0, 1], i_top=[1.9, 1.6], i_bottom=[0.9, 1.3], x=[20e-6, -10e-6], y=[-10e-6, 20e-6])
    head = {"g_v0": 770e-6, "g_w0": 765e-6, "v0": 10e-6, "w0": -5e-6, "k_v": 3.4e-6, "k_w": 3.5e-6}
    fitted = {f"iron_reluctance.{f}[{ax}]": v for f, v in (("mu_r", 1800.0), ("b_knee", 1.1)) for ax in "vw"}
    truth = E.IronReluctance(l_fe=jnp.full(2, 0.11), mu_r=jnp.full(2, 1800.0), b_knee=jnp.full(2, 1.1))
    want = np.asarray(evaluate(BearingParams.from_values([770e-6, 765e-6], [10e-6, -5e-6], [3.4e-6, 3.5e-6]), r,
                               [truth], bearing=b)[0])

    def state(values, held):
        return {"names": list(values), "values": list(values.values()), "covariance": np.zeros((len(values),) * 2),
                "effects": [{"name": "iron_reluctance", "off": [], "held": held}], "bearing": b.name}

    new = FittedModel.from_state(state(head | fitted, {"l_fe": [0.11, 0.11]}), b)
    old = FittedModel.from_state(state(head | fitted | {"iron_reluctance.l_fe[v]": 0.11,
                                                        "iron_reluctance.l_fe[w]": 0.11}, {}), b)
    default = FittedModel.from_state(state(head | fitted, {}), b)           # l_fe at 0.08 m: another force
    for fm in (new, old):
        np.testing.assert_allclose(fm.force(r)[0], want, rtol=1e-12)
    # the older file's estimate of l_fe[v] keeps its error: its variance reaches the force on axis v (row 0) alone
    cov = np.zeros((len(old.names),) * 2)
    j = old.names.index("iron_reluctance.l_fe[v]")
    cov[j, j] = (0.01) ** 2
    s = dataclasses.replace(old, cov=cov).force(r)[1]
    assert s[0] > 0 and s[1] == 0
    assert np.all(np.abs(default.force(r)[0] - want) > 1e-3 * np.abs(want))
    from ambfit.estimation.results import _held_fields

    assert _held_fields(truth) == {"l_fe": [0.11, 0.11]}                    # what a fit's model file records
