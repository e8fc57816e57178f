"""Running emcee ensembles until they are long enough: steps in pieces with progress reports, extension to a
multiple of the integrated autocorrelation time, and the test that tau has settled (used by
:func:`ambfit.estimation.bayes.sample`).

The independent ensembles run in lockstep inside one emcee sampler (:class:`BlockStretchMove`): each walker's
stretch partner comes from its own ensemble, so they never interact, while one vectorised log-probability call
per half-step serves all of them.

Reference: emcee's documentation, "Autocorrelation analysis" (run for at least 50 tau; tau from a chain of 50 tau
scatters by about 10 %).
"""

from __future__ import annotations

import contextlib
import signal
import threading

import emcee
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


class BlockStretchMove(emcee.moves.StretchMove):
    """The stretch move (Goodman & Weare 2010, emcee's default) on ``blocks`` independent ensembles held as one
    emcee sampler's walkers: walker ``j`` belongs to ensemble ``j // (n_walkers // blocks)``, each ensemble is split
    in two random halves every step, and a walker's partner is drawn from the other half of its own ensemble.  No
    walker ever sees another ensemble's, so the ensembles are independent chains (R-hat across them is valid),
    and each half-step evaluates every ensemble's walkers in one call of the vectorised log-probability."""

    def __init__(self, blocks: int, a: float = 2.0):
        super().__init__(a=a)
        self.blocks = int(blocks)

    def propose(self, model, state):
        n, ndim = state.coords.shape
        per = n // self.blocks
        if per * self.blocks != n or per < 2 * ndim:
            raise RuntimeError(f"{n} walkers do not make {self.blocks} ensembles of at least {2 * ndim}")
        # each ensemble's walkers split into two halves at random (emcee's randomize_split, per ensemble)
        half = np.tile(np.arange(per) % 2, self.blocks)
        for b in range(self.blocks):
            model.random.shuffle(half[b * per:(b + 1) * per])
        block = np.arange(n) // per
        accepted = np.zeros(n, dtype=bool)
        for split in (0, 1):
            moving = np.nonzero(half == split)[0]
            # the partners: for each moving walker, one of its own ensemble's other half, at random
            others = np.nonzero(half != split)[0]            # (in walker order: grouped by ensemble)
            count = np.bincount(block[others], minlength=self.blocks)
            first = np.cumsum(count) - count
            b = block[moving]
            partner = others[first[b] + (model.random.rand(len(moving)) * count[b]).astype(int)]
            zz = ((self.a - 1.0) * model.random.rand(len(moving)) + 1) ** 2.0 / self.a
            factors = (ndim - 1.0) * np.log(zz)
            c = state.coords[partner]
            q = c - (c - state.coords[moving]) * zz[:, None]
            new_log_probs, new_blobs = model.compute_log_prob_fn(q)
            ok = factors + new_log_probs - state.log_prob[moving] > np.log(model.random.rand(len(moving)))
            accepted[moving[ok]] = True
            S1 = half == split
            state = self.update(state, emcee.State(q, log_prob=new_log_probs, blobs=new_blobs), accepted, S1)
        return state, accepted


def block_chain(sampler, blocks: int) -> np.ndarray:
    """The chain of a :class:`BlockStretchMove` sampler as ``[blocks, steps, walkers, ndim]``."""
    chain = sampler.get_chain()
    steps, n, ndim = chain.shape
    return chain.reshape(steps, blocks, n // blocks, ndim).transpose(1, 0, 2, 3)


def integrated_time(chain: np.ndarray, c: float = 5.0) -> np.ndarray:
    """The integrated autocorrelation time of each parameter of one ensemble's ``chain [steps, walkers, ndim]``:
    emcee's estimate (``emcee.autocorr.integrated_time(chain, c, tol=0)``: the walkers' normalised
    autocorrelation functions averaged, summed up to Sokal's window ``c tau``), with every walker and parameter
    in one FFT instead of one each."""
    import scipy.fft

    n = len(chain)
    size = scipy.fft.next_fast_len(2 * n - 1, real=True)        # (zero padding past 2n - 1: no wrap-around)
    f = scipy.fft.rfft(chain - chain.mean(axis=0), n=size, axis=0, workers=-1)
    acf = scipy.fft.irfft(f * np.conjugate(f), n=size, axis=0, workers=-1)[:n]
    acf = (acf / acf[0]).mean(axis=1)                                      # [steps, ndim]
    taus = 2.0 * np.cumsum(acf, axis=0) - 1.0
    inside = np.arange(n)[:, None] < c * taus
    window = np.where(inside.any(axis=0), inside.argmin(axis=0), n - 1)
    return taus[window, np.arange(taus.shape[1])]


def block_tau(sampler, blocks: int) -> np.ndarray:
    """Each ensemble's integrated autocorrelation time per parameter, ``[blocks, ndim]`` (on that ensemble's
    walkers alone)."""
    return np.array([integrated_time(c) for c in block_chain(sampler, blocks)])


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


def advance(sampler, start, n: int, tally: Tally, what: str, blocks: int = 1) -> None:
    """``n`` more steps of ``sampler`` (holding ``blocks`` ensembles) from ``start`` (None: where it stopped),
    reporting after each piece; Ctrl-C stops the run at the end of the piece (:func:`interrupt_between_pieces`)."""
    tally(what)
    chunk = min(max(1, -(-n // PROGRESS_CHUNKS)), PIECE_STEPS)
    with interrupt_between_pieces() as check:
        for done in range(0, n, chunk):
            k = min(chunk, n - done)
            sampler.run_mcmc(start if done == 0 else None, k, progress=False)
            tally(what, k * blocks)
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


def run_until_settled(sampler, blocks: int, n_steps: int, max_steps: int, min_tau_multiple: float, tally: Tally):
    """Extend the ``blocks`` ensembles of ``sampler`` (:class:`BlockStretchMove`) until the run is
    ``min_tau_multiple`` times their largest tau and tau has settled, or ``max_steps`` is reached.  Returns
    ``(steps, tau[ensembles, p], settled)``."""
    steps = n_steps
    tau = block_tau(sampler, blocks)
    settled = True   # a run long enough at once needs no second estimate (emcee: 50 tau is reliable)
    while steps < min_tau_multiple * np.max(tau) or not settled:
        if steps >= max_steps:
            break
        target = int(np.ceil(1.1 * min_tau_multiple * np.max(tau)))
        extra = min(max(target - steps, n_steps // 4, 100), max_steps - steps)
        tally.total += extra * blocks
        advance(sampler, None, extra, tally, f"{PHASE}: {extra} more to reach {min_tau_multiple:g} x tau "
                                             f"{np.max(tau):.0f}", blocks)
        steps += extra
        new = block_tau(sampler, blocks)
        settled = bool(np.all(np.abs(new - tau) <= TAU_TOLERANCE * new))
        tau = new
    return steps, tau, settled
