"""Eq. 5-7: exact recovery on noise-free rig data, the paper's validity checks, averaging."""

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ambfit import rig
from ambfit.estimation import closed_form as cf
from ambfit.estimation.fit import fit_many
from ambfit.rig import protocol as P

NF = rig.NOISE_FREE


def least_squares(rows):
    """Least squares on the rows of a closed-form estimate, or the error its fit raised (the reference)."""
    return fit_many([rows])[0]


@given(
    g_v=st.floats(550e-6, 1000e-6), g_w=st.floats(550e-6, 1000e-6),
    x_v=st.floats(-60e-6, 60e-6), x_w=st.floats(-60e-6, 60e-6),
    b1=st.floats(0.9, 1.6), db=st.floats(0.08, 0.5), d=st.floats(8e-6, 60e-6),
    cv=st.floats(-40e-6, 40e-6), cw=st.floats(-40e-6, 40e-6),
)
def test_recovers_truth_on_noise_free_symmetric_designs(g_v, g_w, x_v, x_w, b1, db, d, cv, cw):
    spec = rig.PAPER_RIG.with_truth(g0=(g_v, g_w), x0=(x_v, x_w))
    sim = rig.simulate(spec, P.perturbation((b1, b1 + db), (d,), center=(cv, cw), iterations=2), noise=NF)
    res = cf.identify(sim.data)
    for a, ax in enumerate("vw"):
        est = res.estimates[("all", ax)]
        assert est.g0 == pytest.approx((g_v, g_w)[a], rel=1e-6)
        # origin: 1e-6 relative to the gap (the origin itself may be near zero)
        assert abs(est.x0 - (x_v, x_w)[a]) < 1e-6 * (g_v, g_w)[a]
        assert est.k == pytest.approx(spec.force_constant, rel=1e-6)
        assert not est.rejected


def test_readings_share_a_position_within_the_tolerance_and_each_group_prefers_its_set_points():
    """One grouping serves the closed form's iterations and the fit's seeds (:func:`equations.position_labels`):
    measured positions within ``POSITION_TOLERANCE`` (2 µm) are one position; a group whose every row has a
    set-point is grouped by set-points, a group with one missing falls back to its measured positions."""
    from ambfit.estimation.closed_form.equations import position_labels

    df = pd.DataFrame({"axis": ["v"] * 4 + ["w"] * 4,
                       "v_um": [-20.0, 20.0, -19.0, 21.5, 0.0, 0.0, 0.0, 0.0],
                       "w_um": [0.0] * 4 + [5.0, 5.5, -5.0, 9.0],
                       "v_set_um": [-20.0, 20.0, -20.0, 20.0] + [np.nan] * 4,
                       "w_set_um": [np.nan] * 4 + [-5.0, -5.0, 5.0, np.nan]})
    np.testing.assert_array_equal(position_labels(df, np.repeat([0, 1], 4)), [0, 1, 0, 1, 1, 1, 0, 2])
    # alone, the v rows are one group as before; their measured positions 1.5 µm apart would be one position too
    np.testing.assert_array_equal(position_labels(df.iloc[:4].drop(columns="v_set_um")), [0, 1, 0, 1])


def test_several_position_pairs_use_least_squares():
    sim = rig.simulate(rig.PAPER_RIG, P.perturbation((1.4, 1.6), (20e-6, 40e-6)), noise=NF)
    sol = cf.solve_rows(sim.data[sim.data.axis == "v"])
    assert len(sol.positions) == 4
    assert sol.g0 == pytest.approx(775e-6, rel=1e-9) and sol.x0 == pytest.approx(33.3e-6, rel=1e-8)


def test_ratio_checks():
    assert cf.ratio(1.6, 1.2, 1.7, 1.3) == pytest.approx(math.sqrt((1.6**2 - 1.7**2) / (1.2**2 - 1.3**2)))
    with pytest.raises(cf.ClosedFormError, match="not positive"):
        cf.ratio(1.6, 1.3, 1.7, 1.2)   # top rises while bottom falls
    with pytest.raises(cf.ClosedFormError, match="two different biases"):
        cf.ratio(1.6, 1.2, 1.7, 1.2)


def test_coinciding_positions():
    with pytest.raises(cf.ClosedFormError, match="coincide"):
        cf.solve([20e-6, 20.5e-6], [[1.6, 1.7], [1.6, 1.7]], [[1.2, 1.3], [1.2, 1.3]])


def test_singular_system():
    # identical ratios at two different positions: the rows of A are equal
    with pytest.raises(cf.ClosedFormError, match="singular"):
        cf.solve([20e-6, -20e-6], [[1.6, 1.7], [1.6, 1.7]], [[1.2, 1.3], [1.2, 1.3]])


def test_non_physical_solution():
    # P = 1 at +20 µm puts the origin at -20 µm; P = 0.9 at -20 µm then needs a negative gap
    ib2 = math.sqrt(1.0 + 1.25 / 0.81)
    with pytest.raises(cf.ClosedFormError, match="non-physical"):
        cf.solve([20e-6, -20e-6], [[1.5, 1.0], [1.5, 1.0]], [[1.5, 1.0], [ib2, 1.0]])


def test_single_position_is_rejected_with_a_reason():
    sim = rig.simulate(rig.PAPER_RIG, P.grid([(10e-6, 10e-6)], [1.4, 1.6]), noise=NF)
    with pytest.raises(cf.ClosedFormError, match="two positions"):
        cf.identify(sim.data)


def test_three_biases_are_rejected_with_a_reason():
    sim = rig.simulate(rig.PAPER_RIG, P.perturbation((1.2, 1.4, 1.6), (20e-6,)), noise=NF)
    with pytest.raises(cf.ClosedFormError, match="exactly two bias"):
        cf.identify(sim.data)


def test_no_known_load_means_no_k():
    loads = {"u": P.Load(5.0, 4.0, known=False)}
    sim = rig.simulate(rig.PAPER_RIG, P.perturbation((1.4, 1.6), (20e-6,), load="u", loads=loads), noise=NF)
    res = cf.identify(sim.data)
    assert math.isnan(res.estimates[("all", "v")].k)
    params = res.to_json()["params"]
    assert "k_v_Nm2_per_A2" not in params and params["g_v0_um"]["value"] == pytest.approx(775.0, rel=1e-6)


def test_mean_and_standard_error_over_iterations():
    sim = rig.simulate(rig.PAPER_RIG, P.paper_table2(iterations=10, center=(-33.3e-6, 11.3e-6)), seed=4)
    est = cf.identify(sim.data).estimates[("all", "v")]
    g = np.array([s.g0 for s in est.iterations.values()])
    assert est.n == 10
    assert est.g0 == pytest.approx(g.mean()) and est.g0_sem == pytest.approx(g.std(ddof=1) / math.sqrt(10))
    # with 0.6 mA noise the per-iteration gap scatter is tens of µm (the paper's Table 2 scale)
    assert 10e-6 < est.g0_std < 80e-6


def test_by_experiment_and_contract_json():
    a = rig.simulate(rig.PAPER_RIG, P.perturbation((1.4, 1.5), (20e-6,), iterations=3, experiment="1"), noise=NF)
    b = rig.simulate(rig.PAPER_RIG, P.perturbation((1.4, 1.6), (20e-6,), iterations=3, experiment="2"), noise=NF)
    res = cf.identify(pd.concat([a.data, b.data], ignore_index=True), by_experiment=True)
    js = res.to_json()
    assert js["method"] == "closed_form" and js["converged"] is True and js["n_rows"] == 48
    assert set(js["experiments"]) == {"1", "2"}
    for key in ("g_v0_um", "v0_um", "g_w0_um", "w0_um", "k_v_Nm2_per_A2", "k_w_Nm2_per_A2"):
        assert set(js["params"][key]) == {"value", "std"}


def test_noisy_iteration_with_negative_radicand_is_rejected_not_nan():
    sim = rig.simulate(rig.PAPER_RIG, P.paper_table2(iterations=6), noise=rig.Noise(0.6e-3, 0.1e-6), seed=0)
    df = sim.data.copy()
    # break one iteration: swap the top currents of its two biases at one position
    idx = df.index[(df.axis == "v") & (df.iteration == 3)][:2]
    df.loc[idx, "i_top_A"] = df.loc[idx[::-1], "i_top_A"].to_numpy()
    est = cf.identify(df).estimates[("all", "v")]
    assert "3" in " ".join(str(k) for k in est.rejected) and est.n == 5
    assert np.isfinite(est.g0)


def test_interval_uses_student_t_with_n_minus_1_dof():
    # ten iterations: the standard error is estimated from 9 dof, so 95 % is ± 2.262 sem (Student t table,
    # t(0.975, 9) = 2.2622), not the normal 1.96 that covered 88-91 % on the rig (closed_form_coverage.py)
    sim = rig.simulate(rig.PAPER_RIG, P.paper_table2(iterations=10, center=(-33.3e-6, 11.3e-6)), seed=3)
    res = cf.identify(sim.data)
    for ax in "vw":
        est = res.estimates[("all", ax)]
        assert est.n == 10
        for name in ("g0", "x0"):
            lo, hi = est.interval(name)
            half = (hi - lo) / 2
            assert half / getattr(est, f"{name}_sem") == pytest.approx(2.2622, abs=1e-4)
            assert (lo + hi) / 2 == pytest.approx(getattr(est, name), rel=1e-12)
    detail = res.to_json()["detail"]["all"]["v"]["interval"]
    assert detail["dof"] == 9 and detail["level"] == 0.95


def test_biased_mean_at_three_times_the_noise_is_flagged_not_returned():
    # 3x the paper's noise, seed 40: axis w's closed-form mean is more than 4 standard errors off the truth
    # (Eq. 6-7 are nonlinear in the noisy currents); least squares on the same readings is not, and says so
    spec = rig.PAPER_RIG
    proto = P.paper_table2(iterations=10, center=spec.centre)
    sim = rig.simulate(spec, proto, noise=rig.Noise(1.8e-3, 0.3e-6), seed=40)
    res = cf.identify(sim.data, reference=least_squares)
    est = res.estimates[("all", "w")]
    assert abs(est.g0 - spec.g0[1]) > 4 * est.g0_sem          # the case is really wrong beyond its error bar
    name, ok, text = next(c for c in est.checks() if c[0] == "agrees_with_least_squares")
    assert ok is False and "least squares" in text and "biased" in text
    assert not res.trusted and any("least squares" in h for h in res.health())
    # the paper's noise (another seed: at 1x the check fires on 1.7 % of data sets, seed 40 among them): no flag
    clean = cf.identify(rig.simulate(spec, proto, seed=1).data, reference=least_squares)
    assert all(ok is not False for name, ok, _ in clean.checks() if name == "agrees_with_least_squares")
    # the closed form does not fit by itself: without a reference the check cannot be judged, and says why
    alone = cf.identify(sim.data).estimates[("all", "w")]
    name, ok, text = next(c for c in alone.checks() if c[0] == "agrees_with_least_squares")
    assert ok is None and "no least-squares reference" in text


def test_each_experiment_is_compared_with_its_own_least_squares_fit():
    # with by_experiment the reference is a function of the rows, called once per experiment; a fit of all rows
    # cannot be compared with each experiment's mean and is refused
    a = rig.simulate(rig.PAPER_RIG, P.perturbation((1.4, 1.6), (20e-6,), iterations=3, experiment="a"), seed=1).data
    b = rig.simulate(rig.PAPER_RIG, P.perturbation((1.4, 1.6), (20e-6,), iterations=3, experiment="b"), seed=2).data
    both = pd.concat([a, b], ignore_index=True)
    seen = []

    def fit(rows):
        seen.append(sorted(set(rows["experiment"])))
        return least_squares(rows)

    res = cf.identify(both, by_experiment=True, reference=fit)
    assert seen == [["a"], ["b"]]
    for (exp, ax), est in res.estimates.items():
        own = least_squares(both[both.experiment == exp]).value(f"g_{ax}0")
        assert est.reference.g0 == pytest.approx(own, rel=1e-9)
    with pytest.raises(ValueError, match="by_experiment"):
        cf.identify(both, by_experiment=True, reference=least_squares(both))


def test_a_least_squares_solution_that_closes_a_pole_gap_is_refused():
    # with two positions a positive gap and positive ratios P keep every |u| below g0 by themselves; with three
    # the least-squares solution need not: these ratios (inconsistent, as noise makes them) give g0 = 4.4 µm > 0
    # with the rotor 19 µm off centre, a closed gap, which the guard must refuse rather than report
    p = np.array([0.65, 1.25, 0.6])
    x = np.array([-20e-6, 0.0, 20e-6])
    a, rhs = cf.eq7_system(p, x, rig.PAPER_RIG.bearing.cos_alpha)
    g0 = np.linalg.lstsq(a, rhs, rcond=None)[0][0]
    assert 0 < g0 < 20e-6                                   # positive gap, smaller than the excursions
    it = [[math.sqrt(1.0 + q**2 * (1.2**2 - 1.0)), 1.0] for q in p]   # Eq. 6 gives back exactly these P
    with pytest.raises(cf.ClosedFormError, match="non-physical"):
        cf.solve(x, it, [[1.2, 1.0]] * 3)


def test_a_position_without_its_second_bias_is_named():
    sim = rig.simulate(rig.PAPER_RIG, P.paper_table2(iterations=1), noise=NF)
    rows = sim.data[sim.data.axis == "v"]
    gone = rows[(rows["bias_A"] == rows["bias_A"].max()) & (rows["v_set_um"] > 0)].index
    with pytest.raises(cf.ClosedFormError, match=r"has no reading at bias 1\.6 A: each position needs both"):
        cf.solve_rows(rows.drop(gone))


def test_a_position_whose_biases_carry_different_loads_is_refused():
    # Eq. 5 cancels the load between the two biases: a different load at one of them is a different equation
    sim = rig.simulate(rig.PAPER_RIG, P.paper_table2(iterations=1), noise=NF)
    rows = sim.data[sim.data.axis == "v"].copy()
    rows["load_id"] = "rotor"
    rows.loc[(rows["bias_A"] == rows["bias_A"].max()) & (rows["v_set_um"] > 0), "load_id"] = "rotor+mass"
    with pytest.raises(cf.ClosedFormError, match="carry different loads .* Eq. 5 needs the same load"):
        cf.solve_rows(rows)


def test_the_public_closed_form_is_checked_against_least_squares():
    """``ambfit.closed_form(data)`` compares its mean with least squares on the same readings, as the command line
    does; the closed form alone (below the fit) is not compared."""
    import ambfit
    from ambfit.estimation import closed_form as cf

    data = ambfit.read_csv(Path(__file__).parents[1] / "data" / "paper_table2.csv")
    judged = [ok for name, ok, _ in ambfit.closed_form(data).checks() if name == "agrees_with_least_squares"]
    alone = [ok for name, ok, _ in cf.identify(data).checks() if name == "agrees_with_least_squares"]
    assert judged == [True, True] and alone == [None, None]


def test_the_predicted_gap_scatter_is_the_forward_differences_of_re_solving():
    """The predicted scatter of one iteration's gap (all forward differences solved at once) against re-solving
    Eq. 6-7 once per moved current, here, on random iterations of 2-5 positions; NaN exactly where a moved
    current makes one of those solves fail."""
    from ambfit.estimation.closed_form.equations import ClosedFormError, _predicted_std
    from ambfit.physics.bearing import PAPER_BEARING

    def by_loop(x, it, ib, sigma, h=1e-7):
        base = cf.solve(x, it, ib, _propagate=False).g0
        grads = []
        for cur in (it, ib):
            for idx in np.ndindex(cur.shape):
                moved = cur.copy()
                moved[idx] += h
                try:
                    g = cf.solve(x, *((moved, ib) if cur is it else (it, moved)), _propagate=False).g0
                except ClosedFormError:
                    return math.nan
                grads.append((g - base) / h)
        return float(np.sqrt(np.sum(np.square(grads))) * sigma)

    rng = np.random.default_rng(4)
    compared = 0
    for _ in range(300):
        n = int(rng.integers(2, 6))
        x = np.sort(rng.uniform(-40e-6, 40e-6, n)) + np.arange(n) * 5e-6
        it = 1.5 + rng.normal(0.0, 0.02, (n, 2))
        ib = 1.5 + rng.normal(0.0, 0.02, (n, 2))
        it[:, 1] -= rng.uniform(-0.3, 0.3)
        ib[:, 1] -= rng.uniform(-0.3, 0.3)
        try:
            cf.solve(x, it, ib, _propagate=False)
        except ClosedFormError:
            continue
        want, got = by_loop(x, it, ib, 6e-4), _predicted_std(x, it, ib, 6e-4, 1, PAPER_BEARING)
        assert math.isnan(want) == math.isnan(got)
        if not math.isnan(want):
            assert got == pytest.approx(want, rel=1e-7)
            compared += 1
    assert compared > 30
