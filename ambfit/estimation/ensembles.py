"""Running emcee ensembles until they are long enough: steps in pieces with progress reports, extension to a
multiple of the integrated autocorrelation time, and the test that tau has settled (used by
:func:`ambfit.estimation.bayes.sample`).

Reference: emcee's documentation, "Autocorrelation analysis" (run for at least 50 tau; tau from a chain of 50 tau
scatters by about 10 %).
"""

from __future__ import annotations

import contextlib
import signal
import threading

import numpy as np

TAU_TOLERANCE = 0.1
"""When a run had to be extended, tau counts as settled once the last extension moved no ensemble's estimate by more
than this fraction.  An integrated autocorrelation time estimated from 50 tau of chain scatters by about 10 %
(emcee's documentation, "Autocorrelation analysis"), so a tighter test would chase that noise."""


MAX_CHAIN_BYTES = 2**32
"""Memory the chains may take (4 GiB of float64)."""


class SettingError(ValueError):
    """A sampler setting that cannot work on these data; ``setting`` names the argument (``"n_walkers"``, ...)."""

    def __init__(self, setting: str, value, problem: str):
        super().__init__(f"{setting}={value}: {problem}")
        self.setting, self.value, self.problem = setting, value, problem


def check_settings(*, n_ensembles: int, n_steps: int, max_steps: int, n_walkers: int | None = None,
                   names: list | None = None) -> None:
    """Raise :class:`SettingError` for settings that cannot work: fewer than one ensemble or step, a cap below the
    first run, fewer walkers than twice the parameters ``names`` (emcee's ensemble moves need them), chains over
    ``MAX_CHAIN_BYTES``."""
    for setting, value, least in (("n_ensembles", n_ensembles, 1), ("n_steps", n_steps, 1),
                                  ("max_steps", max_steps, max(n_steps, 1))):
        if value < least:
            raise SettingError(setting, value, f"must be at least {least}")
    if n_walkers is None:
        return
    ndim = len(names)
    if n_walkers < 2 * ndim:
        raise SettingError("n_walkers", n_walkers, f"must be at least {2 * ndim}, twice the parameters {names}")
    if (size := n_ensembles * n_walkers * max_steps * (ndim + 1) * 8) > MAX_CHAIN_BYTES:
        raise SettingError("max_steps", max_steps, f"{n_ensembles} ensembles x {n_walkers} walkers x {max_steps} "
                           f"steps would take {size / 2**30:.1f} GiB of chains, over {MAX_CHAIN_BYTES / 2**30:g} GiB")


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


PIECE_STEPS = 200
"""Most steps in one piece: Ctrl-C waits at most this long (a piece of a 200,000-step run would be minutes)."""


def advance(sampler, start, n: int, tally: Tally, what: str) -> None:
    """``n`` more steps of ``sampler`` from ``start`` (None: where it stopped), reporting after each piece; Ctrl-C
    stops the run at the end of the piece (:func:`interrupt_between_pieces`)."""
    tally(what)
    chunk = min(max(1, -(-n // PROGRESS_CHUNKS)), PIECE_STEPS)
    with interrupt_between_pieces() as check:
        for done in range(0, n, chunk):
            k = min(chunk, n - done)
            sampler.run_mcmc(start if done == 0 else None, k, progress=False)
            tally(what, k)
            check()


@contextlib.contextmanager
def interrupt_between_pieces():
    """Hold Ctrl-C (SIGINT) while emcee runs and raise :class:`KeyboardInterrupt` when ``check()`` is called after a
    piece: emcee prints every walker's position and a traceback for any exception in the log-probability, the
    interrupt too.  Only in the main thread and under Python's own SIGINT handler (else ``check`` does nothing
    and an interrupt arrives as usual)."""
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
        yield lambda: None
        return
    held = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum))

    def check():
        if held:
            raise KeyboardInterrupt

    try:
        yield check
    finally:
        signal.signal(signal.SIGINT, previous)


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
