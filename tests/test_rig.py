"""Virtual rig: equilibria, noise, and each unmodelled effect's direction."""

import numpy as np
import pytest

from ambfit import rig
from ambfit.physics import effects as E
from ambfit.rig import limits
from ambfit.rig import protocol as P

NF = rig.NOISE_FREE


def _sim(proto, effects=(), spec=rig.PAPER_RIG, **kw):
    return rig.simulate(spec, proto, effects, kw.pop("noise", NF), **kw)


def test_paper_rig_matches_the_paper():
    s = rig.PAPER_RIG
    assert s.bearing.bore_diameter == 35e-3 and s.nominal_gap == 762e-6
    assert s.load_capacity == pytest.approx(53.4, rel=1e-12)
    assert s.force_constant == pytest.approx(3.4452e-6, rel=1e-4)
    # saturation current 3.0 A gives about 1.2 T in the nominal gap with 2 x 240 turns
    b = 4e-7 * np.pi * s.bearing.horseshoe_turns * 3.0 / (2 * s.nominal_gap)
    assert 1.1 < b < 1.3


@pytest.mark.parametrize("name", ["none", *E.EFFECTS])
def test_equilibria_balance_the_load(name):
    effs = [] if name == "none" else [E.EFFECTS[name]()]
    sim = _sim(P.rich(), effs)
    assert np.max(np.abs(sim.force_residual)) < rig.FORCE_TOLERANCE_N
    assert np.all(sim.physical_currents >= 0.0)
    assert np.all(sim.data[["i_top_A", "i_bottom_A"]].to_numpy() >= 0.0) or name == "current_offset"


def test_all_effects_together_still_balance():
    effs = [cls() for cls in E.EFFECTS.values()]
    sim = _sim(P.rich(), effs)
    assert np.max(np.abs(sim.force_residual)) < rig.FORCE_TOLERANCE_N


def test_currents_never_negative_when_control_exceeds_bias():
    # bias 0.2 A cannot carry 7 N symmetrically: the bottom coil is switched off (clipped at zero)
    sim = _sim(P.perturbation((0.2, 0.3), (20e-6,)))
    assert np.max(np.abs(sim.force_residual)) < rig.FORCE_TOLERANCE_N
    assert np.all(sim.physical_currents[..., 1] == 0.0)
    assert np.all(sim.physical_currents >= 0.0)


def test_unbalanceable_load_raises():
    heavy = {"big": P.Load(500.0, 500.0, True)}
    with pytest.raises(rig.RigError, match="cannot balance the load"):
        _sim(P.perturbation((1.4, 1.6), (20e-6,), load="big", loads=heavy))


def test_closing_gap_raises():
    with pytest.raises(rig.RigError, match="closes a pole gap"):
        _sim(P.grid([(800e-6, 0.0)], [1.0]))


def test_noise_is_seeded_and_has_the_declared_std():
    proto = P.paper_table2(iterations=50)
    a = _sim(proto, noise=rig.Noise(1e-3, 0.2e-6), seed=5).data
    b = _sim(proto, noise=rig.Noise(1e-3, 0.2e-6), seed=5).data
    clean = _sim(proto).data
    assert a.equals(b)
    d = (a["i_top_A"] - clean["i_top_A"]).to_numpy()
    # 400 draws: the sample std of N(0, 1 mA) lies within ±15 % with probability > 0.999
    assert np.std(d) == pytest.approx(1e-3, rel=0.15)
    assert (a["i_top_std_A"] == 1e-3).all()
    np.testing.assert_allclose(a["v_std_um"], 0.2, rtol=1e-12)
    # both rows of one step share the position sample
    assert np.array_equal(a["v_um"].to_numpy()[0::2], a["v_um"].to_numpy()[1::2])


def _control(sim):
    return (sim.data["i_top_A"] - sim.data["i_bottom_A"]).to_numpy()


HEAVY = P.grid([(20e-6, 20e-6)], [1.6], load="m", loads={"m": P.Load.gravity(2.5)})


@pytest.mark.parametrize("effect, sign", [
    (E.Saturation(), +1),       # force below the square law: more control current for the same load
    (E.IronReluctance(), +1),   # larger magnetic gap: weaker force
    (E.Leakage(), +1),          # less flux crosses the gap: weaker force
    (E.Fringing(), -1),         # larger effective pole area: stronger force
])
def test_force_effects_change_the_control_current_in_their_direction(effect, sign):
    base, eff = _control(_sim(HEAVY)), _control(_sim(HEAVY, [effect]))
    assert np.all(sign * (eff - base) > 1e-4)


def test_saturation_grows_with_flux_density():
    low = P.grid([(0.0, 0.0)], [0.8], load="m", loads={"m": P.Load.gravity(2.5)})
    high = P.grid([(0.0, 0.0)], [2.0], load="m", loads={"m": P.Load.gravity(2.5)})
    rel = [(_control(_sim(p, [E.Saturation()])) / _control(_sim(p)))[0] - 1 for p in (low, high)]
    assert rel[1] > 5 * rel[0] > 0


def test_current_offset_shifts_the_readings_exactly():
    eff = E.CurrentOffset(top=np.array([0.004, 0.006]), bottom=np.array([-0.003, 0.002]))
    a, b = _sim(HEAVY).data, _sim(HEAVY, [eff]).data
    np.testing.assert_allclose((b.i_top_A - a.i_top_A).to_numpy(), [0.004, 0.006], atol=1e-12)
    np.testing.assert_allclose((b.i_bottom_A - a.i_bottom_A).to_numpy(), [-0.003, 0.002], atol=1e-12)


def test_current_gain_scales_top_and_bottom_oppositely():
    a, b = _sim(HEAVY).data, _sim(HEAVY, [E.CurrentGain(mismatch=np.asarray(0.02))]).data
    np.testing.assert_allclose((b.i_top_A / a.i_top_A).to_numpy(), 1.01, rtol=1e-12)
    np.testing.assert_allclose((b.i_bottom_A / a.i_bottom_A).to_numpy(), 0.99, rtol=1e-12)


def test_position_gain_moves_the_physical_rotor():
    # The controller holds the *measured* position at the set-point, so with gain 1+γ the rotor sits at set/(1+γ).
    g = 0.03
    b = _sim(HEAVY, [E.PositionGain(gain_error=np.asarray(g))]).data
    ref = _sim(P.grid([(20e-6 / (1 + g), 20e-6 / (1 + g))], [1.6], load="m", loads={"m": P.Load.gravity(2.5)})).data
    np.testing.assert_allclose(b.v_um, 20.0, rtol=1e-12)
    np.testing.assert_allclose(b.i_top_A.to_numpy(), ref.i_top_A.to_numpy(), rtol=1e-12)


def test_cross_coupling_depends_on_the_other_axis():
    pts = [(0.0, 40e-6), (0.0, -40e-6)]
    proto = P.grid(pts, [1.4])
    eff = E.CrossCoupling(kappa=np.asarray(2000.0), geometric=np.asarray(0.0))
    base, cc = _sim(proto).data, _sim(proto, [eff]).data
    v_base, v_cc = base[base.axis == "v"], cc[cc.axis == "v"]
    dv = (v_cc.i_top_A - v_cc.i_bottom_A).to_numpy() - (v_base.i_top_A - v_base.i_bottom_A).to_numpy()
    # +kappa * (w0 + w) helps the v axis where w0 + w > 0 (w0 = -11.3 µm): less control current needed
    assert dv[0] < -1e-4 and dv[1] > 1e-4


def test_hysteresis_makes_the_order_of_readings_matter():
    sweep = P.bias_sweep([1.2, 1.4, 1.6], up_down=True)  # 1.2 1.4 1.6 1.4 1.2
    h = 0.01
    v = _control(_sim(sweep, [E.Hysteresis(width=np.asarray(h))]))[0::2]
    # 1.4 A approached rising (reading 1) and falling (reading 3) differ ...
    assert abs(v[1] - v[3]) > 1e-3
    # ... exactly as the play operator says: rising, both magnetising currents lag by h, i.e. the
    # ideal bearing at bias 1.4 - h; falling, at bias 1.4 + h.
    for reading, bias in ((1, 1.4 - h), (3, 1.4 + h)):
        ref = _control(_sim(P.grid([(0.0, 0.0)], [bias])))[0]
        assert v[reading] == pytest.approx(ref, abs=1e-12)
    ideal = _control(_sim(sweep))[0::2]
    assert ideal[1] == pytest.approx(ideal[3], abs=1e-12)


def test_thermal_drift_follows_time_and_temperature():
    proto = P.grid([(0.0, 0.0)] * 20, [1.4], dwell_s=120.0)
    eff = E.ThermalDrift(dg_dT=np.asarray(0.0), dx0_dT=np.asarray(1e-6), heating_K=20.0, tau_s=600.0)
    d = _sim(proto, [eff]).data
    v = d[d.axis == "v"]
    assert np.all(np.diff(v.temperature_C) > 0) and v.temperature_C.iloc[-1] > 35
    # origin grows with temperature: the top gap closes, less top current is needed over time
    assert np.all(np.diff(v.i_top_A.to_numpy()) < 0)
    ideal = _sim(proto).data
    assert np.ptp(ideal[ideal.axis == "v"].i_top_A) < 1e-12


def test_reassembly_moves_the_origin():
    proto = P.with_assembly(P.paper_table2(iterations=1), 1, (-80e-6, 24e-6))
    sim = _sim(proto)
    assert sim.truth["params"]["1"]["v0_um"] == pytest.approx(33.3 - 80)
    from ambfit.estimation import closed_form
    est = closed_form.identify(sim.data).estimates
    assert est[("all", "v")].x0 == pytest.approx(-46.7e-6, rel=1e-6)


def test_state_carries_history_and_clock():
    eff = [E.Hysteresis()]
    a = _sim(P.paper_table2(iterations=2), eff)
    first = _sim(P.paper_table2(iterations=1), eff)
    second = rig.simulate(rig.PAPER_RIG, P.paper_table2(iterations=1), eff, NF, state=first.state)
    np.testing.assert_allclose(second.data.i_top_A.to_numpy(), a.data.i_top_A.to_numpy()[8:], atol=1e-13)
    assert second.data.time_s.iloc[0] == a.data.time_s.iloc[8]


@pytest.mark.parametrize("cls", list(E.EFFECTS.values()))
def test_random_effects_stay_in_range_and_balance(cls):
    rng = np.random.default_rng(3)
    e = cls.random(rng)
    for name, (lo, hi) in cls.RANGES.items():
        v = np.abs(np.asarray(getattr(e, name)))
        assert np.all((v >= lo) & (v <= hi))
    sim = _sim(P.rich(), [e])
    assert np.max(np.abs(sim.force_residual)) < rig.FORCE_TOLERANCE_N


def test_protocol_from_dict_matches_builders():
    d = {"block": [{"kind": "perturbation", "biases_A": [1.4, 1.6], "offsets_um": [20], "iterations": 3,
                    "experiment": "t"}]}
    a, b = P.from_dict(d), P.perturbation((1.4, 1.6), (20e-6,), iterations=3, experiment="t")
    np.testing.assert_allclose(a.v_set, b.v_set)
    assert list(a.experiment) == list(b.experiment)
    with pytest.raises(ValueError, match="unknown kind"):
        P.from_dict({"block": [{"kind": "nope"}]})


def test_paper_table_protocols():
    t1 = P.paper_table1(iterations=2)
    assert len(t1) == 3 * 2 * 4 and sorted(set(t1.experiment)) == ["1", "2", "3"]
    t4 = P.paper_table4(iterations=1)
    assert len(t4) == 6 * 4 and set(t4.assembly) == {1}
    sim = _sim(t4)
    from ambfit.estimation import closed_form
    est = closed_form.identify(sim.data, by_experiment=True).estimates
    assert est[("1.0/1.4 ±50", "v")].x0 == pytest.approx(-47.4e-6, rel=1e-6)
    assert len(P.PAPER_TABLE3_STARTS) == 4


# --- the bearing's limits: back-up clearance and coil current --------------------------------------------------

def test_rotor_position_is_the_set_point_plus_the_true_origin():
    proto = P.grid([(20e-6, 20e-6), (-33.3e-6, 11.3e-6)], [1.4])
    pos = limits.rotor_positions(rig.PAPER_RIG, proto)
    np.testing.assert_allclose(pos, [[53.3e-6, 8.7e-6], [0.0, 0.0]], atol=1e-15)
    # a reassembly shifts the true origin, and with it the rotor
    moved = P.with_assembly(proto, 1, (-80.7e-6, 24.4e-6))
    np.testing.assert_allclose(limits.rotor_positions(rig.PAPER_RIG, moved)[1], [-80.7e-6, 24.4e-6], atol=1e-15)


def test_limit_violations_name_the_steps_beyond_the_clearance():
    # Table 2 about the sensor origin: (20, 20) µm puts the rotor 54.0 µm from the centre, inside 60 µm
    assert limits.limit_violations(rig.PAPER_RIG, P.paper_table2(iterations=1)) == []
    # the rich sweep about the sensor origin reaches (40 + 33.3, w - 11.3) µm; about the effective origin it stays
    # within 40 sqrt(2) = 56.6 µm
    found = limits.limit_violations(rig.PAPER_RIG, P.rich())
    assert found and {f.kind for f in found} == {"clearance"}
    first = found[0]
    r = np.hypot(first.set_point[0] + 33.3e-6, first.set_point[1] - 11.3e-6)
    assert first.value == pytest.approx(r, rel=1e-12) and r > 60e-6 and first.limit == 60e-6
    assert f"step {first.step} " in str(first) and "back-up clearance of 60.0 µm" in str(first)
    assert limits.limit_violations(rig.PAPER_RIG, P.rich(center=(-33.3e-6, 11.3e-6))) == []


def test_limit_violations_name_biases_and_coil_currents_beyond_the_limit():
    small = rig.PAPER_RIG.bearing.with_(max_current=1.5)
    spec = rig.RigSpec(bearing=small)
    proto = P.perturbation((1.4, 1.6), (20e-6,), center=(-33.3e-6, 11.3e-6))
    found = limits.limit_violations(spec, proto)
    assert [f.kind for f in found] == ["bias"] * 4 and all(f.value == 1.6 for f in found)
    # the coil currents of a 1.4 A bias carrying the rotor exceed 1.5 A on the top coil
    low = P.perturbation((1.4, 1.45), (20e-6,), center=(-33.3e-6, 11.3e-6))
    sim = _sim(low, spec=spec)
    found = limits.limit_violations(spec, low, currents=sim.physical_currents)
    assert found and all(f.kind == "current" for f in found)
    worst = max(found, key=lambda f: f.value)
    assert worst.value == pytest.approx(sim.physical_currents.max(), rel=1e-12) and worst.value > 1.5
    assert "top coil" in str(worst) and "coil current limit of 1.5 A" in str(worst)


def test_a_protocols_steps_are_its_set_points_biases_and_loads_in_order():
    """The steps a rig operator runs by are the steps the rig records: each step's set-points, biases, load, experiment
    and time, as the contract CSV of that protocol holds them (a row per axis)."""
    p = P.rich(center=(10e-6, -5e-6))
    steps = p.steps()
    data = rig.simulate(rig.PAPER_RIG, p, seed=0).data
    assert len(steps) == len(p) and list(steps["step"]) == list(range(1, len(p) + 1))
    for axis in ("v", "w"):
        rows = data[data["axis"] == axis].reset_index(drop=True)
        np.testing.assert_allclose(steps["v_set_um"], rows["v_set_um"], atol=1e-9)
        np.testing.assert_allclose(steps["w_set_um"], rows["w_set_um"], atol=1e-9)
        np.testing.assert_allclose(steps[f"bias_{axis}_A"], rows["bias_A"])
        np.testing.assert_allclose(steps["time_s"], rows["time_s"])
        assert list(steps["load_id"]) == list(rows["load_id"]) and list(steps["experiment"]) == list(rows["experiment"])
        known = rows["load_N"].notna()
        np.testing.assert_allclose(steps[f"load_{axis}_N"][known], rows["load_N"][known])
