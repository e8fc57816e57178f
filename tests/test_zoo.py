"""The law zoo (ambfit.rig.zoo) draws what benchmarks/gap_zoo.py needs: every law acts on the rig's readings, every
sensor law inverts, and the case draws cover every kind of truth."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ambfit import rig
from ambfit.rig import protocol, zoo
from ambfit.rig.limits import limit_violations
from ambfit.rig.zoo_measurement import NO_FAMILY, Heating

LAWS = [c for f in zoo.FAMILIES for c in zoo.LAWS[f]] + list(NO_FAMILY)
COLUMNS = ["i_top_A", "i_bottom_A", "v_um", "w_um"]


@pytest.fixture(scope="module")
def small():
    """A short protocol around the paper rig's origin under two known loads, and its data without any effect."""
    center = rig.PAPER_RIG.centre
    points = [(center[0] + dv, center[1] + dw) for dv, dw in ((30e-6, 20e-6), (-30e-6, 10e-6), (0.0, -25e-6))]
    loads = {"a": protocol.Load.gravity(1.0), "b": protocol.Load.gravity(2.0)}
    proto = protocol.concat(*(protocol.bias_sweep((1.0, 1.3, 1.6), points, load=k, loads=loads, iteration=j + 1)
                              for j, k in enumerate(loads)))
    return proto, rig.simulate(rig.PAPER_RIG, proto, seed=7).data


@pytest.mark.parametrize("cls", LAWS, ids=lambda c: c.name)
def test_every_law_draws_and_changes_the_readings(cls, small):
    proto, ideal = small
    law = cls.draw(np.random.default_rng(11), float(proto.time[-1]))
    data = rig.simulate(rig.PAPER_RIG, proto, [law], seed=7).data
    change = np.abs(data[COLUMNS].to_numpy() - ideal[COLUMNS].to_numpy()).max(axis=0)
    assert change.max() > 0.0 and np.isfinite(change).all()
    # above the rig's noise (0.6 mA, 0.1 µm) in at least one column: the law is there to be seen
    assert (change / np.array([0.6e-3, 0.6e-3, 0.1, 0.1]) > 1.0).any(), f"{cls.name}: largest change {change}"
    assert law.describe() and all(isinstance(k, str) for k in law.describe())


def test_heating_changes_only_the_temperature(small):
    proto, ideal = small
    data = rig.simulate(rig.PAPER_RIG, proto, [Heating(jnp.asarray(10.0), jnp.asarray(100.0))], seed=7).data
    assert np.array_equal(data[COLUMNS].to_numpy(), ideal[COLUMNS].to_numpy())
    assert data["temperature_C"].iloc[-1] - data["temperature_C"].iloc[0] > 5.0


@pytest.mark.parametrize("cls", [c for c in LAWS if "sense" in vars(c)], ids=lambda c: c.name)
def test_sensor_laws_invert(cls):
    rng = np.random.default_rng(5)
    law = cls.draw(rng, 1000.0)
    axis = np.array([[0, 1]])
    it, ib = rng.uniform(0.0, 2.5, (50, 2)), rng.uniform(0.0, 2.5, (50, 2))
    x, y = rng.uniform(-90e-6, 90e-6, (50, 2)), rng.uniform(-90e-6, 90e-6, (50, 2))
    sensed = law.sense(axis, it, ib, x, y)
    assert not np.allclose(np.concatenate(sensed, axis=1), np.concatenate((it, ib, x, y), axis=1), rtol=0, atol=1e-12)
    back = law.unsense(axis, *sensed)
    for a, b, tol in zip(back, (it, ib, x, y), (1e-12, 1e-12, 1e-15, 1e-15)):
        np.testing.assert_allclose(np.asarray(a), b, rtol=0, atol=tol)
    # the same maps traced, as a fit would call them (numpy draws, jax.numpy under jit)
    traced = jax.jit(lambda e, *a: e.unsense(*a))(law, axis, *sensed)
    for a, b in zip(traced, back):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-18)


def test_cases_cover_every_kind_of_truth():
    cases = [zoo.draw_case(np.random.default_rng(seed)) for seed in range(200)]
    truths = {c.truth for c in cases}
    singles = {t[0] for t in truths if len(t) == 1}
    assert set(zoo.FAMILIES) <= singles
    assert () in truths and ("no_family",) in truths
    assert any(len(t) == 2 for t in truths)
    assert {c.protocol_kind for c in cases} == set(zoo.PROTOCOLS)
    assert {c.kind for c in cases} == set(zoo.KINDS)
    for c in cases:     # each case is within the bearing's back-up clearance, its laws of its truth's families
        assert not limit_violations(c.spec, c.protocol, c.effects)
        assert tuple(sorted({law.family or "no_family" for law in c.laws})) == tuple(sorted(c.truth))


def test_the_zoo_study_scores_a_verdict_and_says_which_wrong_claims_no_verdict_could_avoid():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "gap_zoo.py"
    spec = importlib.util.spec_from_file_location("gap_zoo", path)
    gap_zoo = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gap_zoo)
    pair = ("saturation", "current_offset")
    assert gap_zoo.score(pair, "saturation") == "wrong_claim"
    assert gap_zoo.score(pair, "undecided", ("saturation+current_offset", "saturation+leakage")) == \
        "undecided_with_truth"
    assert gap_zoo.score(pair, "current_offset+saturation") == "right"
    # the missed family, alone, within a noise unit of the floor: no verdict could name it
    assert gap_zoo.unseeable({"missed_alone_excess": {"current_offset": 0.4}})
    assert not gap_zoo.unseeable({"missed_alone_excess": {"current_offset": 1.4}})
    assert not gap_zoo.unseeable({"missed_alone_excess": {"current_offset": None}})
    assert not gap_zoo.unseeable({"missed_alone_excess": None})
    assert not gap_zoo.unseeable({})
