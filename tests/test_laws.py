"""The other-law effects of ambfit.rig.laws do to the data what their docstrings say (benchmarks/gap_hidden_like.py
judges the diagnosis with them, so a broken law would mislead that measurement)."""

import jax.numpy as jnp
import numpy as np
import pytest

from ambfit import rig
from ambfit.physics.effects import CurrentOffset, Hysteresis, Saturation, ThermalDrift
from ambfit.physics.model import BearingParams, Readings, evaluate, ideal_force
from ambfit.rig import laws, protocol
from ambfit.rows import other_axis_currents

PARAMS = BearingParams.from_values((775e-6, 763e-6), (33.3e-6, -11.3e-6), (3.4e-6, 3.4e-6))


def _force(effects, **kw):
    """Force on one v-axis reading (1.5/1.1 A at 10 µm) with ``kw`` overriding its fields; no temperature."""
    fields = dict(axis=[0], i_top=[1.5], i_bottom=[1.1], x=[10e-6], time=[0.0]) | kw
    return float(evaluate(PARAMS, Readings.build(**fields), effects)[0][0])


def _ideal(x0_shift=0.0, g0_shift=0.0, i_top=1.5, i_bottom=1.1):
    return float(ideal_force(775e-6 + g0_shift, 33.3e-6 + x0_shift, 3.4e-6, i_top, i_bottom, 10e-6))


def test_linear_time_drift_moves_origin_and_gap_with_time_alone():
    law = laws.LinearTimeDrift(origin_rate=jnp.asarray(20e-6 / 3600), gap_rate=jnp.asarray(4e-6 / 3600))
    assert _force([law], time=[0.0]) == pytest.approx(_ideal(), rel=1e-12)
    # an hour later, with no temperature given: the origin 20 µm and the gap 4 µm on
    assert _force([law], time=[3600.0]) == pytest.approx(_ideal(20e-6, 4e-6), rel=1e-9)
    # the library's drift has a time law too where no temperature is measured (issue 23 item 4): it moves this row
    assert _force([ThermalDrift()], time=[3600.0]) != pytest.approx(_ideal(), rel=1e-9)


def test_exponential_time_drift_settles_at_its_step():
    law = laws.ExponentialTimeDrift(origin_step=jnp.asarray(-10e-6), gap_step=jnp.asarray(2e-6),
                                    tau_s=jnp.asarray(1200.0))
    assert _force([law], time=[0.0]) == pytest.approx(_ideal(), rel=1e-12)
    frac = 1.0 - np.exp(-1.0)
    assert _force([law], time=[1200.0]) == pytest.approx(_ideal(-10e-6 * frac, 2e-6 * frac), rel=1e-9)
    assert _force([law], time=[1e6]) == pytest.approx(_ideal(-10e-6, 2e-6), rel=1e-9)


def test_drift_with_time_moves_late_readings_on_the_rig():
    """The same set-points read late need other currents than read early; without the drift they need the same."""
    proto = protocol.paper_table2(iterations=6)
    law = laws.LinearTimeDrift(origin_rate=jnp.asarray(30e-6 / 3600), gap_rate=jnp.asarray(0.0))
    spans = {}
    for name, effects in (("drift", [law]), ("none", [])):
        d = rig.simulate(rig.PAPER_RIG, proto, effects, rig.NOISE_FREE).data
        v = d[(d.axis == "v") & (d.bias_A == 1.4) & (d.v_set_um > 0)]
        spans[name] = float(v.i_top_A.iloc[-1] - v.i_top_A.iloc[0])
    assert spans["none"] == pytest.approx(0.0, abs=1e-12)
    assert abs(spans["drift"]) > 1e-3    # 0.9 µm of origin in 110 s: well above the 0.6 mA noise of the rig


def _after_path(effects, currents):
    """Force [N] of the v axis' top coil at the last of a sequence of its currents [A], the coil's state
    carried from reading to reading as the rig carries it, starting demagnetised."""
    m_top, m_bottom = jnp.zeros(1), jnp.zeros(1)
    for i in currents:
        r = Readings.build(axis=[0], i_top=[i], i_bottom=[0.0], x=[10e-6])
        f, ctx = evaluate(PARAMS, r, effects, physical=True, m_prev_top=m_top, m_prev_bottom=m_bottom)
        m_top, m_bottom = ctx.m_top, ctx.m_bottom
    return float(f[0])


def test_minor_loop_hysteresis_remembers_more_than_the_last_direction():
    law = laws.MinorLoopHysteresis(width=jnp.asarray(0.15), fraction=jnp.asarray(0.08))
    # 1.15 A approached from below both times, once by way of 1.2 and 1.1 A: the wide play remembers the detour
    # (play output 1.05 A against 1.0 A, magnetising current 1.142 A against 1.138 A)
    detour, direct = (1.0, 1.2, 1.1, 1.15), (1.0, 1.15)
    assert _after_path([law], detour) / _after_path([law], direct) == pytest.approx((1.142 / 1.138) ** 2, rel=1e-9)
    # the library's narrow play forgets it: only the last direction counts
    lib = Hysteresis(width=jnp.asarray(0.01))
    assert _after_path([lib], detour) == pytest.approx(_after_path([lib], direct), rel=1e-12)


def test_minor_loop_lag_is_bounded_by_fraction_times_width():
    law = laws.MinorLoopHysteresis(width=jnp.asarray(0.15), fraction=jnp.asarray(0.08))
    i = jnp.linspace(0.5, 2.0, 7)
    for p_prev in (0.0, 1.2, 5.0):
        p = jnp.clip(p_prev, i - 0.15, i + 0.15)
        lag = law.magnetising(i, p, 0) - i
        assert float(jnp.max(jnp.abs(lag))) <= 0.08 * 0.15 + 1e-15
    assert float(jnp.max(jnp.abs(law.magnetising(i, jnp.clip(5.0, i - 0.15, i + 0.15), 0) - i))) == pytest.approx(
        0.012, rel=1e-12)


def test_current_coupling_acts_through_the_other_axis_currents():
    law = laws.CurrentCoupling(beta=jnp.asarray(0.04))
    c = 0.5 * (1.6 - 1.0)
    shifted = _ideal(i_top=1.5 + 0.04 * c, i_bottom=1.1 - 0.04 * c)
    assert _force([law], i_top_other=[1.6], i_bottom_other=[1.0]) == pytest.approx(shifted, rel=1e-12)
    # the other axis' position alone does nothing
    assert _force([law], y=[50e-6]) == pytest.approx(_ideal(), rel=1e-12)


def test_rig_equilibrium_with_current_coupling_is_self_consistent():
    """The rig solves both axes together: the recorded currents, paired by time, balance the known loads."""
    law = laws.CurrentCoupling(beta=jnp.asarray(0.05))
    d = rig.simulate(rig.PAPER_RIG, protocol.rich(n_positions=3, masses_kg=(0.0, 1.0)), [law], rig.NOISE_FREE).data
    ot, ob = other_axis_currents(d)
    r = Readings.build(axis=(d.axis == "w").astype(int), i_top=d.i_top_A, i_bottom=d.i_bottom_A,
                       x=np.where(d.axis == "v", d.v_um, d.w_um) * 1e-6, i_top_other=ot, i_bottom_other=ob)
    params = rig.PAPER_RIG.params()
    f = np.asarray(evaluate(params, r, [law])[0])
    assert np.max(np.abs(f - d.load_N.to_numpy())) < 1e-8
    f_uncoupled = np.asarray(evaluate(params, r, [])[0])
    assert np.max(np.abs(f_uncoupled - d.load_N.to_numpy())) > 1e-2   # the coupling is felt


def test_tanh_saturation_bends_from_zero_flux_density():
    law = laws.TanhSaturation(b_sat=jnp.asarray(1.5))
    b = jnp.asarray([0.05, 0.5, 0.8])
    f = np.asarray(law.factor(b, 0))
    assert f[0] == pytest.approx(1.0 - 2.0 * 0.05**2 / (3 * 1.5**2), abs=1e-6)
    assert f[1] == pytest.approx((np.tanh(0.5 / 1.5) / (0.5 / 1.5)) ** 2, rel=1e-12)
    # at 0.5 T it already takes 7 %; the library's knee at 1.3 T takes under 1 %
    assert 1 - f[1] > 0.05 > 0.01 > 1 - float(Saturation().factor(0.5, 0))


def test_position_nonlinearity_reads_gain_and_curve_and_inverts():
    law = laws.PositionNonlinearity(gain=jnp.asarray(0.02), curve=jnp.asarray(-0.03))
    x = jnp.asarray([-80e-6, -20e-6, 0.0, 30e-6, 90e-6])
    axis = jnp.zeros(5, dtype=int)
    _, _, s, _ = law.sense(axis, 0.0, 0.0, x, x)
    np.testing.assert_allclose(s, 1.02 * x - 0.03 * x**2 / 100e-6, rtol=1e-12, atol=1e-18)
    _, _, back, _ = law.unsense(axis, 0.0, 0.0, s, s)
    np.testing.assert_allclose(back, x, rtol=0, atol=1e-15)


def test_channel_calibration_offset_and_gain():
    law = laws.ChannelCalibration(top_offset=jnp.asarray(0.01), bottom_offset=jnp.asarray(-0.005),
                                  top_gain=jnp.asarray(0.003), bottom_gain=jnp.asarray(-0.002))
    i = jnp.asarray([0.0, 1.0, 2.0])
    top, bottom, _, _ = law.sense(jnp.zeros(3, dtype=int), i, i, 0.0, 0.0)
    np.testing.assert_allclose(top, 1.003 * i + 0.01, rtol=1e-14)
    np.testing.assert_allclose(bottom, 0.998 * i - 0.005, rtol=1e-14)
    back = law.unsense(jnp.zeros(3, dtype=int), top, bottom, 0.0, 0.0)
    np.testing.assert_allclose(back[0], i, atol=1e-15)
    np.testing.assert_allclose(back[1], i, atol=1e-15)


def test_two_effects_at_once_both_act():
    """Saturation + current offset: the same physical equilibria as saturation alone, read through the offset."""
    rng = np.random.default_rng(3)
    sat, off = laws.draw(("saturation", "current_offset"), rng)
    assert isinstance(sat, Saturation) and isinstance(off, CurrentOffset)
    proto = protocol.paper_table2(iterations=1)
    both = rig.simulate(rig.PAPER_RIG, proto, [sat, off], rig.NOISE_FREE).data
    alone = rig.simulate(rig.PAPER_RIG, proto, [sat], rig.NOISE_FREE).data
    ideal = rig.simulate(rig.PAPER_RIG, proto, [], rig.NOISE_FREE).data
    ax = (both.axis == "w").astype(int).to_numpy()
    np.testing.assert_allclose(both.i_top_A - alone.i_top_A, np.asarray(off.top)[ax], atol=1e-12)
    np.testing.assert_allclose(both.i_bottom_A - alone.i_bottom_A, np.asarray(off.bottom)[ax], atol=1e-12)
    assert np.max(np.abs(alone.i_top_A - ideal.i_top_A)) > 1e-3     # and the saturation is there
    with pytest.raises(ValueError, match="unknown effect or law 'saturaton'"):
        laws.draw(("saturaton",), rng)


def test_serpentine_protocol_shuffles_biases_and_walks_neighbours():
    p = protocol.serpentine(seed=4)
    assert len(p) == 420
    biases = (1.0, 1.1, 1.2, 1.3, 1.4, 1.5, 1.6)
    blocks = p.bias_v.reshape(-1, 7)
    assert all(sorted(b) == pytest.approx(biases) for b in blocks)
    assert len({tuple(b) for b in blocks}) > 50          # a fresh order at each of the 60 set-points
    pts = np.stack([p.v_set, p.w_set], axis=1)[::7]
    steps = np.abs(np.diff(pts[:15], axis=0))
    # a serpentine: each move changes one coordinate by one grid step (20 µm in v, 30 µm in w)
    assert np.all((np.isclose(steps[:, 0], 20e-6) & (steps[:, 1] == 0))
                  | ((steps[:, 0] == 0) & np.isclose(steps[:, 1], 30e-6)))


def test_as_recorded_drops_the_thermometer_and_keeps_required_columns():
    d = rig.simulate(rig.PAPER_RIG, protocol.paper_table2(iterations=1), [], rig.NOISE_FREE).data
    assert "temperature_C" not in laws.as_recorded(d).columns
    assert "time_s" in laws.as_recorded(d).columns
    assert "time_s" not in laws.as_recorded(d, ("temperature_C", "time_s")).columns
    with pytest.raises(ValueError, match="required"):
        laws.as_recorded(d, ("i_top_A",))
