"""The independent ensembles that run in lockstep inside one emcee sampler (``ensembles.BlockStretchMove``)."""

import emcee
import numpy as np
import pytest

from ambfit.estimation.ensembles import BlockStretchMove, block_chain, block_tau, integrated_time

COV = np.array([[1.0, 0.8], [0.8, 1.0]])
PREC = np.linalg.inv(COV)


def gaussian(zs):
    return -0.5 * np.einsum("ni,ij,nj->n", zs, PREC, zs)


def sampler(blocks, per, seed=0):
    s = emcee.EnsembleSampler(blocks * per, 2, gaussian, vectorize=True, moves=BlockStretchMove(blocks))
    s.random_state = np.random.RandomState(seed).get_state()
    return s


def test_a_walker_moves_only_along_its_own_ensemble():
    # two ensembles started in tiny balls far apart: a stretch from a partner of the other ensemble would land a
    # walker between the balls; with partners from its own ensemble every walker stays within its ball's stretch
    rng = np.random.default_rng(1)
    centres = np.array([[5.0, 5.0], [-5.0, -5.0]])
    start = np.repeat(centres, 8, axis=0) + 1e-3 * rng.standard_normal((16, 2))
    s = sampler(2, 8)
    for _ in range(5):
        s.run_mcmc(start if s.iteration == 0 else None, 1, progress=False)
        chain = block_chain(s, 2)[:, -1]                       # [blocks, walkers, 2]
        for b in range(2):
            assert np.max(np.abs(chain[b] - centres[b])) < 1.0, (s.iteration, chain[b])


def test_the_ensembles_sample_the_target():
    # a correlated Gaussian: mean, covariance and each ensemble's acceptance as emcee's own stretch move gives
    s = sampler(3, 16, seed=2)
    start = np.random.default_rng(2).standard_normal((48, 2))
    s.run_mcmc(start, 4000, progress=False)
    draws = s.get_chain(discard=500).reshape(-1, 2)
    assert np.allclose(draws.mean(axis=0), 0.0, atol=0.08)
    assert np.allclose(np.cov(draws.T), COV, atol=0.08)
    plain = emcee.EnsembleSampler(16, 2, gaussian, vectorize=True)
    plain.random_state = np.random.RandomState(2).get_state()
    plain.run_mcmc(start[:16], 4000, progress=False)
    per_block = s.acceptance_fraction.reshape(3, 16).mean(axis=1)
    assert np.allclose(per_block, plain.acceptance_fraction.mean(), atol=0.03)


def test_too_few_walkers_per_ensemble_are_refused():
    s = sampler(3, 3)                      # 9 walkers: ensembles of 3 < twice the 2 dimensions
    with pytest.raises(RuntimeError, match="9 walkers do not make 3 ensembles of at least 4"):
        s.run_mcmc(np.random.default_rng(0).standard_normal((9, 2)), 1, progress=False)


def test_the_batched_autocorrelation_time_is_emcees():
    rng = np.random.default_rng(3)
    chain = np.cumsum(rng.standard_normal((1500, 12, 3)), axis=0) * 0.05 + rng.standard_normal((1500, 12, 3))
    assert np.allclose(integrated_time(chain), emcee.autocorr.integrated_time(chain, tol=0), rtol=1e-12)
    s = sampler(2, 8, seed=4)
    s.run_mcmc(rng.standard_normal((16, 2)), 300, progress=False)
    tau = block_tau(s, 2)
    for b, c in enumerate(block_chain(s, 2)):
        assert np.allclose(tau[b], emcee.autocorr.integrated_time(c, tol=0), rtol=1e-12)
