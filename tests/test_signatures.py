"""A family named by its signature whatever its law (issue 23): the basis groups, the verdict's thresholds, and the
diagnosis on laws other than the library's."""

import dataclasses

import numpy as np
import pytest

import ambfit
from ambfit import rig
from ambfit.estimation.basis import FAMILY_GROUPS, Basis
from ambfit.estimation.discrepancy import fit_discrepancy
from ambfit.physics import effects as E
from ambfit.physics.bearing import PAPER_BEARING
from ambfit.rig import laws, protocol, zoo_magnetic, zoo_measurement


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
    (laws.RelaxingHysteresis, "hysteresis", [E.Hysteresis()]),
    (laws.PositionNonlinearity(gain=np.array([0.04, -0.03]), curve=np.array([0.05, -0.06])), "position_gain", []),
    (laws.ChannelCalibration, "current_offset", []),
    (laws.CurrentCoupling, "cross_coupling", [E.CrossCoupling()]),
    # through the cube of the other axis' displacement from the bearing centre (its origin unknown to the basis),
    # scaled by this axis' mean current squared: powers of order one, a constant part, a current scale
    (zoo_magnetic.PositionCoupling(coef=np.array([[0.0, 0.0, 0.08], [0.0, 0.0, -0.08]]), power=np.array([2.0, 2.0])),
     "cross_coupling", [E.CrossCoupling()]),
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


def test_a_sensor_ripple_is_followed_by_the_position_splines_not_the_polynomials():
    """A probe's ripple of 1 µm over 30 and 45 µm beside a gentle bend, read at the many set-points of an
    improvised protocol (a serpentine's few positions are fitted by any curve): the polynomials of order four
    leave most of it, the splines of the reading reach the noise."""
    from ambfit.rig import zoo

    law = zoo_measurement.SensorCharacteristic(coef=np.array([[0.0, 0.02, 0.0], [0.0, -0.02, 0.0]]),
                                               amp=np.array([[1e-6, 0.0], [0.0, 1e-6]]),
                                               wavelength=np.array([[30e-6, 30e-6], [45e-6, 45e-6]]),
                                               phase=np.array([[0.5, 0.0], [0.0, 2.0]]))
    data = _simulate(zoo.random_protocol(np.random.default_rng(0)), law)
    res = ambfit.fit(data, throw=False)
    kept = res.fitted_rows

    def left(groups):
        return float(np.mean((res.residuals + fit_discrepancy(res, data, groups=groups).row_correction)[kept] ** 2))

    assert float(np.mean(res.residuals[kept] ** 2)) > 5.0
    assert left(("position_sensor",)) > 5.0
    assert left(FAMILY_GROUPS["position_gain"]) < 1.25


def test_a_coils_path_runs_on_across_experiments_read_on_one_clock():
    """A play of 43 mA on an improvised protocol of nine experiments read one after another (one clock): the memory
    group, fitted on the other loads, predicts each load's readings.  Measured: held-out mean z² 12.1 (the ideal law
    1352 in sample; 5.2 with plays 20 % apart in width, a grid not kept: reports/gap/rules.md); with each
    experiment's history restarted from zero current 8313."""
    from ambfit.diagnosis.heldout import folds
    from ambfit.rig import zoo

    data = rig.simulate(rig.PAPER_RIG, zoo.random_protocol(np.random.default_rng(1)), [E.Hysteresis(width=0.043)],
                        seed=1).data
    assert data["experiment"].nunique() == 9
    res = ambfit.fit(data, throw=False)
    _, tests = folds(data)
    z = np.asarray(res.residuals)
    held = np.concatenate([(z + fit_discrepancy(res, data, groups=("memory",), mask=(~t).astype(float))
                            .row_correction)[t] for t in tests])
    assert float(np.mean(z**2)) > 1000.0
    assert float(np.mean(held**2)) < 30.0


def test_a_drift_that_steps_in_the_middle_of_the_run_is_predicted_from_the_other_loads(design):
    """An origin that shifts by 6 and -4 µm within 3 % of the run, at 45 % of it, under a serpentine whose four
    loads are four blocks of time: the drift signature, fitted on three blocks, predicts the fourth.  Measured:
    held-out mean z² 5.1 (the ideal law 41 in sample; the step falls inside a held-out block, where no reading shows
    when); with the powers and settling curves of time alone (no steps), 24,000: they extrapolate over each held-out
    block."""
    from ambfit.diagnosis.heldout import folds
    from ambfit.rig.zoo_measurement import TimeDrift
    from ambfit.rig.zoo_shapes import SLOTS, Shape

    w, a, s = np.zeros((4, SLOTS)), np.ones((4, SLOTS)), np.ones((4, SLOTS))
    w[1, 0], a[1, 0], s[1, 0] = 1.0, 0.45, 0.03           # one sigmoid step: weight, centre, width
    step = Shape(w, a, s)
    law = TimeDrift(origin_drift=np.array([6e-6, -4e-6]), gap_drift=np.array([0.0, 0.0]),
                    duration=np.asarray(float(design.time[-1])), shape_v=step, shape_w=step, shape_gap=step)
    data = _simulate(design, law)
    res = ambfit.fit(data, throw=False)
    name, tests = folds(data)
    z = np.asarray(res.residuals)

    def held_out(groups):
        return float(np.mean(np.concatenate([(z + fit_discrepancy(res, data, groups=groups, mask=(~t).astype(float))
                                              .row_correction)[t] for t in tests]) ** 2))

    assert name == "leave-one-load-out" and float(np.mean(z**2)) > 30.0
    # 10: twice the measured 5.1 (other noise seeds give 5.8-7.0); a step at 20 or 80 % of the run, inside the
    # first or last block, is extrapolated whatever the basis (41-48 with the steps), and is not this test's case
    assert held_out(FAMILY_GROUPS["thermal_drift"]) < 10.0
    assert held_out(("drift",)) > 1000.0


@pytest.mark.parametrize("group", ["drift", "drift_steps"])
def test_the_drift_basis_follows_the_readings_clock(design, group):
    # time scaled by the data's span; a drift column is zero at each experiment's first reading, and every one is
    # zero without a clock (a term of the readings alone would not be a drift)
    data = _simulate(design, laws.LinearTimeDrift)
    from ambfit.rows import readings

    r = readings(data)
    basis = Basis.of(PAPER_BEARING, (group,), r)
    assert basis.t_ref == pytest.approx(float(np.max(np.asarray(r.time))))
    m = basis.matrix(r)
    first = np.asarray(r.time) == 0
    assert first.any() and np.all(m[first] == 0) and np.any(m[~first] != 0)
    untimed = readings(data.drop(columns="time_s"))
    assert np.all(Basis.of(PAPER_BEARING, (group,), untimed).matrix(untimed) == 0)


@pytest.mark.parametrize("group", ["memory", "fading"])
def test_the_path_bases_need_the_order_of_readings(design, group):
    data = _simulate(design, laws.MinorLoopHysteresis)
    from ambfit.rows import readings

    with pytest.raises(ValueError, match=group):
        Basis.of(PAPER_BEARING, (group,)).matrix(readings(data))


def test_every_groups_terms_name_its_columns(design):
    from ambfit.data import zero_based
    from ambfit.estimation.basis import ALL_GROUPS
    from ambfit.rows import readings

    df = zero_based(_simulate(design, laws.RelaxingHysteresis))
    r = readings(df)
    for group in ALL_GROUPS:
        basis = Basis.of(PAPER_BEARING, (group,), r)
        assert len(basis.terms()) == basis.matrix(r, df).shape[1] > 0, group


def test_memory_hysteresis_is_named_by_its_signature(design):
    """A play much wider than the library's, felt in part: the library's hysteresis law leaves most of it, the
    hysteresis family's signature (direction and path of each coil current) reaches it held out."""
    data = _simulate(design, laws.MinorLoopHysteresis, seed=11)
    d = ambfit.diagnose(data, check_force=False, discrepancy=False)
    assert d.verdict == "hysteresis", d.summary()
    assert d.law.groups == FAMILY_GROUPS["hysteresis"] and d.grade.by == "signature"
    assert d.law.law.shrink < 0.5 < d.law.shrink == d.shrink
    from ambfit.diagnosis import text

    said = next(f for f in text.findings(d) if f.startswith("hysteresis's signature"))
    assert " in its residuals: " in said and "the library's hysteresis law shrinks" in said
    assert said.endswith(": the family is hysteresis, its law differs from the library's")


def test_on_clean_data_no_widened_law_predicts_better_than_the_ideal_law(design):
    """The ideal law is the truth here: a family's signature that predicted held-out readings clearly better would
    be regressing on the readings' noise (a term steep in a noisy reading, at set-points the grid repeats)."""
    from ambfit.diagnosis.scoring import Scorer
    from ambfit.diagnosis.signatures import widened
    from ambfit.diagnosis.threads import _Each
    from ambfit.diagnosis.verdict import Judge, Rules

    data = rig.simulate(rig.PAPER_RIG, design, [], seed=11).data
    with _Each(2) as each:
        ideal, = Scorer(data, ambfit.fit(data), bearing=PAPER_BEARING, noise={}, max_steps=60, each=each).laws([()])
    judge = Judge(len(ideal.heldout_z), ideal.score, Rules())
    for family, groups in FAMILY_GROUPS.items():
        assert not judge.clearly_better(widened(ideal, data, groups, {}), ideal), family


def test_the_lagged_temperature_is_a_first_order_lag_in_time_order():
    from ambfit.estimation.basis import _lagged

    tau = np.array([0.3, 0.0, 0.1, 0.2, 0.2, 0.4])              # out of order, a moment read twice
    step = np.array([1.0, 0.0, 1.0, 1.0, 1.0, 1.0])             # a step at tau = 0.1
    got = _lagged(tau, step, 0.1)
    np.testing.assert_allclose(got[[1, 2, 3, 0, 5]], 1.0 - np.exp(-np.array([0.0, 1.0, 2.0, 3.0, 4.0])), rtol=1e-12)
    assert got[3] == got[4]                                      # one moment, one state
    gap = step.copy()
    gap[0] = np.nan                                              # a reading without a temperature holds the lag
    held = _lagged(tau, gap, 0.1)
    assert held[0] == held[3] and held[5] > held[0]
    assert np.all(_lagged(tau, np.full(6, np.nan), 0.1) == 0.0)


def test_a_signature_is_wanted_where_its_law_saw_outliers():
    """A play hysteresis (the law zoo's study seed 3131, draw 142: a rich protocol, the play's widths growing with
    the current) that the library's hysteresis law fits on most readings and sets aside as outliers where the loop
    is widest.  On the rows the law's fit kept, its signature is not clearly wanted; on every reading (the outliers
    too) it is.  Every law at the noise floor sets those readings aside, so the diagnosis leaves them out of its
    scores (:func:`ambfit.diagnosis.heldout.gross_errors`), and names hysteresis from the others."""
    from ambfit.diagnosis.signatures import widened
    from ambfit.diagnosis.verdict import Rules
    from ambfit.rig import zoo

    _, data = zoo.draw(np.random.default_rng(np.random.SeedSequence(3131).spawn(143)[142]))
    d = ambfit.diagnose(data, check_force=False, discrepancy=False)
    sig = next(s for s in d.signatures if s.family == "hysteresis")
    kept = fit_discrepancy(sig.law.fit, data, groups=sig.groups)
    every = widened(sig.law, data, sig.groups, {})
    assert not sig.law.fit.fitted_rows.all()
    assert max(kept.log_bayes.values()) < Rules().log_bayes_clear < every.log_bayes_max, (kept.log_bayes,
                                                                                         every.log_bayes)
    left = np.zeros(len(data), bool)
    left[np.asarray(d.left_out) - 1] = True
    assert left.any() and np.all(~sig.law.fit.fitted_rows[left])    # what is left out, the law set aside
    assert d.verdict == "hysteresis", d.summary()


@pytest.mark.parametrize("proto", ["serpentine", "rich"])
def test_glitches_in_clean_data_leave_it_on_the_floor(proto):
    """Three position readings 17 noise units off and one current 17 off, in data of the ideal law: the signatures
    are now asked about the law's outliers too, where a glitch is one; the verdict must stay ``none``."""
    design = protocol.serpentine(seed=4) if proto == "serpentine" else protocol.rich()
    df = rig.simulate(rig.PAPER_RIG, design, [], seed=11).data
    rng = np.random.default_rng(11)
    rows = rng.choice(len(df), 3, replace=False)
    df.loc[rows, "v_um"] += rng.choice([-1.0, 1.0], 3) * 17 * df.loc[rows, "v_std_um"]
    df.loc[rows[:1], "i_top_A"] += 17 * df.loc[rows[:1], "i_top_std_A"]
    d = ambfit.diagnose(df, check_force=False, discrepancy=False)
    assert d.verdict == "none", d.summary()


def test_the_signature_is_wanted_on_the_folds_rows_and_only_refitted_when_they_differ(design):
    """Without outliers the folds learn from the fit's own rows and the saved correction's log Bayes factor is the
    signature's; with rows the fit set aside, the factor is that of a correction on them too."""
    import dataclasses

    from ambfit.diagnosis.scoring import Scorer
    from ambfit.diagnosis.signatures import widened
    from ambfit.diagnosis.threads import _Each
    from ambfit.estimation.discrepancy import seen_rows

    data = _simulate(design, laws.MinorLoopHysteresis, seed=11)
    with _Each(2) as each:
        law, = Scorer(data, ambfit.fit(data), bearing=PAPER_BEARING, noise={}, max_steps=60, each=each).laws(
            [(E.Hysteresis(),)])
    groups = FAMILY_GROUPS["hysteresis"]
    kept = widened(dataclasses.replace(law, fit=dataclasses.replace(law.fit, weights=None)), data, groups, {})
    assert kept.log_bayes == kept.full.log_bayes
    weights = np.ones(len(data))
    weights[: len(data) // 10] = 0.0                       # a tenth of the rows set aside as the fit's outliers
    cut = dataclasses.replace(law, fit=dataclasses.replace(law.fit, weights=weights))
    sig = widened(cut, data, groups, {})
    seen = fit_discrepancy(cut.fit, data, groups=groups, mask=seen_rows(cut.fit, np.ones(len(data), bool)))
    assert sig.log_bayes == seen.log_bayes != sig.full.log_bayes
    assert widened(cut, data, groups, {}, wanted=False).log_bayes == sig.full.log_bayes


def test_a_pair_with_one_law_widened_reaches_a_law_the_library_lacks_beside_a_second_effect(design):
    """A play much wider than the library's beside a drift: the library's pair leaves the play, the pair with its
    hysteresis widened by the family's signature (the drift's law beside it) predicts the held-out readings
    clearly better; each of the pair's families is widened in turn."""
    from ambfit.diagnosis.scoring import Scorer
    from ambfit.diagnosis.threads import _Each
    from ambfit.diagnosis.verdict import Judge, Rules

    rng = np.random.default_rng(11)
    data = laws.as_recorded(rig.simulate(rig.PAPER_RIG, design, [laws.MinorLoopHysteresis.random(rng),
                                                                  E.ThermalDrift.random(rng)], seed=rng).data)
    with _Each(2) as each:
        scorer = Scorer(data, ambfit.fit(data), bearing=PAPER_BEARING, noise={}, max_steps=60, each=each)
        ideal, pair = scorer.laws([(), (E.Hysteresis(), E.ThermalDrift())])
        pair = dataclasses.replace(pair, before=ideal.after)
        both = scorer.widened_pairs([pair])
        # two families of one signature: the pair is widened once, by the first's
        (shared,) = scorer.widened_pairs([dataclasses.replace(pair, effect="saturation+leakage")])
    assert shared.family == "saturation" and shared.second == "leakage" and shared.groups == FAMILY_GROUPS["leakage"]
    by = {s.family: s for s in both}
    assert sorted(by) == ["hysteresis", "thermal_drift"] and all(s.kind == "widened_pair" for s in both)
    hyst = by["hysteresis"]
    assert hyst.families == ("hysteresis", "thermal_drift") and hyst.groups == FAMILY_GROUPS["hysteresis"]
    assert hyst.to_json(True)["with"] == "thermal_drift"
    judge = Judge(len(ideal.heldout_z), ideal.score, Rules())
    assert judge.clearly_better(hyst, pair) and hyst.score < pair.score


def test_a_widened_pair_verdict_says_which_law_differs_and_beside_which():
    """With ``Rules(widened_pairs=True)``: a law zoo case (study seed 3131, draw 70: a position sensor's
    characteristic beside a current offset) that no law, pair or widened law explains is named by the pair with its
    position-gain law widened; its record, steps and findings say which law is widened and which stands beside it."""
    from ambfit.diagnosis import text
    from ambfit.diagnosis.verdict import Rules
    from ambfit.rig import zoo

    case, data = zoo.draw(np.random.default_rng(np.random.SeedSequence(3131).spawn(71)[70]))
    assert case.label == "current_offset+position_gain"
    dg = ambfit.diagnose(data, check_force=False, discrepancy=False, rules=Rules(widened_pairs=True))
    assert dg.verdict == "current_offset+position_gain" and dg.grade.by == "widened_pair", dg.summary()
    assert dg.law.family == "position_gain" and dg.law.second == "current_offset"
    law = dg.to_json()["law"]
    assert law["with"] == "current_offset" and law["library_pair"] == "current_offset+position_gain"
    assert [s["model"] for s in dg.steps()] == ["current_offset", "current_offset+position_gain", dg.law.model]
    said = next(f for f in text.findings(dg) if "with its position_gain law widened by that signature" in f)
    assert said.startswith("position_gain's signature (position_sensor+position_spline terms) in the pair's residuals")
    assert said.endswith("the families are current_offset+position_gain; position_gain's law differs from the "
                         "library's, beside current_offset's library law")
