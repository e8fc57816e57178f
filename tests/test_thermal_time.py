"""Thermal drift where no temperature is measured: the drift acts through time (issue 23, item 4).

Reference values come from the rig's truth (the rates it was given), not from earlier runs.
"""

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

import ambfit
from ambfit import data as data_mod
from ambfit import diagnosis, rig
from ambfit import rows as rows_mod
from ambfit.faces.cli import app
from ambfit.physics import effects as E
from ambfit.physics.model import BearingParams, Readings, evaluate
from ambfit.rig import protocol as P

NOISE = rig.Noise(0.6e-3, 0.1e-6)
# rates within ThermalDrift.RANGES (the heating curve's initial slope times the temperature coefficients):
# over the rich protocol's 700 s the gaps drift 1.4-2.1 µm and the origins 7-10 µm
TRUE_RATES = {"dg_dt": (3e-9, -2e-9), "dx0_dt": (1.5e-8, -1e-8)}
Z_MAX = 3.0
"""A rate is recovered when it lies within this many of its standard errors of the truth (a 0.3 % chance miss
per rate at a fixed seed)."""


@pytest.fixture(scope="module")
def timed():
    """Rich-design rig data with the drift in time and no temperature column."""
    truth = E.ThermalDrift(**{k: jnp.asarray(v) for k, v in TRUE_RATES.items()})
    return rig.simulate(rig.PAPER_RIG, P.rich(), [truth], NOISE, seed=3, thermometer=False).data


def _row(effect, time, temperature=None):
    r = Readings.build(axis=[0], i_top=[1.6], i_bottom=[1.2], x=[5e-6], time=[time],
                       temperature=None if temperature is None else [temperature])
    return evaluate(BearingParams(jnp.asarray([775e-6, 763e-6]), jnp.asarray([30e-6, -10e-6]),
                                  jnp.asarray([3.4e-6, 3.4e-6])), r, (effect,))[1]


def test_without_temperature_the_drift_is_linear_in_time_and_with_one_time_is_ignored():
    td = E.ThermalDrift(dg_dT=0.2e-6, dx0_dT=1e-6, dg_dt=jnp.asarray([3e-9, 0.0]),
                        dx0_dt=jnp.asarray([1e-8, -2e-8]))
    ctx = _row(td, 600.0)
    assert float(ctx.g0[0]) == pytest.approx(775e-6 + 3e-9 * 600, rel=1e-12)
    assert float(ctx.x0[0]) == pytest.approx(30e-6 + 1e-8 * 600, rel=1e-12)
    assert float(ctx.y0[0]) == pytest.approx(-10e-6 - 2e-8 * 600, rel=1e-12)     # the other axis' rate
    ctx = _row(td, 600.0, temperature=32.0)          # a measured temperature: its law alone
    assert float(ctx.g0[0]) == pytest.approx(775e-6 + 0.2e-6 * 10, rel=1e-12)
    assert float(ctx.x0[0]) == pytest.approx(30e-6 + 1e-6 * 10, rel=1e-12)


def test_the_rig_without_thermometer_writes_no_temperature_and_drifts_in_time():
    proto = P.grid([(0.0, 0.0)] * 6, [1.4], dwell_s=100.0)
    eff = [E.ThermalDrift(dg_dt=jnp.asarray(0.0), dx0_dt=jnp.asarray(1e-8))]
    d = rig.simulate(rig.PAPER_RIG, proto, eff, rig.NOISE_FREE, thermometer=False).data
    assert "temperature_C" not in d.columns and "time_s" in d.columns
    v = d[d.axis == "v"]
    # the origin grows with time: the top gap closes, less top current is needed at each later reading
    assert np.all(np.diff(v.i_top_A.to_numpy()) < 0)
    assert "temperature_C" in rig.simulate(rig.PAPER_RIG, proto, eff, rig.NOISE_FREE).data.columns


def test_time_counts_from_the_start_of_the_clock(timed):
    """The fitted gap and origin are those at the clock's start, wherever the clock's zero is."""
    late = timed.assign(time_s=timed.time_s + 1.7e9)         # a Unix clock
    t = np.asarray(rows_mod.readings(late).time)
    assert np.array_equal(t, timed.time_s.to_numpy() - timed.time_s.min())
    # two experiments read one after another on one clock: the drift runs on, one clock counts from the start
    two = late.assign(experiment=np.where(np.arange(len(late)) < 140, "a", "b"))
    assert np.array_equal(np.asarray(rows_mod.readings(two).time), t)
    # the second experiment's clock restarts: each counts from its own first reading
    restart = two.assign(time_s=np.where(two.experiment == "b", two.time_s - two.time_s.iloc[140] + 5.0,
                                         two.time_s))
    t2 = np.asarray(rows_mod.readings(restart).time)
    assert t2[0] == 0.0 and t2[140] == 0.0 and t2[141] == t[141] - t[140]
    a = ambfit.fit(timed, effects=(E.ThermalDrift(),))
    b = ambfit.fit(late, effects=(E.ThermalDrift(),))
    np.testing.assert_allclose(b.values, a.values, rtol=1e-9)
    np.testing.assert_allclose(b.std, a.std, rtol=1e-9)


def test_fit_recovers_the_drift_rates_from_time_alone(timed):
    res = ambfit.fit(timed, effects=(E.ThermalDrift(),))
    assert res.converged and res.well_conditioned
    got = dict(zip(res.names, zip(res.values, res.std)))
    for name, truth in TRUE_RATES.items():
        for ax, true in zip("vw", truth):
            value, std = got[f"thermal_drift.{name}[{ax}]"]
            assert abs(value - true) < Z_MAX * std, (name, ax, value, true, std)
            assert std < abs(true) / 3          # determined by the data, not by the prior
    ideal = ambfit.fit(timed)
    assert res.chi2 / res.dof < 1.5 < ideal.chi2 / ideal.dof


def test_diagnose_names_thermal_drift_on_time_alone(timed):
    d = diagnosis.diagnose(timed).to_json()
    assert [r["effect"] for r in d["ranking"] if "+" not in r["effect"]][0] == "thermal_drift"
    assert d["verdict"] == "thermal_drift"
    assert d["shrink"] > 0.8          # the ideal law's held-out excess shrinks (attribution target, 0.8)


class _TemperatureOnly(E.ThermalDrift):
    """The temperature law alone: what ThermalDrift fitted before it had a time law."""

    def ranges(self):
        return {k: v for k, v in type(self).RANGES.items() if k in ("dg_dT", "dx0_dT")}


def test_with_a_temperature_column_the_time_rates_change_nothing():
    truth = E.ThermalDrift(dg_dT=jnp.asarray([0.3e-6, 0.2e-6]), dx0_dT=jnp.asarray([1.5e-6, -1e-6]))
    d = rig.simulate(rig.PAPER_RIG, P.rich(), [truth], NOISE, seed=5).data
    assert "temperature_C" in d.columns
    both = ambfit.fit(d, effects=(E.ThermalDrift(),))
    alone = ambfit.fit(d, effects=(_TemperatureOnly(),))
    assert both.converged and alone.converged
    got = dict(zip(both.names, zip(both.values, both.std)))
    assert set(got) - set(alone.names) == {f"thermal_drift.{n}[{ax}]" for n in ("dg_dt", "dx0_dt") for ax in "vw"}
    for name, value, std in zip(alone.names, alone.values, alone.std):
        # the rates' Jacobian columns are zero: the same solve to round-off
        assert got[name][0] == pytest.approx(value, rel=1e-7, abs=1e-15), name
        assert got[name][1] == pytest.approx(std, rel=1e-7), name
    for name, (lo, hi) in E.ThermalDrift.RANGES.items():
        if name.endswith("_dt"):
            for ax in "vw":    # unseen: at the prior's centre (zero, signed) with the prior's width
                assert got[f"thermal_drift.{name}[{ax}]"] == (0.0, pytest.approx(hi, rel=1e-9))
    assert both.chi2 == pytest.approx(alone.chi2, rel=1e-9)


def test_cli_simulates_without_temperature(tmp_path):
    csv = tmp_path / "d.csv"
    r = CliRunner().invoke(app, ["simulate", "-o", str(csv), "--preset", "table2", "--iterations", "1",
                                 "--effect", "thermal_drift:dx0_dt=1e-8", "--no-temperature"])
    assert r.exit_code == 0, r.output
    d = data_mod.read_csv(csv).frame
    assert "temperature_C" not in d.columns and "time_s" in d.columns


def test_identification_names_only_the_drift_law_the_data_cannot_see(timed):
    """A law no reading uses cannot make the solver wander; an effect the data do not see at all still can."""
    from ambfit.estimation import conditioning
    from ambfit.estimation.identification import undetermined_text

    shares = conditioning.effect_identification(timed, (E.ThermalDrift(),))
    assert set(shares) == {f"thermal_drift.{n}[{ax}]" for n in ("dg_dt", "dx0_dt") for ax in "vw"}
    assert max(shares.values()) < 0.01 and not undetermined_text(shares)
    hot = rig.simulate(rig.PAPER_RIG, P.rich(), [E.ThermalDrift()], NOISE, seed=5).data
    shares = conditioning.effect_identification(hot, (E.ThermalDrift(),))
    assert {n.split(".")[1].split("[")[0] for n in shares} == {"dg_dT", "dx0_dT"}
    assert not undetermined_text(shares)
    blind = timed.drop(columns="time_s")            # neither time nor temperature: the drift is unseen
    shares = conditioning.effect_identification(blind, (E.ThermalDrift(),))
    assert len(shares) == 8 and min(shares.values()) > 0.99
    assert "readings over a range of temperature" in undetermined_text(shares)


def test_parameters_no_reading_depends_on_take_no_degree_of_freedom():
    """On data with a temperature column the time law's four rates have no reading to act on: χ²'s degrees of freedom
    drop by the four temperature coefficients only (its p-value and an estimated noise would be off otherwise)."""
    data = rig.simulate(rig.PAPER_RIG, P.rich(), [E.ThermalDrift()], seed=5).data
    assert "temperature_C" in data
    ideal = ambfit.fit(data, throw=False)
    drift = ambfit.fit(data, effects=(E.ThermalDrift(),), throw=False)
    assert len(drift.names) - len(ideal.names) == 8
    assert drift.dof == ideal.dof - 4


def test_a_temperature_column_that_does_not_change_is_no_thermometer(timed):
    """A logged room or set-point temperature measures no thermal state: the drift is followed in time, as
    without the column, not pinned to a constant temperature."""
    steady = timed.assign(temperature_C=22.0)
    assert rows_mod.thermometer(steady) is None
    a = ambfit.fit(timed, effects=(E.ThermalDrift(),))
    b = ambfit.fit(steady, effects=(E.ThermalDrift(),))
    np.testing.assert_allclose(b.values, a.values, rtol=1e-9)
    warming = timed.assign(temperature_C=22.0 + np.linspace(0.0, 0.5, len(timed)))
    np.testing.assert_array_equal(rows_mod.thermometer(warming), warming.temperature_C.to_numpy())


def test_the_clock_is_one_run_only_when_every_experiment_follows_the_one_before(timed):
    t = timed.time_s.to_numpy()
    three = timed.assign(experiment=np.repeat(["a", "b", "c"], [100, 100, len(timed) - 200]))
    np.testing.assert_array_equal(rows_mod.clock(three), t - t.min())
    # c's clock restarted: each experiment counts from its own first reading
    restart = three.assign(time_s=np.where(three.experiment == "c", t - t[200], t))
    got = rows_mod.clock(restart)
    assert got[0] == got[100] == got[200] == 0.0
    assert rows_mod.clock(timed.drop(columns="time_s")) is None


def test_a_joined_tables_clocks_are_each_tables_own(timed):
    """A study's joined table decides each data set's clock as that table alone would (one run or restarted), and
    rows of no experiment or no time count as they do there."""
    t = timed.time_s.to_numpy()
    three = timed.assign(experiment=np.repeat(["a", "b", "c"], [100, 100, len(timed) - 200]))
    restart = three.assign(time_s=np.where(three.experiment == "c", t - t[200], t))
    gaps = restart.assign(time_s=np.where(np.arange(len(t)) % 7 == 0, np.nan, restart.time_s),
                          experiment=np.where(np.arange(len(t)) % 11 == 0, None, restart.experiment))
    # integer experiment codes with a missing one (a study's joined tables number theirs): no experiment at all
    coded = restart.assign(experiment=pd.array(np.where(np.arange(len(t)) % 13 == 0, None,
                                                        np.repeat([1, 2, 3], [100, 100, len(t) - 200])), dtype="Int64"))
    tables = [three, restart, gaps, restart.iloc[150:260], three.iloc[:0], coded]
    sets = np.repeat(np.arange(len(tables)), [len(x) for x in tables])
    joined = rows_mod.clock(pd.concat(tables, ignore_index=True), sets)
    np.testing.assert_array_equal(joined, np.concatenate([rows_mod.clock(x) for x in tables]))
    assert np.isnan(joined[sets == 2]).any() and np.all(joined[sets == 1][[0, 100, 200]] == 0.0)
