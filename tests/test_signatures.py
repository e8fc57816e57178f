"""A family named by its signature whatever its law (issue 23): the basis groups, the verdict's thresholds, and the
diagnosis on laws other than the library's."""

import types

import numpy as np
import pytest

import ambfit
from ambfit import rig
from ambfit.diagnosis.verdict import Judge, choose_law, confounded
from ambfit.estimation.basis import FAMILY_GROUPS, Basis
from ambfit.estimation.discrepancy import fit_discrepancy
from ambfit.physics import effects as E
from ambfit.physics.bearing import PAPER_BEARING
from ambfit.rig import laws, protocol


@pytest.fixture(scope="module")
def design():
    return protocol.serpentine(seed=4)


def _simulate(design, law, seed=7):
    rng = np.random.default_rng(seed)
    effect = law.random(rng) if isinstance(law, type) else law
    return laws.as_recorded(rig.simulate(rig.PAPER_RIG, design, [effect], seed=rng).data)


# each other-law effect, the family whose signature should express it, and the host law: the family's library law,
# or the ideal law where the library's law already takes most of it (a calibration curve's offset and gain)
CASES = [
    (laws.ExponentialTimeDrift, "thermal_drift", [E.ThermalDrift()]),
    (laws.MinorLoopHysteresis, "hysteresis", [E.Hysteresis()]),
    (laws.PositionNonlinearity(gain=np.array([0.04, -0.03]), curve=np.array([0.05, -0.06])), "position_gain", []),
    (laws.ChannelCalibration, "current_offset", []),
    (laws.CurrentCoupling, "cross_coupling", [E.CrossCoupling()]),
]


@pytest.mark.parametrize("law, family, host", CASES, ids=[c[1] for c in CASES])
def test_a_familys_signature_expresses_a_law_the_library_lacks(design, law, family, host):
    """The host law widened by the family's signature reaches the noise floor in sample (mean z² below 1.25: a
    smooth basis expresses the law up to a little left in the noise), from well above it."""
    data = _simulate(design, law)
    res = ambfit.fit(data, host, throw=False)
    d = fit_discrepancy(res, data, groups=FAMILY_GROUPS[family])
    kept = res.fitted_rows
    before = float(np.mean(res.residuals[kept] ** 2))
    after = float(np.mean((res.residuals + d.row_correction)[kept] ** 2))
    assert before > 1.5 and after < 1.25, (family, before, after)
    assert max(d.log_bayes.values()) > 10


def test_the_drift_basis_follows_the_readings_clock(design):
    # time scaled by the data's span; a drift column is zero at each experiment's first reading
    data = _simulate(design, laws.LinearTimeDrift)
    from ambfit.rows import readings

    r = readings(data)
    basis = Basis.of(PAPER_BEARING, ("drift",), r)
    assert basis.t_ref == pytest.approx(float(np.max(np.asarray(r.time))))
    m = basis.matrix(r)
    first = np.asarray(r.time) == 0
    assert first.any() and np.all(m[first] == 0) and np.any(m[~first] != 0)


def test_the_memory_basis_needs_the_order_of_readings(design):
    data = _simulate(design, laws.MinorLoopHysteresis)
    from ambfit.rows import readings

    with pytest.raises(ValueError, match="memory"):
        Basis.of(PAPER_BEARING, ("memory",)).matrix(readings(data))


def _model(score, before_score=4.0):
    """A stand-in model with a held-out score (mean z²) and the ideal law's score before."""
    after = np.sqrt(max(score - 1, 0))
    before = np.sqrt(before_score - 1)
    return types.SimpleNamespace(score=score, after=after, shrink=1 - after / before, effect="x")


def test_judge_thresholds_follow_the_standard_error_of_a_mean_of_squares():
    judge = Judge(n=800, ideal_score=4.0)
    se = np.sqrt(2 / 800)
    assert judge.floor == pytest.approx(1 + 3 * se)
    assert judge.at_floor(_model(1 + 2.9 * se)) and not judge.at_floor(_model(1 + 3.1 * se))
    # better: lower by more than three standard errors of the other's score
    assert judge.better(_model(1.01), _model(1.2)) and not judge.better(_model(1.03), _model(1.2))   # 1.2 (1 - 3 se)
    # explains: half the excess removed and less than one noise unit left
    assert judge.explains(_model(1.8, 10.0)) and not judge.explains(_model(2.2, 10.0))    # after 0.89 / 1.10
    assert not judge.explains(_model(1.5, before_score=1.6))                        # removes 0.09 only


def test_a_weak_effect_is_explained_by_reaching_the_floor():
    # the ideal law 0.43 noise units above the floor (mean z² 1.185 on 840 readings), a model at the floor removes
    # less than half of that excess, which near the floor is mostly noise: it explains the data all the same
    judge = Judge(n=840, ideal_score=1.185)
    weak = _model(1.05, before_score=1.185)
    assert weak.shrink < 0.5 and judge.explains(weak)
    assert not Judge(n=840, ideal_score=1.05).explains(_model(1.04, before_score=1.05))   # the ideal at the floor too


def test_a_pair_wins_only_when_needed():
    judge = Judge(n=800, ideal_score=30.0)
    single, pair = _model(1.4, 30.0), _model(1.02, 30.0)
    single.effect, pair.effect = "saturation", "saturation+current_offset"
    assert choose_law(judge, [single], [pair], pair_verdict=True) is pair         # significantly better
    assert choose_law(judge, [single], [pair], pair_verdict=False) is single
    close = _model(1.38, 30.0)
    close.effect = "saturation+leakage"
    assert choose_law(judge, [single], [close], pair_verdict=True) is single      # not significantly better
    assert confounded(judge, single, [single, close]) == ["saturation+leakage"]
    # at the floor, every model at the floor is consistent with noise: none can be told from the verdict's
    low, far = _model(0.9, 30.0), _model(1.0 + 2.8 * judge.se(), 30.0)
    low.effect, far.effect = "fringing+current_gain", "position_gain"
    assert not judge.close(far, low.score) and confounded(judge, low, [low, far]) == ["position_gain"]
    assert confounded(judge, low, [low, _model(1.0 + 3.2 * judge.se(), 30.0)]) == []


def test_memory_hysteresis_is_named_by_its_signature(design):
    """A play much wider than the library's, felt in part: the library's hysteresis law leaves most of it, the
    hysteresis family's signature (direction and path of each coil current) reaches it held out."""
    data = _simulate(design, laws.MinorLoopHysteresis, seed=11)
    d = ambfit.diagnose(data, check_force=False, discrepancy=False)
    assert d.verdict == "hysteresis", d.summary()
    assert d.law["signature"] == "hysteresis+memory" and d.grade["by"] == "signature"
    assert d.law["library_law_shrink"] < 0.5 < d.law["shrink"] == d.shrink
