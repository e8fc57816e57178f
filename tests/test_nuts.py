"""BlackJAX's NUTS (``ambfit[nuts]``) beside emcee: the same posterior, a second opinion."""

import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from ambfit import rig
from ambfit.estimation import bayes, fit
from ambfit.faces.cli import app
from ambfit.rig import protocol as P


@pytest.fixture(scope="module")
def table2():
    return rig.simulate(rig.PAPER_RIG, P.paper_table2(center=(-33.3e-6, 11.3e-6)), seed=4).data


@pytest.fixture(scope="module")
def runs(table2):
    """The least-squares fit, emcee (2000 steps: ESS ~8000, enough for the comparison) and NUTS on one data set."""
    pytest.importorskip("blackjax")
    from ambfit.estimation.nuts import sample_nuts

    ls = fit.fit(table2)
    return ls, bayes.sample(table2, seed=3, ls=ls, n_steps=2000, max_steps=2000), sample_nuts(table2, seed=3, ls=ls)


def test_nuts_and_emcee_draw_the_same_posterior(runs):
    _, e, n = runs
    assert n.sampler == "nuts" and n.to_json()["sampler"] == "nuts" and n.converged
    assert "0 divergent" in n.message
    ess = n.to_json()["params"]
    for name in e.names:
        sd = e.error(name)
        # Monte Carlo error of each mean: sd / sqrt(ESS) with ESS of thousands: 0.02 sd for the difference;
        # 0.1 sd is 5 of those.  Each sd is known to ~1 % (1 / sqrt(2 ESS)): 5 % is 5 of those.
        assert abs(n.value(name) - e.value(name)) < 0.1 * sd, name
        assert n.error(name) == pytest.approx(sd, rel=0.05), name
    assert min(p["ess_bulk"] for p in ess.values()) > 2000         # NUTS on a near-Gaussian: ESS ~ draws
    assert n.draws.shape == (4, 1000, len(e.names)) and n.datatree.sample_stats["diverging"].shape == (4, 1000)


def test_sample_names_the_extra_when_blackjax_is_missing(tmp_path, monkeypatch):
    data = tmp_path / "t.csv"
    rig.simulate(rig.PAPER_RIG, P.paper_table2(center=(-33.3e-6, 11.3e-6)), seed=4).data.to_csv(data, index=False)
    monkeypatch.setitem(sys.modules, "blackjax", None)                   # import blackjax raises ImportError
    r = CliRunner().invoke(app, ["sample", str(data), "--sampler", "nuts"])
    assert r.exit_code == 2 and "pip install 'ambfit[nuts]'" in r.output, r.output
    r = CliRunner().invoke(app, ["sample", str(data), "--sampler", "nuts", "--walkers", "16"])
    assert r.exit_code == 2 and "--walkers is emcee's" in r.output, r.output


def test_nuts_draws_sit_in_the_parameters_own_coordinates(runs):
    # the whitening z = z_hat + L u is undone for every draw: the draws' covariance is the least-squares one
    ls, _, n = runs
    cov = np.cov(n.draws.reshape(-1, len(n.names)).T)
    rel = np.sqrt(np.diag(cov)) / np.sqrt(np.diag(ls.cov))
    assert np.all(np.abs(rel - 1) < 0.1), rel
    corr = cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
    corr_ls = ls.cov / np.sqrt(np.outer(np.diag(ls.cov), np.diag(ls.cov)))
    assert np.allclose(corr, corr_ls, atol=0.05)


def test_the_command_lines_sampler_defaults_are_the_librarys():
    from ambfit.estimation import nuts
    from ambfit.faces.cli import sample

    assert (sample.EMCEE_STEPS, sample.MAX_STEPS, sample.NUTS_DRAWS) == (bayes.N_STEPS, bayes.MAX_STEPS, nuts.N_DRAWS)
