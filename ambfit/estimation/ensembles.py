"""Running emcee ensembles until they are long enough: steps in pieces with progress reports, extension to a
multiple of the integrated autocorrelation time, and the test that tau has settled (used by
:func:`ambfit.estimation.bayes.sample`).

Reference: emcee's documentation, "Autocorrelation analysis" (run for at least 50 tau; tau from a chain of 50 tau
scatters by about 10 %).
"""

from __future__ import annotations

import numpy as np

TAU_TOLERANCE = 0.1
"""When a run had to be extended, tau counts as settled once the last extension moved no ensemble's estimate by more
than this fraction.  An integrated autocorrelation time estimated from 50 tau of chain scatters by about 10 %
(emcee's documentation, "Autocorrelation analysis"), so a tighter test would chase that noise."""


class Tally:
    """Steps done and planned over all ensembles, reported to a ``progress(what, done, total)`` callback."""

    def __init__(self, progress, total: int):
        self.progress, self.done, self.total = progress, 0, total

    def __call__(self, what: str, steps: int = 0) -> None:
        self.done += steps
        if self.progress is not None:
            self.progress(what, self.done, self.total)


PHASE = "posterior steps, all ensembles"
"""The ``what`` of every progress report of :func:`ambfit.estimation.bayes.sample`, before ``": "`` and what runs now."""

PROGRESS_CHUNKS = 20
"""Progress reports per run of one ensemble: the run goes in this many pieces (the same chain as one run)."""


def advance(sampler, start, n: int, tally: Tally, what: str) -> None:
    """``n`` more steps of ``sampler`` from ``start`` (None: where it stopped), reporting after each piece."""
    tally(what)
    chunk = max(1, -(-n // PROGRESS_CHUNKS))
    for done in range(0, n, chunk):
        k = min(chunk, n - done)
        sampler.run_mcmc(start if done == 0 else None, k, progress=False)
        tally(what, k)


def run_until_settled(samplers, n_steps: int, max_steps: int, min_tau_multiple: float, tally: Tally):
    """Extend every ensemble until the run is ``min_tau_multiple`` times its largest tau and tau has settled, or
    ``max_steps`` is reached.  Returns ``(steps, tau[ensembles, p], settled)``."""
    steps = n_steps
    tau = np.array([s.get_autocorr_time(tol=0) for s in samplers])
    settled = True   # a run long enough at once needs no second estimate (emcee: 50 tau is reliable)
    while steps < min_tau_multiple * np.max(tau) or not settled:
        if steps >= max_steps:
            break
        target = int(np.ceil(1.1 * min_tau_multiple * np.max(tau)))
        extra = min(max(target - steps, n_steps // 4, 100), max_steps - steps)
        tally.total += extra * len(samplers)
        for e, s in enumerate(samplers):
            advance(s, None, extra, tally, f"{PHASE}: ensemble {e + 1} of {len(samplers)}, {extra} more to reach "
                                            f"{min_tau_multiple:g} x tau {np.max(tau):.0f}")
        steps += extra
        new = np.array([s.get_autocorr_time(tol=0) for s in samplers])
        settled = bool(np.all(np.abs(new - tau) <= TAU_TOLERANCE * new))
        tau = new
    return steps, tau, settled
