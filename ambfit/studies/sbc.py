"""Simulation-based calibration (Talts et al. 2018, arXiv:1804.06788) of the posterior on the virtual rig.

Draw parameters from the prior, simulate a data set on the rig with them, sample
the posterior, and record the rank of each true value among the posterior draws.
If the sampler and the likelihood are right, the ranks are uniform and the
central credible intervals cover the truth at their nominal rate.

The design is fixed and independent of the drawn parameters (a design that
depended on the truth would carry information the posterior does not use).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from ambfit import rig
from ambfit.estimation.bayes import Prior, sample
from ambfit.estimation.units import BY_AXIS, FORCE_CONSTANTS, GAPS, ORIGINS
from ambfit.rig import protocol as P

SBC_PRIOR = Prior(gap=rig.PAPER_RIG.nominal_gap, gap_log_sd=0.05, origin_sd=30e-6, k=rig.PAPER_RIG.force_constant, k_log_sd=0.2)
"""The prior the calibration draws from and the sampler assumes (the paper's rig, nominal values)."""


NAMES = BY_AXIS["v"] + BY_AXIS["w"]
"""The calibrated parameters, in the order of :attr:`Calibration.names`."""


def sbc_design() -> P.Protocol:
    """Biases 1.4/1.6 A at ±20 and ±40 µm around the sensor zero, 3 iterations, the rotor's known load."""
    return P.perturbation((1.4, 1.6), (20e-6, 40e-6), center=(0.0, 0.0), iterations=3, experiment="sbc")


@dataclasses.dataclass(frozen=True)
class Calibration:
    """Ranks of the truth among ``n_draws`` posterior draws, and central-interval coverage."""

    names: list
    ranks: np.ndarray        # [datasets, params] in 0..n_draws
    n_draws: int
    coverage: dict           # {prob: array[params]}

    def chi2_uniformity(self, bins: int = 10) -> dict:
        """χ² test of uniform ranks per parameter: ``{name: (statistic, p-value)}``."""
        from scipy.stats import chisquare

        out = {}
        for j, n in enumerate(self.names):
            counts, _ = np.histogram(self.ranks[:, j], bins=bins, range=(0, self.n_draws + 1))
            res = chisquare(counts)
            out[n] = (float(res.statistic), float(res.pvalue))
        return out


def run(n_datasets: int, *, n_draws: int = 99, n_steps: int = 1500, n_ensembles: int = 2, seed: int = 0,
        noise: rig.Noise = rig.Noise(), probs=(0.5, 0.9), workers: int | None = None, scheduler: str | None = None,
        chunk_size: int | None = None, progress=None) -> Calibration:
    """SBC over ``n_datasets`` prior draws; ``n_draws`` thinned posterior draws per data set.

    Each data set has its own seed (``numpy.random.SeedSequence(seed).spawn(n_datasets)``: prior draw, noise,
    sampler and the choice of draws), so the result does not depend on where it runs: in this process (the
    default), on ``workers`` local processes or on the Dask cluster at ``scheduler`` (:mod:`ambfit.engine`; an
    enclosing ``with ambfit.engine.Engine(...)`` block is used when neither is given), in chunks of
    ``chunk_size`` data sets.  ``progress(what, done, total)`` is called as data sets finish (``"data sets"``).
    """
    from ambfit import engine

    one = functools.partial(_calibrate_one, n_draws=n_draws, n_steps=n_steps, n_ensembles=n_ensembles, noise=noise,
                            probs=tuple(probs))
    with engine.using(workers, scheduler) as eng:
        out = eng.map(one, range(n_datasets), seed=seed, chunk_size=chunk_size, progress=progress,
                      what="data sets")
    ranks = np.array([r for r, _ in out]).reshape(-1, len(NAMES))
    return Calibration(names=list(NAMES), ranks=ranks, n_draws=n_draws,
                       coverage={p: np.mean([c[p] for _, c in out], axis=0) for p in probs})


def _calibrate_one(_index: int, seed: np.random.SeedSequence, *, n_draws: int, n_steps: int, n_ensembles: int,
                   noise: rig.Noise, probs: tuple) -> tuple[list[int], dict]:
    """One data set of the calibration: the truth's rank among ``n_draws`` posterior draws per parameter, and
    whether each central interval covers it."""
    rng = np.random.default_rng(seed)
    th = SBC_PRIOR.sample(rng, 1)
    spec = rig.PAPER_RIG.with_truth(g0=th["g0"][0], x0=th["x0"][0], k=th["k"][0])
    data = rig.simulate(spec, sbc_design(), noise=noise, seed=rng).data
    # fixed-length runs: SBC calibrates the sampler as configured, and the benchmark's lengths are chosen for it
    res = sample(data, prior=SBC_PRIOR, n_ensembles=n_ensembles, n_steps=n_steps, max_steps=n_steps,
                 seed=int(rng.integers(2**31)))
    flat = res.draws.reshape(-1, res.draws.shape[-1])
    pick = flat[rng.choice(len(flat), size=n_draws, replace=False)]
    truth = dict(zip(GAPS + ORIGINS + FORCE_CONSTANTS, np.concatenate([th["g0"][0], th["x0"][0], th["k"][0]])))
    idx = [res.names.index(n) for n in NAMES]
    ranks = [int(np.sum(pick[:, i] < truth[n])) for i, n in zip(idx, NAMES)]
    t = np.array([truth[n] for n in NAMES])
    cover = {}
    for p in probs:
        lo, hi = np.quantile(flat[:, idx], [(1 - p) / 2, (1 + p) / 2], axis=0)
        cover[p] = (lo <= t) & (t <= hi)
    return ranks, cover
