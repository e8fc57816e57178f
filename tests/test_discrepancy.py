"""The model-discrepancy term (ambfit.estimation.discrepancy) and the diagnosis' use of it."""

import numpy as np
import pytest

from ambfit import rig
from ambfit.diagnosis import Rules
from ambfit.estimation.basis import X_SCALE
from ambfit.estimation.discrepancy import fit_discrepancy
from ambfit.estimation.fit import fit
from ambfit.estimation.measure import FittedModel, force_check, predict
from ambfit.physics import effects as E
from ambfit.rig import protocol
from ambfit.rows import readings

HEAD = ("g_v0", "g_w0", "v0", "w0", "k_v", "k_w")


def _design():
    # centred on the rig's effective origin, so the ±40 µm set-points stay inside the back-up clearance
    return protocol.rich(biases=(1.0, 1.3, 1.6), n_positions=4, masses_kg=(0.0, 1.0, 2.0),
                         center=rig.PAPER_RIG.centre)


@pytest.fixture(scope="module")
def saturated():
    data = rig.simulate(rig.PAPER_RIG, _design(), [E.Saturation()], seed=3).data
    res = fit(data, loss="linear", throw=False)
    return data, res, fit_discrepancy(res, data)


@pytest.fixture(scope="module")
def clean():
    data = rig.simulate(rig.PAPER_RIG, _design(), seed=4).data
    res = fit(data, loss="linear")
    return data, res, fit_discrepancy(res, data)


def test_discrepancy_carries_what_the_ideal_law_misses(saturated):
    data, res, d = saturated
    z = res.residuals
    assert np.mean(z**2) > 20                        # saturation the ideal law cannot express
    assert np.mean((z + d.row_correction) ** 2) < 0.1 * np.mean(z**2)
    assert d.log_bayes["shape"] > Rules().log_bayes_clear    # in the flux-density shape, where saturation acts


def test_clean_data_want_no_correction(clean):
    _, res, d = clean
    assert max(d.log_bayes.values()) < 5.0
    assert np.mean((res.residuals + d.row_correction) ** 2) > 0.8 * np.mean(res.residuals**2)


def _refit_with_loads(data, res, correction_n):
    """Refit the ideal law to loads that the correction makes the physical model responsible for."""
    assert data["load_N"].notna().all()
    return fit(data.assign(load_N=data["load_N"] - correction_n), loss="linear", start_from=res, throw=False)


def test_correction_leaves_the_physical_parameters_where_they_are(saturated):
    # orthogonality: the physical law refitted to the data minus the correction does not move (Plumlee 2017)
    data, res, d = saturated
    moved = _refit_with_loads(data, res, d.row_correction_n)
    for n in HEAD:
        assert abs(moved.value(n) - res.value(n)) < 0.05 * res.error(n), n


def test_unconstrained_shift_is_what_an_unprojected_correction_does(saturated):
    # the same correction without the projection: the parameters absorb -A c of it, as reported
    data, res, d = saturated
    # (-A c is first order: here the gap moves ~40 µm, 5 % of itself, where Eq. 4 is visibly nonlinear, so the
    # refit agrees to ~5 % of the shift; 10 % still fails a wrong sign, scale or projection by far)
    raw = d.basis.matrix(readings(data)) @ d.coef
    moved = _refit_with_loads(data, res, raw)
    for n in HEAD:
        predicted = d.unconstrained_shift[n][0]
        assert abs(moved.value(n) - res.value(n) - predicted) < 0.1 * abs(predicted) + 0.1 * res.error(n), n
    assert max(abs(v[1]) for v in d.unconstrained_shift.values()) > 3     # it would have moved them


def test_fitted_model_adds_the_same_correction_at_new_readings(saturated):
    # the force path (projection in SI units, sensitivities at the readings) agrees with the fit's rows
    data, res, d = saturated
    fm = FittedModel.from_state(res.model_state() | {"discrepancy": d.to_json()}, res.bearing)
    assert fm.model == "ideal+discrepancy"
    f, s = fm.force(readings(data))
    np.testing.assert_allclose(f, predict(res, data) + d.row_correction_n, rtol=1e-6, atol=1e-6)
    plain, plain_s = FittedModel.from_result(res).force(readings(data))
    assert np.all(s >= plain_s)                     # the correction's own uncertainty adds


def test_force_check_with_discrepancy(saturated):
    data, res, _ = saturated
    fc = force_check(data, base=res, discrepancy=True, loss="linear")
    assert fc["discrepancy"]["rms_rel"] < fc["rms_rel"] / 3
    assert fc["noise_floor_rel"] < fc["discrepancy"]["rms_rel"] < 10 * fc["rms_rel"]
    # the per-load mean error is at most the per-reading RMS
    assert fc["rms_rel_mean"] <= fc["rms_rel"] + 1e-12


def test_model_file_with_discrepancy_is_checked(saturated):
    from ambfit.estimation.measure import ModelFileError

    _, res, d = saturated
    state = res.model_state() | {"discrepancy": d.to_json() | {"names": ["g_v0"]}}
    with pytest.raises(ModelFileError, match="discrepancy"):
        FittedModel.from_state(state, res.bearing)
    with pytest.raises(ModelFileError, match="no discrepancy model"):
        FittedModel.from_json({"baseline_fit": {"model_state": res.model_state()}}, res.bearing, use="discrepancy")
    # a basis saved with another displacement scale has the same terms and other columns: refused, not used
    saved = d.to_json()
    assert saved["basis"]["x_scale"] == X_SCALE
    other = saved | {"basis": saved["basis"] | {"x_scale": 2 * X_SCALE}}
    with pytest.raises(ModelFileError, match="x_scale"):
        FittedModel.from_state(res.model_state() | {"discrepancy": other}, res.bearing)
    # one saved before the shape group left out the gap alone (no shape_p_min) had other columns too
    older = saved | {"basis": {k: v for k, v in saved["basis"].items() if k != "shape_p_min"}}
    with pytest.raises(ModelFileError, match="shape_p_min"):
        FittedModel.from_state(res.model_state() | {"discrepancy": older}, res.bearing)


def test_no_shape_column_is_a_force_of_position_alone(saturated):
    # a flux family acts where there is flux: with both coils off, every shape column is zero (a spring of the
    # rotor's position is no law of flux density and gap), while the coupling group keeps its other-axis terms
    from ambfit.estimation.basis import Basis
    from ambfit.estimation.core import build_problem

    data = saturated[0]
    off = data.assign(i_top_A=0.0, i_bottom_A=0.0)
    prob, _ = build_problem(off)
    basis = Basis.of(saturated[1].bearing, ("shape",), prob.readings)
    on = basis.matrix(build_problem(data)[0].readings)
    assert np.abs(on).max() > 0 and np.abs(basis.matrix(prob.readings)).max() == 0.0


def test_diagnosis_names_the_family_when_its_law_differs():
    # hysteresis whose loop width grows with the current (Rayleigh): the library's constant-width law leaves a third
    # of it, and its fit sets aside the readings where the loop is widest as outliers.  The family's signature,
    # fitted on those readings too (its law's parameters refitted to them first), reaches the noise floor held out:
    # the family is named by its widened law
    from ambfit import diagnosis
    from ambfit.rig.laws import RayleighHysteresis

    data = rig.simulate(rig.PAPER_RIG, _design(), [RayleighHysteresis(ratio=np.array([0.01, 0.008]))], seed=5).data
    d = diagnosis.diagnose(data, check_force=False, pairs=False)
    assert d.verdict == "hysteresis" and d.grade.by == "signature" and d.grade.explains, str(d)
    assert d.law.log_bayes_max > Rules().log_bayes_clear
    assert d.law.law.shrink < 0.9 <= d.law.shrink == d.shrink
    rec = d.to_json()
    assert rec["law"]["family"] == "hysteresis" and "discrepancy_fit" in rec
    assert [st["shrink"] for st in rec["steps"]] == [d.law.law.shrink, d.law.shrink]


def test_identify_writes_effects_and_discrepancy_into_the_model_for_ambfit_force(saturated, tmp_path):
    # the model JSON of identify --effect --discrepancy carries both; ambfit force predicts with them
    import json

    from typer.testing import CliRunner

    from ambfit.data import write_csv
    from ambfit.faces.cli import app

    data, _, _ = saturated
    csv, model = tmp_path / "sat.csv", tmp_path / "model.json"
    write_csv(data, csv)
    r = CliRunner().invoke(app, ["identify", str(csv), "--effect", "saturation", "--discrepancy", "--json", str(model)])
    assert r.exit_code == 0, r.output
    rec = json.loads(model.read_text())
    assert [e["name"] for e in rec["model_state"]["effects"]] == ["saturation"]
    assert "discrepancy" in rec["model_state"] and "discrepancy" in rec["force_check"]
    fm = FittedModel.from_json(rec, saturated[1].bearing)
    assert fm.model == "saturation+discrepancy"
    write_csv(data, tmp_path / "again.csv")
    r = CliRunner().invoke(app, ["identify", str(csv), str(tmp_path / "again.csv"), "--effect", "saturation"])
    assert r.exit_code == 2 and "one data set" in r.output


def _marginal_likelihood(x, y, scales, known):
    """``log N(y | 0, I + X S^2 X^T)`` (noise known), or with the noise level profiled out, ``max over sigma^2`` of
    ``N(0, sigma^2 (I + X S^2 X^T))`` at ``sigma^2 = y^T C^-1 y / n``: written directly, n x n."""
    from scipy.stats import multivariate_normal

    c = np.eye(len(y)) + (x * scales) @ (x * scales).T
    var = 1.0 if known else y @ np.linalg.solve(c, y) / len(y)
    return multivariate_normal.logpdf(y, cov=var * c)


def test_the_evidence_grid_is_the_gaussian_marginal_likelihood():
    """``_Evidence`` (the m x m identities of its docstring) against the marginal likelihood written directly,
    each scale vector reached as the grid of its last column with the others held."""
    from ambfit.estimation.discrepancy import _Evidence

    rng = np.random.default_rng(3)
    x, y = rng.normal(size=(40, 5)), rng.normal(size=40)
    scales = np.array([[0.0] * 5, [0.3, 0.3, 1.0, 2.0, 0.0], [1e-3, 5.0, 0.1, 0.1, 0.1]])
    last = np.arange(5) == 4
    for known in (True, False):
        ev = _Evidence(x, y, known)
        for s in scales:
            value = ev.along(s, last, [s[4]])[0]
            # float64 round-off of two routes through a 40 x 40 determinant: ~1e-13 relative is observed
            assert value == pytest.approx(_marginal_likelihood(x, y, s, known), rel=1e-10)
        assert ev.common([0.0])[0] == pytest.approx(_marginal_likelihood(x, y, scales[0], known), rel=1e-10)


def test_each_grid_of_one_group_is_the_evidence_with_that_group_scaled():
    # _scales walks the grid of one group at a time from one factorization (block elimination of the other
    # groups, an eigendecomposition of the rest); every value must be the evidence of the full scales.
    from ambfit.estimation.discrepancy import TAU_GRID, _Evidence

    rng = np.random.default_rng(5)
    x, y = rng.normal(size=(60, 7)), rng.normal(size=60)
    group = np.array([0, 0, 1, 1, 1, 2, 2])
    grid = np.concatenate([[0.0], TAU_GRID])
    for known in (True, False):
        ev = _Evidence(x, y, known)
        for tau in ([0.3, 0.0, 2.0], [1e-3, 5.0, 0.1], [0.0, 0.0, 0.0]):
            for g in range(3):
                trials = np.repeat(np.asarray(tau)[None, :], len(grid), axis=0)
                trials[:, g] = grid
                # ~1e-12 relative agreement is observed (two routes through a 60 x 60 determinant)
                np.testing.assert_allclose(ev.along(np.asarray(tau)[group], group == g, grid),
                                           [_marginal_likelihood(x, y, t[group], known) for t in trials], rtol=1e-9)
        np.testing.assert_allclose(ev.common(grid), [_marginal_likelihood(x, y, np.full(7, t), known) for t in grid],
                                   rtol=1e-9)


def test_a_correction_on_rows_the_fit_did_not_use_refits_the_laws_parameters(saturated):
    """Fitted on more rows than the law's fit used (a widened law learns from its law's outliers), the correction
    first moves the law's parameters, linearised, to those rows: the ideal law fitted on the lowest bias alone is
    wrong about gap and k for the others in a way no column orthogonal to them can carry."""
    data, res, _ = saturated
    low = (data["bias_A"] == data["bias_A"].min()).to_numpy()
    part = fit(data, loss="linear", mask=low.astype(float), throw=False)
    z = part.residuals[:len(data)]
    d = fit_discrepancy(part, data, mask=np.ones(len(data)))
    left = np.mean((z + d.row_correction) ** 2)
    assert np.mean(z**2) > 20 * left and left < 2.0, (np.mean(z**2), left)


def test_the_prior_scales_are_the_marginal_likelihoods_highest_maximum_whatever_the_groups_order():
    """Two groups that can carry the same structure give the marginal likelihood two maxima, one per group: a
    Rayleigh loop is in the direction group (b^p xi^q by approach direction) and, less well, in the plays of the
    memory group.  The ascent from one common scale ends in the plays' maximum; the search from each group alone
    finds the direction group's, far higher, in either order of the groups."""
    from ambfit.rig.laws import RayleighHysteresis

    data = rig.simulate(rig.PAPER_RIG, _design(), [RayleighHysteresis(ratio=np.array([0.01, 0.008]))], seed=5).data
    res = fit(data, [E.Hysteresis()], throw=False)
    kept = res.fitted_rows
    for groups in (("hysteresis", "memory"), ("memory", "hysteresis")):
        d = fit_discrepancy(res, data, groups=groups)
        assert d.log_bayes["hysteresis"] > 1000 and d.log_bayes["memory"] < 5, (groups, d.log_bayes)
        assert np.mean((res.residuals + d.row_correction)[kept] ** 2) < 1.0
