"""The least-squares core: the likelihood (Eq. 4 with effective variance), masks, effect priors,
the covariance when the noise is estimated, and fit health (``FitResult``).

References are computed by hand in the test with the ``math`` module or, for the covariance, from an
analytic Jacobian of Eq. 4 written out here (not the library's automatic derivative).
"""

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

from ambfit import rig
from ambfit.estimation import core, lm
from ambfit.estimation.fit import FitError, fit
from ambfit.physics import effects as E
from ambfit.rig import protocol as P

# Closed-form references of a few float64 operations against the library's (automatically differentiated)
# evaluation: agreement to ~1e-15 is observed; 1e-12 is round-off headroom, far below any formula error.
REL = 1e-12
COS = math.cos(math.radians(22.5))
STD_COLUMNS = ["i_top_std_A", "i_bottom_std_A", "v_std_um", "w_std_um"]

# --- a two-row problem ------------------------------------------------------------------------------------

# one reading per axis, known loads, std columns (the w row's position std differs to check the column used)
TWO_ROWS = pd.DataFrame({
    "axis": ["v", "w"], "bias_A": [1.5, 1.5], "i_top_A": [1.62, 1.71], "i_bottom_A": [1.38, 1.27],
    "v_um": [12.0, 12.0], "w_um": [-7.0, -7.0], "load_N": [6.9, 6.5], "load_id": ["a", "a"],
    "i_top_std_A": [0.6e-3, 0.5e-3], "i_bottom_std_A": [0.7e-3, 0.4e-3], "v_std_um": [0.1, 0.1],
    "w_std_um": [0.2, 0.2],
})
G0, X0, K = (780e-6, 760e-6), (30e-6, -10e-6), (3.4e-6, 3.5e-6)


def eq4_by_hand(a: int):
    """Force misfit [N] and effective noise std [N] of row ``a`` of TWO_ROWS by hand (contract section 1).

    s_eff = sqrt((2 k i_t / g_t^2 s_t)^2 + (2 k i_b / g_b^2 s_b)^2 + (2 k cos(alpha) (i_t^2/g_t^3 + i_b^2/g_b^3) s_x)^2)
    (dF/di_t, dF/di_b and dF/dx of F = k (i_t^2/g_t^2 - i_b^2/g_b^2), dg_t/dx = -cos(alpha), dg_b/dx = +cos(alpha)).
    """
    row = TWO_ROWS.iloc[a]
    x = (row["v_um"] if a == 0 else row["w_um"]) * 1e-6
    s_x = (row["v_std_um"] if a == 0 else row["w_std_um"]) * 1e-6
    it, ib, k = row["i_top_A"], row["i_bottom_A"], K[a]
    gt = G0[a] - (X0[a] + x) * COS
    gb = G0[a] + (X0[a] + x) * COS
    f = k * (it**2 / gt**2 - ib**2 / gb**2)
    s = math.sqrt((2 * k * it / gt**2 * row["i_top_std_A"]) ** 2 + (2 * k * ib / gb**2 * row["i_bottom_std_A"]) ** 2
                  + (2 * k * COS * (it**2 / gt**3 + ib**2 / gb**3) * s_x) ** 2)
    return f - row["load_N"], s


def test_misfit_of_the_ideal_model_is_eq4_with_effective_variance():
    prob, meta = core.build_problem(TWO_ROWS)
    assert meta.k_free == (True, True) and meta.noise_source.count("std columns") == 2
    theta = jnp.asarray(core.to_theta(G0, X0, K))
    f, s = (np.asarray(a) for a in core.misfit(theta, prob))
    for a in range(2):
        f_hand, s_hand = eq4_by_hand(a)
        assert f[a] == pytest.approx(f_hand, rel=REL)
        assert s[a] == pytest.approx(s_hand, rel=REL)
    # the position term is a real part of s_eff here (dropping it changes s_eff by more than 1 %)
    assert float(s[1]) > 1.01 * math.hypot(2 * K[1] * 1.71 / (G0[1] - (X0[1] - 7e-6) * COS) ** 2 * 0.5e-3,
                                           2 * K[1] * 1.27 / (G0[1] + (X0[1] - 7e-6) * COS) ** 2 * 0.4e-3)


def test_automatic_differentiation_through_the_effect_pipeline_matches_eq4():
    # A model with an effect that changes nothing runs the effect pipeline (physics.model.evaluate); the ideal
    # model runs Eq. 4 itself (physics.model.ideal_force).  The one derivative route (forward-mode AD in
    # core.measured) must give both the hand computation above.
    prob, _ = core.build_problem(TWO_ROWS)
    theta = jnp.asarray(core.to_theta(G0, X0, K))
    general = core.Model.of((E.Effect(),))
    assert general.effects and general.n == 0
    f_ad, s_ad = (np.asarray(a) for a in core.misfit(theta, prob, general))
    f_cf, s_cf = (np.asarray(a) for a in core.misfit(theta, prob))
    for a in range(2):
        f_hand, s_hand = eq4_by_hand(a)
        assert f_ad[a] == pytest.approx(f_hand, rel=REL) and s_ad[a] == pytest.approx(s_hand, rel=REL)
    np.testing.assert_allclose(f_ad, f_cf, rtol=REL)
    np.testing.assert_allclose(s_ad, s_cf, rtol=REL)


def test_masked_rows_give_zero_residual_but_keep_their_standardized_residual():
    prob, _ = core.build_problem(TWO_ROWS, mask=[1.0, 0.0])
    theta = jnp.asarray(core.to_theta(G0, X0, K))
    r = np.asarray(core.residuals(theta, prob))
    z = np.asarray(core.standardized(theta, prob))
    hand = [eq4_by_hand(a)[0] / eq4_by_hand(a)[1] for a in range(2)]
    assert r.shape == (2,)                          # ideal model: no prior residuals
    assert r[0] == pytest.approx(hand[0], rel=1e-10) and r[1] == 0.0
    np.testing.assert_allclose(z, hand, rtol=1e-10)   # ratio of two 1e-12 quantities
    assert abs(hand[1]) > 1.0                        # the held-out row does have a misfit to hide


def test_a_held_noise_replaces_the_propagated_one_row_by_row():
    # Nested models compared by their χ² rise hold the full model's noise (Problem.with_noise): the held std
    # replaces s_eff where it is given (> 0), for the ideal law and through the effect pipeline.
    prob, _ = core.build_problem(TWO_ROWS)
    theta = jnp.asarray(core.to_theta(G0, X0, K))
    hand = [eq4_by_hand(a) for a in range(2)]
    held = prob.with_noise([3.0 * hand[0][1], 0.0])           # row 0 held at 3 s_eff, row 1 propagated
    for model in (core.IDEAL, core.Model.of((E.Effect(),))):
        f, s = (np.asarray(a) for a in core.misfit(theta, held, model))
        assert s[0] == pytest.approx(3.0 * hand[0][1], rel=REL) and s[1] == pytest.approx(hand[1][1], rel=REL)
        np.testing.assert_allclose(np.asarray(core.standardized(theta, held, model)),
                                   [hand[0][0] / (3.0 * hand[0][1]), hand[1][0] / hand[1][1]], rtol=1e-10)
    assert np.all(np.asarray(core.build_problem(TWO_ROWS)[0].s_held) == 0.0)    # propagated unless asked


def test_effect_parameters_carry_a_unit_gaussian_prior_residual():
    # Saturation: b_sat in (1.0, 1.3) T -> centre 1.15, width 0.3; sharpness in (3, 6) -> centre 4.5, width 3.
    # CurrentOffset.top is signed, in (4, 15) mA -> centre 0, width 15 mA.
    model = core.Model.of((E.Saturation(), E.CurrentOffset()))
    assert model.names()[:4] == ["saturation.b_sat[v]", "saturation.b_sat[w]", "saturation.sharpness[v]",
                                 "saturation.sharpness[w]"]
    q = np.array([0.5, -1.0, 0.0, 2.0, 1.0, -0.2, 0.3, 0.0])
    sat, off = model.build(jnp.asarray(q))
    np.testing.assert_allclose(np.asarray(sat.b_sat), [1.15 + 0.3 * 0.5, 1.15 - 0.3], rtol=REL)
    np.testing.assert_allclose(np.asarray(sat.sharpness), [4.5, 4.5 + 3.0 * 2.0], rtol=REL)
    np.testing.assert_allclose(np.asarray(off.top), [0.015, -0.2 * 0.015], rtol=REL)
    prob, _ = core.build_problem(TWO_ROWS)
    theta = jnp.asarray(np.concatenate([core.to_theta(G0, X0, K), q]))
    r = np.asarray(core.residuals(theta, prob, model))
    assert r.shape == (2 + 8,)
    np.testing.assert_array_equal(r[2:], q)            # -log prior = sum(q^2)/2: residual q exactly
    # and its Jacobian block is the identity: the prior does not depend on the data
    j = np.asarray(core.jacobian(theta, prob, model))
    np.testing.assert_array_equal(j[2:, 6:], np.eye(8))
    np.testing.assert_array_equal(j[2:, :6], 0.0)


# --- covariance when the noise is estimated -----------------------------------------------------------------

@pytest.fixture(scope="module")
def noisy_table2():
    """paper_table2, 2 iterations (16 rows, known rotor load), 2 mA current noise, fixed seed."""
    return rig.simulate(rig.PAPER_RIG, P.paper_table2(iterations=2, center=(-33.3e-6, 11.3e-6)),
                        noise=rig.Noise(current=2e-3, position=0.1e-6), seed=11).data


def _analytic_jacobian(res, df, s_i=1e-3, s_x=0.0):
    """d((F - L)/s) / d(g_v0, g_w0, v0, w0, k_v, k_w) [SI] by hand, s_eff held fixed at the estimate
    (default: the unit weights of estimated noise, s_t = s_b = 1 mA, s_x = 0); also the residuals."""
    p = dict(zip(res.names, res.values))
    a = (df["axis"] == "w").to_numpy().astype(int)
    x = np.where(a == 0, df["v_um"], df["w_um"]) * 1e-6
    it, ib, load = df["i_top_A"].to_numpy(), df["i_bottom_A"].to_numpy(), df["load_N"].to_numpy()
    g0 = np.array([p["g_v0"], p["g_w0"]])[a]
    x0 = np.array([p["v0"], p["w0"]])[a]
    k = np.array([p["k_v"], p["k_w"]])[a]
    gt, gb = g0 - (x0 + x) * COS, g0 + (x0 + x) * COS
    d_x0 = 2 * k * COS * (it**2 / gt**3 + ib**2 / gb**3)          # dg_t/dx0 = -cos, dg_b/dx0 = +cos (= dF/dx)
    s = np.sqrt((2 * k * it / gt**2 * s_i) ** 2 + (2 * k * ib / gb**2 * s_i) ** 2 + (d_x0 * s_x) ** 2)
    r = (k * (it**2 / gt**2 - ib**2 / gb**2) - load) / s
    d_g0 = k * (-2 * it**2 / gt**3 + 2 * ib**2 / gb**3)          # dg_t/dg0 = dg_b/dg0 = 1
    d_k = it**2 / gt**2 - ib**2 / gb**2
    j = np.zeros((len(df), 6))
    rows = np.arange(len(df))
    j[rows, 0 + a] = d_g0 / s
    j[rows, 2 + a] = d_x0 / s
    j[rows, 4 + a] = d_k / s
    return j, r


# The library inverts the column-scaled J^T J of its automatic Jacobian with pinv, the reference the analytic one
# with inv; the scaled condition number is ~30 here and they agree to 7e-14 (observed).  1e-9 is headroom for
# other BLAS builds; a wrong noise scaling changes the covariance by a factor sqrt(chi2/dof) > 1.4 (asserted).
COV_REL = 1e-9


def assert_cov_equal(actual, expected):
    """Covariances equal entry by entry relative to sqrt(var_i var_j) (exact zeros of the v-w blocks come out
    as 1e-25 of round-off from the library's joint inverse)."""
    sd = np.sqrt(np.diag(expected))
    np.testing.assert_allclose(actual / np.outer(sd, sd), expected / np.outer(sd, sd), rtol=0, atol=COV_REL)


def test_covariance_is_scaled_by_reduced_chi2_when_noise_is_estimated(noisy_table2):
    bare = noisy_table2.drop(columns=STD_COLUMNS)
    res = fit(bare, debias="none")            # the least-squares minimum (the correction moves off it)
    assert res.noise_estimated and res.names == ["g_v0", "g_w0", "v0", "w0", "k_v", "k_w"]
    j, r = _analytic_jacobian(res, bare)
    chi2, dof = float(r @ r), len(r) - 6
    assert res.chi2 == pytest.approx(chi2, rel=1e-9)      # 1e-9: round-off of a sum of 16 squares, with headroom
    # precondition: chi2/dof far from 1, so chi2/dof and its square root (a wrong scaling) differ by a factor > 1.4
    assert chi2 / dof > 2.0
    # cov = (J^T J)^-1 chi2/dof, inverted with column scaling (the columns differ by 10 orders of magnitude)
    n = np.linalg.norm(j, axis=0)
    cov_hand = np.linalg.inv((j / n).T @ (j / n)) / np.outer(n, n) * chi2 / dof
    assert_cov_equal(res.cov, cov_hand)
    np.testing.assert_allclose(res.std, np.sqrt(np.diag(cov_hand)), rtol=COV_REL)
    # the same weights declared rather than estimated: the same estimate, the covariance without the scaling
    declared = fit(bare, sigma_i=1e-3, sigma_x=0.0, debias="none")
    assert not declared.noise_estimated
    np.testing.assert_allclose(declared.values, res.values, rtol=1e-9)
    assert_cov_equal(res.cov, declared.cov * chi2 / dof)


def test_noise_from_std_columns_is_not_rescaled(noisy_table2):
    # the rig wrote its noise levels (2 mA, 0.1 µm) to the std columns: cov = (J^T J)^-1, no chi2/dof factor
    res = fit(noisy_table2)
    assert not res.noise_estimated and "std columns" in res.noise_source
    j, r = _analytic_jacobian(res, noisy_table2, s_i=2e-3, s_x=0.1e-6)
    assert res.chi2 == pytest.approx(float(r @ r), rel=1e-9)      # as above
    n = np.linalg.norm(j, axis=0)
    cov_hand = np.linalg.inv((j / n).T @ (j / n)) / np.outer(n, n)
    assert_cov_equal(res.cov, cov_hand)


# --- health -----------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def saturated_table2():
    """Three biases (1.0/1.4/1.8 A) at ±20 and ±40 µm (24 rows) on a saturating rig (b_sat 1.2 T), default noise,
    std columns.  (Table 2's design, two biases at one pair of positions, absorbs saturation into biased
    gap and origin with an adequate χ², so it cannot show the effect.)"""
    proto = P.perturbation((1.0, 1.4, 1.8), (20e-6, 40e-6), center=(-33.3e-6, 11.3e-6))
    sat = rig.simulate(rig.PAPER_RIG, proto, (E.Saturation(b_sat=1.2, sharpness=5.0),), seed=5).data
    clean = rig.simulate(rig.PAPER_RIG, proto, seed=5).data
    return sat, clean


def test_adequacy_detects_a_planted_effect(saturated_table2):
    sat, clean = saturated_table2
    bad = fit(sat)
    assert bad.converged and not bad.noise_estimated
    assert bad.adequate is False and bad.p_value < 1e-3
    text = " ".join(bad.health())
    assert "χ²/dof" in text and "ideal law" in text and f"{bad.reduced_chi2:.3g}" in text
    assert bad.to_json()["goodness_of_fit"]["adequate"] is False
    # the same design and noise without the effect: the ideal law is adequate and healthy
    good = fit(clean)
    assert good.adequate is True and good.health() == []


def test_adequacy_is_unknown_when_noise_is_estimated(saturated_table2):
    sat, _ = saturated_table2
    res = fit(sat.drop(columns=STD_COLUMNS))
    assert res.adequate is None
    assert not any("χ²/dof" in h for h in res.health())
    assert res.to_json()["goodness_of_fit"]["adequate"] is None


def test_unidentifiable_design_is_reported_or_raised():
    # one set-point, unknown load: gap and origin trade off along the valley of Fig. 2
    loads = {"u": P.Load(5.0, 4.0, known=False)}
    repeated = P.concat(*(P.grid([(10e-6, 10e-6)], [1.2, 1.4, 1.6], load="u", loads=loads, iteration=i)
                          for i in range(4)))
    data = rig.simulate(rig.PAPER_RIG, repeated, seed=0).data
    res = fit(data, throw=False, max_steps=20)
    assert res.well_conditioned is False
    assert any("does not identify" in h for h in res.health())
    assert res.to_json()["well_conditioned"] is False
    with pytest.raises(FitError, match="does not identify"):
        fit(data, max_steps=20)


def test_the_solve_measures_every_rows_jacobian_and_fits_only_the_masked_rows():
    sim = rig.simulate(rig.PAPER_RIG, P.rich(), [E.Saturation(b_sat=jnp.asarray(1.3))], seed=2).data
    keep = (np.arange(len(sim)) % 3 != 0).astype(float)
    res = fit(sim, [E.Saturation()], mask=keep, loss="linear", throw=False)
    prob, meta = core.build_problem(sim)
    model = core.Model.of([E.Saturation()])
    free = core.free_mask(prob, meta, model)
    direct = np.asarray(core.jacobian(jnp.asarray(res.theta), prob, model))[: len(sim)][:, free]
    # the held-out rows' Jacobian too (the outlier test's leverages need it), at weight 1
    assert np.abs(direct[keep == 0]).sum() > 0
    np.testing.assert_allclose(res.jacobian_rows, direct, rtol=1e-9, atol=1e-12 * np.abs(direct).max())
    # ... while the covariance comes from the fitted rows alone: the same as a fit of only those rows
    alone = fit(sim[keep > 0].reset_index(drop=True), [E.Saturation()], loss="linear", throw=False)
    assert alone.names == res.names
    np.testing.assert_allclose(res.std, alone.std, rtol=1e-5)
    # and every row's effective noise, the unit of its residual
    s = np.asarray(core.noise_std(jnp.asarray(res.theta), prob, model))
    np.testing.assert_allclose(res.row_noise, s, rtol=1e-12)
    np.testing.assert_allclose(res.residuals[: len(sim)] * s, np.asarray(core.misfit(res.theta, prob, model)[0]),
                               rtol=1e-9, atol=1e-12 * np.abs(s).max())


def test_problems_padded_to_one_shape_measure_as_each_alone():
    """The vmapped measurement of problems padded to a common number of rows and loads gives each problem's own
    rows: forces, effective noise and Jacobian columns (its head, its loads, the effects)."""
    from ambfit.estimation.batches import pad

    model = core.Model.of([E.Saturation(b_sat=jnp.asarray(1.3))])
    tables = [rig.simulate(rig.PAPER_RIG, P.rich(), seed=1).data,
              rig.simulate(rig.PAPER_RIG, P.paper_table2(), seed=2).data]
    built = [core.build_problem(t) for t in tables]
    rows, loads = 1024, 32
    assert rows >= max(len(t) for t in tables) and loads >= max(len(m.load_groups) for _, m in built)
    thetas = []
    for prob, meta in built:
        theta = np.zeros(6 + loads + model.n)
        theta[:6] = core.to_theta(760e-6, 0.0, core.K_REFERENCE, np.zeros(0))[:6] + 0.01
        theta[6:6 + len(meta.load_groups)] = np.linspace(-0.5, 0.5, len(meta.load_groups))
        theta[-model.n:] = 0.3
        thetas.append(theta)
    f, s, jac = (np.asarray(a) for a in core.measured_sets(np.stack(thetas), pad([p for p, _ in built], rows), model))
    for b, ((prob, meta), theta) in enumerate(zip(built, thetas)):
        n, own = len(np.asarray(prob.mask)), np.r_[0:6 + len(meta.load_groups), 6 + loads:6 + loads + model.n]
        f1, s1, j1 = core.rows_measured(theta[own], prob, meta, model)
        np.testing.assert_allclose(f[b, :n], f1, rtol=1e-12, atol=1e-12 * np.abs(f1).max())
        np.testing.assert_allclose(s[b, :n], s1, rtol=1e-12)
        np.testing.assert_allclose(jac[b, :n][:, own[core.free_mask(prob, meta, model)]], j1, rtol=1e-10,
                                   atol=1e-12 * np.abs(j1).max())


# --- one compiled solve for a set of models -----------------------------------------------------------------

def test_models_solved_together_fit_as_each_alone():
    """Within ``compiled_together`` each model runs the set's one solve (theta padded to the widest member, the
    force a switch over the members, the Jacobian each member's own): the estimate, its Jacobian and its
    residuals are those of the model solved alone.  Red when the switch picks another member, when the padding
    leaks into the model's parameters, or when the members' Jacobians are not the acting member's."""
    sim = rig.simulate(rig.PAPER_RIG, P.rich(), [E.Saturation(b_sat=jnp.asarray(1.3))], seed=4).data
    prob, _ = core.build_problem(sim)
    base = fit(sim, throw=False)
    members = [core.Model.of(()), core.Model.of([E.Saturation()]), core.Model.of([E.IronReluctance()]),
               core.Model.of([E.Hysteresis()])]
    for model in members[:2]:
        theta0 = jnp.asarray(np.concatenate([base.theta, np.zeros(model.n)]))
        alone = lm.solve(theta0, prob, model, max_steps=60)
        with lm.compiled_together(members):
            together = lm.solve(theta0, prob, model, max_steps=60)
        assert together.theta.shape == alone.theta.shape and together.jac.shape == alone.jac.shape
        assert float(together.edm) < core.EDM_MAX and float(alone.edm) < core.EDM_MAX
        # both converged to the same optimum (EDM < 1e-6: within 1e-3 standard errors); 1e-7 relative is the
        # agreement of two Levenberg-Marquardt paths that stop at different round-off
        np.testing.assert_allclose(np.asarray(together.theta), np.asarray(alone.theta), rtol=1e-7, atol=1e-9)
        for k in ("jac", "z", "jac_all"):          # Jacobian, standardized residuals, every row's Jacobian
            a, t = np.asarray(getattr(alone, k)), np.asarray(getattr(together, k))
            np.testing.assert_allclose(t, a, rtol=1e-6, atol=1e-9 * np.abs(a).max())


def test_compiled_sets_nest_innermost_first():
    """A model of the inner block's set is solved in it; one only in the outer block's, in that one; one in
    neither, alone (a diagnosis compiles its pairs as a set of their own inside its singles' block)."""
    singles = [core.Model.of(()), core.Model.of([E.Saturation()])]
    pairs = [core.Model.of([E.Saturation(), E.Hysteresis()]), core.Model.of([E.Saturation(), E.CurrentOffset()])]
    lone = core.Model.of([E.Hysteresis(), E.Leakage()])
    with lm.compiled_together(singles):
        with lm.compiled_together(pairs):
            assert lm._members(pairs[1])[1] == 1 and len(lm._members(pairs[1])[0]) == len(pairs)
            assert lm._members(singles[1])[1] == 1 and len(lm._members(singles[1])[0]) == len(singles)
            assert lm._members(lone) == ((lone,), 0)
        assert lm._members(pairs[0]) == ((pairs[0],), 0)


def test_a_step_budget_is_a_traced_number_and_is_kept():
    """One compiled solve serves every budget: a budget of one step per round stops there and says so."""
    sim = rig.simulate(rig.PAPER_RIG, P.rich(), [E.Saturation(b_sat=jnp.asarray(1.3))], seed=4).data
    prob, _ = core.build_problem(sim)
    model = core.Model.of([E.Saturation()])
    theta0 = jnp.asarray(np.concatenate([fit(sim, throw=False).theta, np.zeros(model.n)]))
    short = lm.solve(theta0, prob, model, max_steps=1)
    assert int(short.steps) <= lm.REWEIGHTINGS
    assert short.result == lm.RESULTS.nonlinear_max_steps_reached
    full = lm.solve(theta0, prob, model, max_steps=60)
    assert full.result == lm.RESULTS.successful and int(full.steps) > lm.REWEIGHTINGS


def test_the_solver_settings_are_arguments_that_share_one_program():
    """``reweightings``, ``edm_round`` and ``rtol`` are arguments of the solve with the module's constants as
    defaults, traced like the budget: other values run the same compiled program and do what they say."""
    sim = rig.simulate(rig.PAPER_RIG, P.rich(), [E.Saturation(b_sat=jnp.asarray(1.3))], seed=4).data
    prob, _ = core.build_problem(sim)
    model = core.Model.of([E.Saturation()])
    theta0 = np.concatenate([fit(sim, throw=False).theta, np.zeros(model.n)])
    default = lm.solve(theta0, prob, model, max_steps=60)
    program = lm._compiled(prob, (model,))[0]
    compiled = program._cache_size()
    same = lm.solve(theta0, prob, model, max_steps=60, reweightings=lm.REWEIGHTINGS, edm_round=lm.EDM_ROUND,
                    rtol=lm.RTOL)
    np.testing.assert_array_equal(same.theta, default.theta)
    one = lm.solve(theta0, prob, model, max_steps=60, reweightings=1)
    assert int(one.steps) < int(default.steps)
    # an EDM stop that any point meets ends each round at its first step, which evaluates the round's start
    loose = lm.solve(theta0, prob, model, max_steps=60, edm_round=np.inf)
    assert int(loose.steps) == lm.REWEIGHTINGS and not loose.converged
    assert program._cache_size() == compiled


def test_a_model_is_built_once_per_set_of_effect_instances_and_bearing():
    from ambfit.physics.bearing import PAPER_BEARING

    sat = E.Saturation()
    model = core.Model.of((sat,))
    assert core.Model.of([sat]) is model                                   # the same instances: the same model
    assert core.Model.of((E.Saturation(),)) is not model                   # another instance is looked at afresh
    other = core.Model.of((sat,), dataclasses.replace(PAPER_BEARING, nominal_gap=500e-6))
    assert other is not model and other.bearing.nominal_gap == 500e-6


def test_a_table_owned_by_its_caller_is_hashed_once_and_a_changed_table_is_seen(monkeypatch):
    from ambfit.estimation import problem

    table = TWO_ROWS.copy()
    outside, _ = core.build_problem(table)
    hashed = []
    monkeypatch.setattr(problem, "_digest", lambda df, _d=problem._digest: hashed.append(1) or _d(df))
    with problem.owned(table):
        for _ in range(3):
            inside, _ = core.build_problem(table)
    assert len(hashed) == 1                   # on entering the block, not once per build
    np.testing.assert_array_equal(np.asarray(inside.i_top), np.asarray(outside.i_top))
    table.loc[0, "i_top_A"] = 1.70            # changed in place after the block: the content key sees it
    changed, _ = core.build_problem(table)
    assert float(changed.i_top[0]) == 1.70


def test_a_built_problem_holds_its_own_copy_of_the_table():
    # Problems are kept by the table's content; one built from a table later changed in place must still hold
    # the values it was built from, and a table with the original values must get them back
    table = TWO_ROWS.copy()
    built, _ = core.build_problem(table)
    kept = {name: np.array(getattr(built, name)) for name in ("i_top", "s_x")}
    table.loc[0, "i_top_A"] = 1.90
    table.loc[1, "w_std_um"] = 0.5
    for name, values in kept.items():
        np.testing.assert_array_equal(np.asarray(getattr(built, name)), values)
    again, _ = core.build_problem(TWO_ROWS.copy())
    np.testing.assert_array_equal(np.asarray(again.i_top), kept["i_top"])
    with pytest.raises(ValueError):
        np.asarray(again.i_top)[0] = 0.0          # the kept problem's arrays cannot be written through


def test_the_written_out_levenberg_marquardt_takes_optimistix_steps():
    """The solve's iteration is optimistix's LevenbergMarquardt written out (one place evaluates the model).  One
    round with the weights held and our extra EDM stop off gives optimistix's iterates from a far start (150 µm off
    in gap, 60 µm in origin, the effect two prior widths off): the same point and result after 2, 3, 5 and 12
    steps, through rejected steps too.  Red when the trust region's step-size factors differ (measured: 3 for 3.5
    and 0.5 for 0.25 each fail it; an acceptance cutoff of 0.1 for 0.01 does not, no step here falls between)."""
    import optimistix as optx

    sim = rig.simulate(rig.PAPER_RIG, P.rich(), [E.Saturation(b_sat=jnp.asarray(1.3))], seed=4).data
    prob, _ = core.build_problem(sim)
    model = core.Model.of([E.Saturation()])
    base = fit(sim, throw=False)
    theta0 = np.concatenate([base.theta, np.zeros(model.n)])
    theta0[:4] += np.array([150e-6, -150e-6, 60e-6, -60e-6]) / core.SCALE_HEAD[:4]
    theta0[-model.n:] = 2.0                    # the effect two prior widths off
    theta0 = jnp.asarray(theta0)
    s0 = core.misfit(theta0, prob, model)[1]

    def residuals(theta, _):
        return core.with_priors(theta, prob.mask * core.force_misfit(theta, prob, model) / s0, model.n)

    solver = optx.LevenbergMarquardt(rtol=lm.RTOL, atol=lm.RTOL)
    for budget in (2, 3, 5, 12):
        ours = lm.solve(theta0, prob, model, max_steps=budget, reweightings=1, edm_round=0.0)
        ref = optx.least_squares(residuals, solver, theta0, max_steps=budget, throw=False)
        assert lm.RESULTS[ours.result] == optx.RESULTS[ref.result], budget     # (the same messages)
        assert int(ours.steps) == int(ref.stats["num_steps"]), budget
        # ours solves each damped step by Cholesky of the column-scaled normal equations, optimistix by QR: the
        # round-off differs (measured 2.5e-10 relative after 12 steps from this far start), so 1e-8, not 1e-10;
        # a changed trust-region factor moves the iterates by far more (and changes the step counts above)
        np.testing.assert_allclose(np.asarray(ours.theta), np.asarray(ref.value), rtol=1e-8, atol=1e-12)
    # the path went through rejected steps too (the trust region's shrinking branch was compared)
    assert int(ref.state.num_accepted_steps) < int(ref.stats["num_steps"])
