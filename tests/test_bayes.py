"""Posterior sampling, ArviZ output, solution-space map and design recommendation (fast versions)."""

import json
import math

import numpy as np
import pytest

from ambfit import rig
from ambfit.estimation import bayes, conditioning, design, fit
from ambfit.rig import protocol as P


@pytest.fixture(scope="module")
def table2():
    return rig.simulate(rig.PAPER_RIG, P.paper_table2(center=(-33.3e-6, 11.3e-6)), seed=4).data


@pytest.fixture(scope="module")
def short_run(table2):
    return bayes.sample(table2, n_ensembles=2, n_steps=800, max_steps=800, seed=1)   # capped: too short on purpose


def test_posterior_recovers_truth_and_agrees_with_least_squares(short_run):
    post = short_run.datatree.posterior
    ls = short_run.ls
    truth = {"g_v0": 775.0, "v0": 33.3, "g_w0": 763.0, "w0": -11.3}
    for name, t in truth.items():
        v = np.asarray(post[name])
        assert abs(v.mean() - t) < 4 * v.std(), name
        # near-Gaussian posterior: mean and sd within 5 % of a sd / of the sd of least squares
        assert abs(v.mean() - ls.value(name) * 1e6) < 0.1 * ls.error(name) * 1e6, name
        assert v.std() == pytest.approx(ls.error(name) * 1e6, rel=0.1), name


def test_a_short_run_is_flagged_with_the_length_it_needs(short_run):
    assert short_run.too_short
    assert "too short and the cap of 800 steps was reached: run at least" in short_run.message
    js = short_run.to_json()
    assert js["method"] == "bayes" and js["converged"] is False
    for key in ("g_v0_um", "v0_um", "k_v_Nm2_per_A2"):
        assert set(js["params"][key]) >= {"value", "std", "hdi_low", "hdi_high", "r_hat", "ess_bulk"}
        p = js["params"][key]
        assert p["hdi_low"] < p["value"] < p["hdi_high"]


def test_netcdf_round_trip(short_run, tmp_path):
    import arviz as az
    path = tmp_path / "post.nc"
    short_run.datatree.to_netcdf(path, engine="h5netcdf")
    back = az.from_netcdf(path)
    np.testing.assert_allclose(np.asarray(back.posterior["g_v0"]), np.asarray(short_run.datatree.posterior["g_v0"]))
    assert back.log_likelihood["reading"].shape[-1] == 80
    loo = az.loo(back)
    assert np.isfinite(float(loo.elpd))


def test_prior_support_is_physical():
    post_prior = bayes.Prior()
    draws = post_prior.sample(np.random.default_rng(0), 1000)
    assert np.all(draws["g0"] > 0) and np.all(draws["k"] > 0)


def test_predictive_force(short_run):
    out = bayes.force_predictive(short_run, "v", [1.7], [1.3], [0.0])
    from ambfit.physics.model import ideal_force
    spec = rig.PAPER_RIG
    true = float(ideal_force(spec.g0[0], spec.x0[0], spec.force_constant, 1.7, 1.3, 0.0))
    assert abs(out["mean"][0] - true) < 4 * out["sd"][0]
    assert out["q03"][0] < out["mean"][0] < out["q97"][0]


def test_solution_space_grid_and_minimum(table2):
    res = fit.fit(table2)
    space = conditioning.solution_space(table2, "v", weights_at=res, **conditioning.PAPER_FIG2)
    assert space.chi2.shape == (401, 201)          # the paper's Fig. 2 axes at 1 µm
    g, x = space.minimum
    assert abs(g - res.value("g_v0")) <= 1e-6 and abs(x - res.value("v0")) <= 1e-6
    d = space.delta_chi2()
    # the valley runs along the weakest direction: Δχ² grows slower along it than across it
    v = conditioning.weakest_direction(res, "v")
    assert abs(v[0]) > abs(v[1])     # mostly along the gap
    perp = np.array([-v[1], v[0]])
    i0, j0 = np.argmin(np.abs(space.gap - g)), np.argmin(np.abs(space.origin - x))

    def at(direction, step=3e-6):
        i = i0 + int(round(direction[0] * step / 1e-6))
        j = j0 + int(round(direction[1] * step / 1e-6))
        return d[i, j]
    assert at(v) < at(perp)


def test_design_comparison_explains_the_paper():
    t = conditioning.compare_designs()
    per = t[t["loads"] == "load per position"].set_index("design")
    assert not np.isfinite(per.loc["current-only", "crlb_gap_um"])        # ill-conditioned: unbounded
    assert not np.isfinite(per.loc["position-only", "crlb_gap_um"])
    assert np.isfinite(per.loc["symmetric (paper)", "crlb_gap_um"])
    assert per.loc["rich", "crlb_gap_um"] < per.loc["symmetric (paper)", "crlb_gap_um"]


def test_design_recommendation_reduces_the_predicted_gap_error(table2):
    rec = design.recommend(table2, n_steps=3)
    after = rec.steps["predicted_std_after"].to_numpy()
    assert after[0] < rec.std_now and np.all(np.diff(after) < 0)
    assert set(rec.steps.columns) >= {"v_set_um", "w_set_um", "bias_A"}


def test_sample_cli_writes_netcdf_and_bayes_json(tmp_path):
    from typer.testing import CliRunner

    from ambfit.faces.cli import app
    d = rig.simulate(rig.PAPER_RIG, P.paper_table2(iterations=3, center=(-33.3e-6, 11.3e-6)), seed=2).data
    csv = tmp_path / "d.csv"
    d.to_csv(csv, index=False)
    out, js = tmp_path / "p.nc", tmp_path / "p.json"
    r = CliRunner().invoke(app, ["sample", str(csv), "--steps", "300", "--max-steps", "300", "--ensembles", "2", "--out", str(out),
                                 "--json", str(js), "--no-progress"])
    assert r.exit_code == 3 and "too short" in r.output     # 300 steps is well below 50 tau
    rec = json.loads(js.read_text())
    assert rec["method"] == "bayes" and out.exists()
    # the calibration's type-B terms beside the posterior sd (GUM): u_combined^2 = sd^2 + the terms', by hand
    for key in ("g_v0_um", "w0_um"):
        p = rec["params"][key]
        sd = next(t["u"] for t in p["budget"] if t["term"] == "posterior sd (type A)")
        assert sd == pytest.approx(p["std"], rel=1e-12)
        assert p["u_combined"] == pytest.approx(math.sqrt(sum(t["u"] ** 2 for t in p["budget"])), rel=1e-12)
        assert p["u_combined"] > p["std"]
        # the posterior with the calibration marginalised is wider than the posterior alone
        assert p["hdi_low_combined"] < p["hdi_low"] < p["hdi_high"] < p["hdi_high_combined"]


def test_sbc_small_fast_version():
    # The benchmark (benchmarks/sbc.py) runs 200 data sets; this twin runs 12 and checks the machinery:
    # ranks in range, and the 90 % intervals covering the truth about as often as they claim.
    from ambfit.studies import sbc
    cal = sbc.run(12, n_steps=600, seed=5)
    assert cal.ranks.shape == (12, 6) and cal.ranks.min() >= 0 and cal.ranks.max() <= cal.n_draws
    pooled = float(np.mean(cal.coverage[0.9]))
    # 72 pooled coverage indicators (correlated within a data set); a calibrated posterior gives ~0.9, and
    # below 0.7 happens by chance with probability < 0.1 % even counting the correlation as 12 independent sets
    assert pooled > 0.7


def test_a_short_start_is_extended_until_fifty_tau(table2):
    # Started far too short (300 steps), the run is extended until it is 50 autocorrelation times long and tau
    # has settled, and then counts as converged: the default `ambfit sample` succeeds on ordinary data.
    res = bayes.sample(table2, n_ensembles=2, n_steps=300, seed=3)
    assert res.n_steps > 300 and not res.too_short
    assert res.n_steps >= 50 * float(np.max(res.tau))
    assert "added to reach 50 tau" in res.message
    assert res.to_json()["converged"]


def test_posterior_variables_state_their_units_and_value_agrees_with_least_squares(short_run, tmp_path):
    """Issue 24: FitResult.value is in metres, the DataTree in µm, and nothing said so."""
    import arviz as az

    to_si = {"µm": 1e-6, "N·m²/A²": 1.0, "N": 1.0}          # the units a reader may meet in the tree
    post, ls = short_run.datatree.posterior, short_run.ls
    assert post["g_v0"].attrs["units"] == "µm" and post["k_v"].attrs["units"] == "N·m²/A²"
    assert ls.units["g_v0"] == short_run.units["g_v0"] == "m" and ls.units["k_v"] == "N·m²/A²"
    for name in ("g_v0", "v0", "g_w0", "w0", "k_v", "k_w"):
        mean_si = float(post[name].mean()) * to_si[post[name].attrs["units"]]
        assert mean_si == pytest.approx(short_run.value(name), rel=1e-12), name
        # near-Gaussian posterior: the mean within 0.1 least-squares sd of the estimate (as above)
        assert abs(short_run.value(name) - ls.value(name)) < 0.1 * ls.error(name), name
        assert short_run.error(name) == pytest.approx(ls.error(name), rel=0.1), name
    for var in post.data_vars:
        assert post[var].attrs["units"] in to_si, var
    for col in ("i_top_A", "v_um"):
        assert short_run.datatree.observed_data[col].attrs["units"] == col.rsplit("_", 1)[1].replace("um", "µm")
    path = tmp_path / "post.nc"
    short_run.datatree.to_netcdf(path, engine="h5netcdf")
    assert az.from_netcdf(path).posterior["w0"].attrs["units"] == "µm"


def test_progress_is_one_labelled_callback_and_the_sampler_draws_nothing(table2, capfd):
    """Issue 24: ``ambfit sample`` showed emcee's bars, one unlabelled bar per ensemble and extension (20)."""
    calls = []
    ls = fit.fit(table2)
    capfd.readouterr()
    bayes.sample(table2, n_ensembles=2, n_steps=60, max_steps=200, seed=2, ls=ls,
                 progress=lambda what, done, total: calls.append((what, done, total)))
    assert capfd.readouterr().err == ""                          # the library draws nothing itself
    assert calls and all(w.startswith(bayes.PHASE + ": ") for w, _, _ in calls)
    done = [d for _, d, _ in calls]
    assert done == sorted(done) and all(d <= t for _, d, t in calls)
    assert calls[-1][1] == calls[-1][2] == 2 * 200               # 60 steps, extended to the cap, both ensembles
    assert calls[0][0] == bayes.PHASE + ": 2 in lockstep" and "more to reach 50 x tau" in calls[-1][0]
    with pytest.raises(TypeError, match="callback"):
        bayes.sample(table2, n_ensembles=1, n_steps=10, ls=ls, progress=True)


def test_the_json_interval_is_the_contracts_94_percent_hdi(short_run):
    # contract section 2: the 94 % highest-density interval, here computed by hand over the pooled draws (the
    # narrowest window holding floor(0.94 n) of the sorted draws); a 90 % interval would sit 0.2 sd inside it
    js = short_run.to_json()
    assert js["hdi_prob"] == 0.94
    for name, key in (("g_v0", "g_v0_um"), ("v0", "v0_um")):
        x = np.sort(np.asarray(short_run.datatree.posterior[name]).ravel())
        k = int(np.floor(0.94 * len(x)))
        i = int(np.argmin(x[k:] - x[:len(x) - k]))
        p = js["params"][key]
        assert p["hdi_low"] == pytest.approx(x[i], abs=0.02 * p["std"]), name
        assert p["hdi_high"] == pytest.approx(x[i + k], abs=0.02 * p["std"]), name


def test_a_posterior_away_from_least_squares_is_flagged(short_run):
    # the short run agrees with its least-squares start to a fraction of an sd; the same draws moved by 2.5 sd
    # on g_v0 (and 1.5 sd on v0) disagree on g_v0 alone, in the JSON and in words
    import dataclasses

    a = short_run.agreement()
    assert a["disagrees"] == [] and a["text"] == "" and max(abs(z) for z in a["z"].values()) < 0.3
    draws = short_run.draws.copy()
    for name, k in (("g_v0", 2.5), ("v0", 1.5)):
        j = short_run.names.index(name)
        draws[..., j] += k * short_run.error(name)
    moved = dataclasses.replace(short_run, draws=draws)
    a = moved.agreement()
    assert a["disagrees"] == ["g_v0"] and a["z"]["g_v0"] == pytest.approx(2.5 + short_run.agreement()["z"]["g_v0"])
    assert "g_v0 (+2.5 sd)" in a["text"] and "not the Gaussian" in a["text"]
    assert short_run.to_json()["least_squares_agreement"]["threshold"] == 2.0


def test_divergent_transitions_unconverge_the_posterior_and_warn(short_run):
    # a NUTS run's divergences (set here on a posterior record) make it not converged and reach the warnings
    import dataclasses

    from ambfit.faces.warnings import posterior_warnings

    assert short_run.to_json()["divergent_transitions"] == 0
    bad = dataclasses.replace(short_run, too_short=False, divergent=3, sampler="nuts")
    rec = bad.to_json()
    assert rec["divergent_transitions"] == 3 and rec["converged"] is False
    assert any(w.startswith("3 divergent transition(s) of NUTS") for w in posterior_warnings(bad, rec))
