"""The second-order bias correction of the least-squares estimate (ambfit.estimation.debias), the fit's default.

Its size on many data sets (bias and spread against the Cramér-Rao bound, per protocol) is measured by
benchmarks/ls_bias.py; here: that the differences compute the expansion's derivatives, that the expansion
agrees with a bootstrap of the model, and how the fit applies it.
"""

import contextlib
import json

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from ambfit import rig
from ambfit.estimation import core, fit
from ambfit.estimation.debias import bootstrap_bias, second_order_biases
from ambfit.physics.effects import CurrentOffset
from ambfit.rig import protocol as P

NOISY = rig.Noise(1.8e-3, 0.1e-6)
"""Three times the paper rig's current noise: a bias of about 0.3 standard deviations on the origins."""


@pytest.fixture(scope="module")
def table2():
    spec = rig.PAPER_RIG
    return rig.simulate(spec, P.paper_table2(center=spec.centre), noise=NOISY, seed=5).data


def _exact_bias(theta, prob, free, model=core.IDEAL):
    """The expansion of the module docstring with every derivative by nested forward differentiation (exact)."""
    free = jnp.asarray(free, dtype=float)
    r = prob.readings
    var = [jnp.broadcast_to(jnp.asarray(s, dtype=float), r.x.shape) ** 2 for s in (prob.s_top, prob.s_bottom, prob.s_x)]
    primal = (r.i_top, r.i_bottom, r.x)

    def scores(th, *m):
        f, s, jac = core.measured(th, prob.with_readings(*m), model)
        return (jnp.asarray(prob.mask) ** 2 * f / s**2)[:, None] * jac * free

    def psi(th):
        prior = jnp.zeros_like(th).at[len(th) - model.n:].set(th[len(th) - model.n:]) if model.n else 0.0
        return scores(th, *primal).sum(axis=0) + prior * free

    def along(c, th):
        tangent = tuple(jnp.ones_like(a) if k == c else jnp.zeros_like(a) for k, a in enumerate(primal))
        return jax.jvp(lambda *m: jax.jvp(lambda *mm: scores(th, *mm), m, tangent)[1], primal, tangent)

    a_inv = jnp.linalg.inv(jax.jacfwd(psi)(theta) * free[:, None] * free[None, :] + jnp.diag(1.0 - free))
    total = jnp.zeros_like(theta)
    m = jnp.zeros((len(theta), len(theta)))
    for c in range(3):
        d1, d2 = along(c, theta)
        cross = jax.jacfwd(lambda th, c=c: along(c, th)[0])(theta)
        v = -d1 @ a_inv.T
        total = total + var[c] @ d2 + 2.0 * jnp.einsum("n,nab,nb->a", var[c], cross, v)
        m = m + jnp.einsum("n,na,nb->ab", var[c], v, v)
    total = total + jnp.einsum("abe,be->a", jax.jacfwd(jax.jacfwd(psi))(theta), m)
    return np.asarray(-0.5 * a_inv @ (total * free))


def _scaled_cov(res, prob, meta, model=core.IDEAL):
    free = core.free_mask(prob, meta, model)
    scale = core.si_scale(prob, model)[0]
    cov = np.zeros((len(free), len(free)))
    cov[np.ix_(free, free)] = res.cov / np.outer(scale[free], scale[free])
    return free, cov


def _cases():
    spec = rig.PAPER_RIG
    centre = spec.centre
    t2 = rig.simulate(spec, P.paper_table2(center=centre), noise=NOISY, seed=5).data
    unknown = {"u": P.Load(5.0, 4.0, known=False)}
    loads = rig.simulate(spec, P.perturbation((1.2, 1.4, 1.6), (20e-6, 40e-6), center=centre, load="u", loads=unknown),
                         noise=NOISY, seed=3).data
    # (every entry free is the bootstrap test's case; one axis holds entries as k held does)
    return {"unknown loads, k held": (loads, ()), "effect priors": (t2, (CurrentOffset(),))}


@pytest.mark.parametrize("case", list(_cases()))
def test_the_differences_give_the_exact_expansion(case):
    data, effects = _cases()[case]
    model = core.Model.of(effects)
    plain = fit.fit(data, effects, debias="none")
    prob, meta = core.build_problem(data)
    free, cov = _scaled_cov(plain, prob, meta, model)
    one = jax.tree.map(lambda a: np.asarray(a)[None], prob)
    approx = second_order_biases(plain.theta[None], one, model, free[None], cov[None])[0]
    exact = _exact_bias(jnp.asarray(plain.theta), prob, free.astype(float), model)
    # differences of a hundredth of a standard error along theta and of one noise std along the readings, and the
    # covariance's diagonal in place of M's (module docstring): measured within 0.5 % of each entry
    sd = np.sqrt(np.diag(cov))[free]
    np.testing.assert_allclose(approx[free] / sd, exact[free] / sd, rtol=0.01, atol=1e-4)
    assert np.all(approx[~free] == 0.0)
    assert free.all() == (case == "effect priors")      # (the cases test what they say)


def _routes(data, effects, *, mask=None, held=False, share=(1.0, 1.0, 1.0), together=False):
    """A data set's bias by both routes: its own programs (the mixed term along one direction per reading) and its
    solve's program (the mixed term along the covariance's square roots), scaled by its standard errors."""
    from ambfit.estimation import lm

    model = core.Model.of(effects)
    plain = fit.fit(data, effects, debias="none", mask=mask)
    prob, meta = core.build_problem(data, mask=mask)
    if held:                      # the noise held at the fit's, every row's its own
        prob = prob.with_noise(np.asarray(core.misfit(np.asarray(plain.theta), prob, model)[1]))
    free, cov = _scaled_cov(plain, prob, meta, model)
    one = jax.tree.map(lambda a: np.asarray(a)[None], prob)
    wider = core.Model.of((*effects, CurrentOffset())) if together else None
    with lm.compiled_together([model, wider]) if together else contextlib.nullcontext():
        routes = [second_order_biases(plain.theta[None], one, model, free[None], cov[None], share, via_solve=v)[0]
                  for v in (False, True)]
    sd = np.sqrt(np.diag(cov))[free]
    return [r[free] / sd for r in routes], [r[~free] for r in routes]


ROUTE_CASES = {
    **{name: (name, {}) for name in _cases()},
    "weights and held-out rows": ("unknown loads, k held", {"mask": "weights"}),
    "held noise, shares": ("effect priors", {"held": True, "share": (2.0, 0.5, 0.0)}),
    "solved in a set": ("unknown loads, k held", {"together": True}),
}


@pytest.mark.parametrize("name", list(ROUTE_CASES))
def test_the_solves_program_gives_the_same_bias(name):
    """A data set's bias from its solve's program, a point and a reading at a time, is the one its own programs
    give: the same differences but for the mixed term's, taken along the covariance's square roots there and along
    one direction per reading here (their difference is the differences' own error)."""
    case, kw = ROUTE_CASES[name]
    data, effects = _cases()[case]
    if kw.get("mask") == "weights":
        w = np.where(np.arange(len(data)) % 5 == 0, 0.0, 1.0)
        w[1::7] = 0.5
        kw = kw | {"mask": w}
    (mine, solved), (held_mine, held_solved) = _routes(data, effects, **kw)
    assert np.all(np.abs(mine) > 1e-4)                    # (a bias to compare)
    # (measured: at most 1.3e-9 of a standard deviation in these cases)
    np.testing.assert_allclose(solved, mine, rtol=1e-6, atol=1e-7)
    assert np.all(held_mine == 0.0) and np.all(held_solved == 0.0)


@pytest.mark.parametrize("via_solve", [False, True])
def test_rows_standing_for_more_are_summed_as_that_many(via_solve):
    """A long data set's bias is summed over a subset of its rows scaled up (``row_scale``): every row counted
    twice gives the bias of the data set with each row there twice, by both routes."""
    data, effects = _cases()["effect priors"]
    model = core.Model.of(effects)
    plain = fit.fit(data, effects, debias="none")
    prob, meta = core.build_problem(data)
    twice, _ = core.build_problem(pd.concat([data, data], ignore_index=True))
    free, cov = _scaled_cov(plain, prob, meta, model)
    one, two = (jax.tree.map(lambda a: np.asarray(a)[None], p) for p in (prob, twice))
    scaled, doubled = (second_order_biases(plain.theta[None], p, model, free[None], cov[None], row_scale=r,
                                           via_solve=via_solve)[0] for p, r in ((one, 2.0), (two, 1.0)))
    sd = np.sqrt(np.diag(cov))[free]
    assert np.all(np.abs(doubled[free] / sd) > 1e-3)
    np.testing.assert_allclose(scaled[free] / sd, doubled[free] / sd, rtol=1e-8, atol=1e-10)


def test_identify_takes_the_bias_from_its_solves_program(tmp_path, table2, monkeypatch):
    """A command fits once and ends: its bias costs no program of its own (whose compilation would cost more than
    the fit), and the library's fit of one data set still runs that program."""
    from ambfit.estimation import debias
    from ambfit.faces.cli import app

    calls = []
    batched = debias.bias_of_one
    monkeypatch.setattr(debias, "bias_of_one", lambda *a: calls.append(1) or batched(*a))
    csv = tmp_path / "t2.csv"
    table2.to_csv(csv, index=False)
    js = tmp_path / "t2.json"
    r = CliRunner().invoke(app, ["identify", str(csv), "--json", str(js), "--no-force-check"])
    assert r.exit_code == 0, r.output
    corrected = json.loads(js.read_text())["bias_correction"]
    assert corrected["method"] == "second-order" and "skipped" not in corrected and not calls
    res = fit.fit(table2)
    assert res.bias_correction["method"] == "second-order" and "skipped" not in res.bias_correction and calls
    with debias.by_solve():
        again = fit.fit(table2)
    assert len(calls) == 1 and not debias.bias_by_solve()
    # (the two routes' biases, a few tenths of a standard deviation, agree to 1e-6 of themselves or better)
    np.testing.assert_allclose(again.values, res.values, rtol=1e-10)


def test_the_expansion_agrees_with_a_bootstrap_of_the_model(table2):
    # An independent check of the formula: simulate the fitted model with the declared noise and refit.
    plain = fit.fit(table2, debias="none")
    prob, meta = core.build_problem(table2)
    free, cov = _scaled_cov(plain, prob, meta)
    one = jax.tree.map(lambda a: np.asarray(a)[None], prob)
    expansion = second_order_biases(plain.theta[None], one, core.IDEAL, free[None], cov[None])[0]
    boot = bootstrap_bias(plain.theta, prob, prob.bias, n=4000, seed=2)
    assert boot.converged_fraction == 1.0
    sd = np.sqrt(np.diag(cov))
    for j in np.nonzero(free)[0]:
        # within 4 Monte Carlo errors (1/sqrt(4000) sd each) and the expansion's own third order
        assert abs(expansion[j] - boot.bias[j]) < 4 * boot.mc_error[j] + 0.02 * sd[j], (j, expansion[j], boot.bias[j])
    origins = [2, 3]
    assert np.all(expansion[origins] / sd[origins] > 0.15)       # the origins' bias is there to be found


def test_the_default_fit_subtracts_it_and_is_measured_there(table2):
    plain = fit.fit(table2, debias="none")
    res = fit.fit(table2)
    bc = res.bias_correction
    assert bc["method"] == "second-order" and plain.bias_correction is None
    for j, name in enumerate(res.names):
        assert res.values[j] == pytest.approx(plain.values[j] - bc[name]["subtracted"], rel=1e-12, abs=1e-18)
    assert 0.15 < bc["v0"]["subtracted"] / plain.error("v0") < 0.5
    # residuals and χ² are those of the corrected estimate; the solve's record is the minimum's
    prob, _ = core.build_problem(table2)
    z = np.asarray(core.standardized(jnp.asarray(res.theta), prob))
    np.testing.assert_allclose(res.residuals, z, rtol=1e-9)
    assert res.chi2 == pytest.approx(float(z @ z), rel=1e-9)
    assert res.edm == plain.edm and res.converged and res.dof == plain.dof
    assert "second-order bias subtracted" in " ".join(res.notes())
    assert res.to_json()["bias_correction"]["method"] == "second-order"


def test_a_batch_corrects_each_data_set_as_alone():
    spec = rig.PAPER_RIG.with_truth(g0=(790e-6, 745e-6), x0=(-20e-6, 14e-6))

    def unknown_loads(k):        # k load ids with unknown loads, each on both axes: 2k nuisance loads
        loads = {f"u{j}": P.Load(3.0 + j, 4.0 - j, known=False) for j in range(k)}
        return P.concat(*(P.perturbation((1.4, 1.6), (20e-6,), center=(20e-6, -14e-6), iterations=2, load=f"u{j}",
                                         loads=loads, experiment=f"u{j}") for j in range(k)))

    # known loads alone in its bucket, and two in one bucket (128 rows, 16 loads: one of them padded from 12)
    sets = [rig.simulate(spec, P.paper_table2(center=(20e-6, -14e-6)), noise=NOISY, seed=1).data]
    sets += [rig.simulate(spec, unknown_loads(k), noise=NOISY, seed=4 + k).data for k in (6, 8)]
    together = fit.fit_many(sets)
    for d, res in zip(sets, together):
        alone = fit.fit(d)
        assert res.names == alone.names
        sub = np.array([res.bias_correction[n]["subtracted"] for n in res.names])
        assert np.all(np.isfinite(sub)) and np.all(sub != 0.0)
        # in standard errors: the covariances of a batch and of a fit alone agree to round-off (1e-14 of sd x sd),
        # and the steps along theta follow them; the largest difference measured is 3e-5 sd
        assert np.max(np.abs(res.values - alone.values) / res.std) < 1e-3
        alone_sub = np.array([alone.bias_correction[n]["subtracted"] for n in alone.names])
        assert np.max(np.abs(sub - alone_sub) / res.std) < 1e-3


def test_estimated_noise_scales_the_bias_by_its_variance(table2):
    bare = table2.drop(columns=["i_top_std_A", "i_bottom_std_A", "v_std_um", "w_std_um"])
    est = fit.fit(bare)
    declared = fit.fit(bare, sigma_i=1e-3, sigma_x=0.0)     # the unit weights an estimate starts from
    plain = fit.fit(bare, debias="none")
    assert est.noise_estimated and not declared.noise_estimated
    for name in est.names:
        ratio = est.bias_correction[name]["subtracted"] / declared.bias_correction[name]["subtracted"]
        # 1 %: the differences along theta step a fraction of a standard error, which the estimated noise scales
        assert ratio == pytest.approx(plain.reduced_chi2, rel=0.01), name


def test_a_current_noise_estimated_beside_declared_positions_scales_only_itself(table2):
    bare = table2.drop(columns=["i_top_std_A", "i_bottom_std_A"]).assign(v_std_um=0.3, w_std_um=0.3)
    est, plain = fit.fit(bare), fit.fit(bare, debias="none")
    assert est.noise_estimated and "position from the std columns" in est.noise_source
    prob, meta = core.build_problem(bare)
    free, cov = _scaled_cov(plain, prob, meta)
    one = jax.tree.map(lambda a: np.asarray(a)[None], prob)
    r = plain.reduced_chi2
    scale = core.si_scale(prob)[0][free]
    for share, same in (((r, r, 1.0), True), ((r, r, r), False)):
        bias = second_order_biases(plain.theta[None], one, core.IDEAL, free[None], cov[None], share)[0][free] * scale
        sub = np.array([est.bias_correction[n]["subtracted"] for n in est.names])
        assert np.allclose(sub, bias, rtol=1e-6, atol=1e-6 * plain.std) == same, share


def test_no_correction_where_it_does_not_apply(table2):
    plain = fit.fit(table2, debias="none")
    for res, why in ((fit.fit(table2, loss="huber"), "huber loss"),                      # another estimating equation
                     (fit.fit(table2, max_steps=1, throw=False), "did not converge"),     # not at a minimum
                     (fit.fit(table2, max_condition=10, throw=False), "does not identify")):
        assert not res.converged or not res.well_conditioned or res.loss == "huber"
        assert res.bias_correction["method"] == "second-order" and why in res.bias_correction["skipped"]
        assert set(res.bias_correction) == {"method", "skipped"}
        assert "second-order bias not subtracted: " in " ".join(res.notes())
    assert fit.fit(table2, max_condition=10, throw=False).values == pytest.approx(plain.values, rel=1e-12)


def test_a_correction_beyond_the_expansion_is_not_made(table2, monkeypatch):
    # the ideal law's correction here moves the estimate by about 0.12 standard errors of a fit of 6 readings
    res = fit.fit(table2)
    assert "skipped" not in res.bias_correction
    monkeypatch.setattr(fit, "MAX_SHIFT", 0.08)
    res = fit.fit(table2)
    assert "higher orders are not negligible" in res.bias_correction["skipped"]
    assert res.values == pytest.approx(fit.fit(table2, debias="none").values, rel=1e-12)
    monkeypatch.setattr(fit, "MAX_SHIFT", 0.2)
    assert "skipped" not in fit.fit(table2).bias_correction


def test_a_model_with_effects_is_corrected_too(table2):
    # (with current offsets free on one bias pair the plain origins sit -2.4 of their scatter low, -0.8 of their
    # errors, and the correction brings them to within 0.05: benchmarks/ls_bias.py measures it)
    res = fit.fit(table2, [CurrentOffset()])
    plain = fit.fit(table2, [CurrentOffset()], debias="none")
    bc = res.bias_correction
    assert bc["method"] == "second-order" and set(bc) - {"method"} == set(res.names)
    assert all(np.isfinite(bc[n]["subtracted"]) for n in res.names)
    j = res.names.index("current_offset.top[v]")
    assert float(res.effects[0].top[0]) == pytest.approx(res.values[j], rel=1e-12)      # the effects moved with theta
    assert float(res.effects[0].top[0]) != float(plain.effects[0].top[0])


def test_identify_takes_the_correction_by_name_or_number(tmp_path, table2):
    from ambfit.faces.cli import app

    csv = tmp_path / "t2.csv"
    table2.to_csv(csv, index=False)
    runner = CliRunner()
    out = {}
    for choice in (*fit.DEBIAS, "40"):      # (the option's names, kept in the light CLI module, are the fit's)
        js = tmp_path / f"{choice}.json"
        r = runner.invoke(app, ["identify", str(csv), "--debias", choice, "--json", str(js), "--no-force-check"])
        assert r.exit_code == 0, r.output
        out[choice] = json.loads(js.read_text())
    assert out["second-order"]["bias_correction"]["method"] == "second-order"
    assert out["none"]["bias_correction"] is None
    assert out["40"]["bias_correction"]["n"] == 40
    r = runner.invoke(app, ["identify", str(csv), "--debias", "third-order"])
    assert r.exit_code != 0 and "--debias third-order" in r.output
