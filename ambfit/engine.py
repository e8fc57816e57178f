"""Where repeated work runs: in this process, on local worker processes, or on any Dask cluster.

Monte Carlo studies, simulation-based calibration, the paper's replicates and fleets of
bearings are many independent pieces of work.  :class:`Engine` maps a function over them
in *chunks*: each task is one call of the function on a list of items (a vmapped batch of
many data sets or replicates, not one fit), so scheduling costs little next to the work.

``Engine()``
    In this process, chunk after chunk (the default; Dask is not imported).
``Engine(workers=N)``
    ``N`` separate worker processes on this machine (a ``distributed.LocalCluster``, one
    thread each).
``Engine(scheduler="tcp://host:8786")``
    Any running Dask scheduler, e.g. a dask-jobqueue ``SLURMCluster``'s
    ``cluster.scheduler_address``.  Its workers need ambfit installed (the same version).

Seeds are per *item*: ``seed`` is spread with :meth:`numpy.random.SeedSequence.spawn` over
the items, so the results depend neither on the number of workers nor on the chunk size.
Progress goes through the ``progress(what, done, total)`` callback that every long
function of ambfit takes (the command line draws it).

Worker processes switch JAX to float64 (importing ambfit does it; the setup makes sure) and,
unless ``compilation_cache=False``, keep compiled code in the persistent compilation cache
(:mod:`ambfit._jaxcache`: ``$AMBFIT_JAX_CACHE``, default ``~/.cache/ambfit/jax``), so that a
worker does not spend its first seconds recompiling what another run already compiled; how a
worker is set up and runs a task is :mod:`ambfit.workers`.

Dask is an optional extra: ``pip install 'ambfit[dask]'``.

Example
-------
>>> def squares(items):
...     return [x * x for x in items]
>>> Engine().map_batches(squares, range(5), chunk_size=2)
[0, 1, 4, 9, 16]
>>> def draw(item, seed):
...     return float(np.random.default_rng(seed).normal())
>>> a = Engine().map(draw, range(4), seed=1, chunk_size=1)
>>> a == Engine().map(draw, range(4), seed=1, chunk_size=3)
True
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import math
import os
from collections.abc import Callable, Iterable, Iterator, Sequence

import numpy as np

from ambfit.workers import (
    KEEP_MALLOC_DEFAULTS,
    WORKER_CONFIG,
    WORKER_XLA_FLAGS,
    EngineError,
    _call_prepared,
    _import_distributed,
    _run_chunk,
    _worker_plugin,
)

TASKS_PER_WORKER = 4
"""Default number of chunks per worker: enough to balance uneven chunks, few enough that each task is a big batch."""

IN_PROCESS_CHUNKS = 10
"""Default number of chunks in this process (only for progress: the chunks run one after another)."""

_CURRENT: contextvars.ContextVar[Engine | None] = contextvars.ContextVar("ambfit_engine", default=None)


class Engine:
    """Where :meth:`map` and :meth:`map_batches` run (see the module docstring).

    Parameters
    ----------
    workers : int, optional
        Start this many local worker processes (one thread each) when the engine is entered.
    scheduler : str, optional
        Address of a running Dask scheduler (``"tcp://10.0.0.5:8786"``).
    timeout : float
        Seconds to wait for the scheduler (or the local cluster) before giving up.
    compilation_cache : bool
        Workers keep JAX's compiled code in the persistent cache (``$AMBFIT_JAX_CACHE``; ``off`` disables it).

    With neither ``workers`` nor ``scheduler`` the engine runs in this process.  Used as a context
    manager (``with Engine(workers=4) as e: ...``) it starts the cluster once, shuts it down at the end,
    and is the engine of every study called inside the block without ``workers``/``scheduler`` of its own
    (:func:`using`), the way a ``distributed.Client`` becomes Dask's default.
    """

    def __init__(self, workers: int | None = None, scheduler: str | None = None, *, timeout: float = 30.0,
                 compilation_cache: bool = True):
        if workers is not None and scheduler is not None:
            raise ValueError(f"give workers ({workers}) or scheduler ({scheduler!r}), not both: workers starts "
                             "local processes, scheduler connects to a running cluster")
        if workers is not None and (isinstance(workers, bool) or not isinstance(workers, (int, np.integer))
                                    or workers < 1):
            raise ValueError(f"workers must be a positive integer (processes on this machine), got {workers!r}")
        if scheduler is not None and (not isinstance(scheduler, str) or not scheduler.strip()):
            raise ValueError(f"scheduler must be a Dask scheduler address such as 'tcp://host:8786', got {scheduler!r}")
        self.workers = None if workers is None else int(workers)
        self.scheduler = None if scheduler is None else scheduler.strip()
        self.timeout = float(timeout)
        self.compilation_cache = bool(compilation_cache)
        self._cluster = None
        self._client = None
        self._token = None
        self._depth = 0
        self._owned = False

    # --- what kind of engine ------------------------------------------------------------------------------

    @property
    def kind(self) -> str:
        """``"in-process"``, ``"local"`` (worker processes on this machine) or ``"cluster"`` (a scheduler)."""
        return "in-process" if self.in_process else ("local" if self.workers is not None else "cluster")

    @property
    def in_process(self) -> bool:
        return self.workers is None and self.scheduler is None

    @property
    def client(self):
        """The ``distributed.Client`` while the engine is open (None in-process)."""
        return self._client

    @property
    def n_workers(self) -> int:
        """Threads that run tasks at once: 1 in-process, else the cluster's worker threads (as they are now)."""
        if self.in_process:
            return 1
        if self._client is None:
            return self.workers or 1
        return max(1, sum(self._client.nthreads().values()))

    def __repr__(self) -> str:
        where = {"in-process": "in this process", "local": f"{self.workers} local worker processes",
                 "cluster": f"the Dask scheduler at {self.scheduler}"}[self.kind]
        return f"Engine({where})"

    # --- opening and closing ------------------------------------------------------------------------------

    def open(self) -> Engine:
        """Start the local cluster or connect to the scheduler (nothing in-process); idempotent."""
        if self.in_process or self._client is not None:
            return self
        distributed = _import_distributed()
        import logging

        if self.workers is not None:
            env = {"JAX_ENABLE_X64": "True",
                   "XLA_FLAGS": (os.environ.get("XLA_FLAGS", "") + " " + WORKER_XLA_FLAGS).strip()}
            import dask

            try:
                # Dask's statistical profiler samples every worker thread's stack every 10 ms: on this Python-heavy
                # work (JAX dispatch) it takes about a third of the workers' CPU (benchmarks/scale.py); the worker
                # processes receive this setting from the nanny
                spawn_env = {k: v for k, v in dask.config.get("distributed.nanny.pre-spawn-environ", {}).items()
                             if k not in KEEP_MALLOC_DEFAULTS}
                with dask.config.set({**WORKER_CONFIG, "distributed.nanny.pre-spawn-environ": spawn_env}):
                    self._cluster = distributed.LocalCluster(
                        n_workers=self.workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                        silence_logs=logging.ERROR, env=env)
                self._client = distributed.Client(self._cluster, timeout=self.timeout)
            except Exception as exc:  # noqa: BLE001 - any failure to start: close what started, say what failed
                self.close()
                raise EngineError(f"could not start {self.workers} local Dask worker processes: {exc}") from exc
        else:
            try:
                self._client = distributed.Client(self.scheduler, timeout=self.timeout)
            except (OSError, TimeoutError, ValueError) as exc:
                self.close()
                raise EngineError(
                    f"cannot reach the Dask scheduler at {self.scheduler!r} within {self.timeout:g} s ({exc}); "
                    "check the address (a dask-jobqueue cluster prints it as cluster.scheduler_address) and that "
                    "the scheduler is running and reachable from this machine") from None
            try:
                self._client.wait_for_workers(1, timeout=self.timeout)
            except (OSError, TimeoutError) as exc:
                self.close()
                raise EngineError(f"the Dask scheduler at {self.scheduler!r} has no workers after {self.timeout:g} s "
                                  f"({exc}); start some (dask worker {self.scheduler}, or cluster.scale(...))") from None
        try:
            self._client.register_plugin(_worker_plugin(self.compilation_cache), name="ambfit-setup")
        except Exception as exc:  # noqa: BLE001 - a worker that cannot import ambfit cannot run anything
            self.close()
            raise EngineError(f"the Dask workers cannot be prepared for ambfit ({exc}); every worker needs ambfit "
                              "(and its dependencies) installed, the same version as here") from exc
        return self

    def close(self) -> None:
        """Shut down the local cluster, or disconnect from the scheduler (which keeps running)."""
        client, cluster = self._client, self._cluster
        self._client = self._cluster = None
        with contextlib.suppress(Exception):
            if client is not None:
                client.close()
        with contextlib.suppress(Exception):
            if cluster is not None:
                cluster.close()

    def __enter__(self) -> Engine:
        if self._depth == 0:
            self._owned = self._client is None     # the block started it, so the block shuts it down
            self.open()
            self._token = _CURRENT.set(self)
        self._depth += 1
        return self

    def __exit__(self, *exc) -> None:
        self._depth -= 1
        if self._depth == 0:
            _CURRENT.reset(self._token)
            self._token = None
            if self._owned:
                self.close()

    # --- mapping ------------------------------------------------------------------------------------------

    def chunk_size(self, n: int) -> int:
        """The default number of items per task for ``n`` items."""
        parts = IN_PROCESS_CHUNKS if self.in_process else TASKS_PER_WORKER * self.n_workers
        return max(1, math.ceil(n / max(parts, 1)))

    def map_batches(self, fn: Callable, items: Iterable, *, seed=None, chunk_size: int | None = None,
                    progress=None, what: str = "items") -> list:
        """``fn`` on chunks of ``items``: one result per item, in the order of ``items``.

        Parameters
        ----------
        fn : callable
            ``fn(chunk) -> list`` (one result per item of the chunk), or with ``seed`` given
            ``fn(chunk, seeds)``, ``seeds`` the chunk's :class:`numpy.random.SeedSequence` s.  On worker
            processes ``fn`` and the items are pickled: a module-level function (or a
            :func:`functools.partial` of one) and plain data travel best.
        items : iterable
        seed : int or SeedSequence, optional
            Spawned into one seed per item (not per chunk or worker).
        chunk_size : int, optional
            Items per task (default: 4 tasks per worker; in-process 10 chunks).
        progress : callable, optional
            Called as ``progress(what, done, total)`` (items finished of all items).
        """
        items = list(items)
        n = len(items)
        seeds = None
        if seed is not None:
            seeds = (seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)).spawn(n)
        if chunk_size is not None and (isinstance(chunk_size, bool) or int(chunk_size) != chunk_size
                                       or chunk_size < 1):
            raise ValueError(f"chunk_size must be a positive integer, got {chunk_size!r}")
        if progress is not None:
            progress(what, 0, n)
        if not n:
            return []
        if self.in_process:
            return self._run_here(fn, items, seeds, int(chunk_size or self.chunk_size(n)), progress, what)
        with self:              # opens the cluster for this call unless an enclosing block already did
            return self._run_dask(fn, items, seeds, int(chunk_size or self.chunk_size(n)), progress, what)

    def map(self, fn: Callable, items: Iterable, *, seed=None, chunk_size: int | None = None, progress=None,
            what: str = "items") -> list:
        """``fn(item)`` (with ``seed``: ``fn(item, seed)``) for every item, in chunks; see :meth:`map_batches`."""
        return self.map_batches(functools.partial(_each, fn), items, seed=seed, chunk_size=chunk_size,
                                progress=progress, what=what)

    def on_every_worker(self, fn: Callable) -> dict:
        """``fn()`` once in every worker process (in-process: once here), e.g. to warm up compiled code before a
        timed run or to read each process's peak memory; ``{worker address: result}``."""
        if self.in_process:
            return {"this process": fn()}
        with self:
            futures = {address: self._client.submit(_call_prepared, fn, self.compilation_cache, workers=[address],
                                                    allow_other_workers=False, pure=False)
                       for address in self._client.nthreads()}
            return {address: f.result() for address, f in futures.items()}

    def _run_here(self, fn, items, seeds, size, progress, what) -> list:
        out = []
        for lo in range(0, len(items), size):
            out += _run_chunk(fn, items[lo:lo + size], None if seeds is None else seeds[lo:lo + size], prepare=False)
            if progress is not None:
                progress(what, len(out), len(items))
        return out

    def _run_dask(self, fn, items, seeds, size, progress, what) -> list:
        distributed = _import_distributed()
        starts = list(range(0, len(items), size))
        futures = {}
        for lo in starts:
            f = self._client.submit(_run_chunk, fn, items[lo:lo + size],
                                    None if seeds is None else seeds[lo:lo + size], prepare=True,
                                    compilation_cache=self.compilation_cache, pure=False)
            futures[f] = lo
        results, done = {}, 0
        try:
            for f in distributed.as_completed(list(futures)):
                part = f.result()
                results[futures[f]] = part
                done += len(part)
                if progress is not None:
                    progress(what, done, len(items))
        except BaseException:
            self._client.cancel(list(futures))
            raise
        return [r for lo in starts for r in results[lo]]


def _each(fn, chunk, seeds=None) -> list:
    """``fn`` item by item (the chunk function of :meth:`Engine.map`)."""
    if seeds is None:
        return [fn(item) for item in chunk]
    return [fn(item, s) for item, s in zip(chunk, seeds)]


@contextlib.contextmanager
def using(workers: int | None = None, scheduler: str | None = None) -> Iterator[Engine]:
    """The engine a study runs on: a new one for ``workers``/``scheduler`` (closed at the end), else the engine of
    an enclosing ``with Engine(...)`` block, else this process."""
    if workers is None and scheduler is None:
        current = _CURRENT.get()
        yield current if current is not None else Engine()
        return
    with Engine(workers, scheduler) as engine:
        yield engine


def map_batches(fn: Callable, items: Sequence, *, workers: int | None = None, scheduler: str | None = None,
                seed=None, chunk_size: int | None = None, progress=None, what: str = "items") -> list:
    """:meth:`Engine.map_batches` on the engine :func:`using` picks."""
    with using(workers, scheduler) as engine:
        return engine.map_batches(fn, items, seed=seed, chunk_size=chunk_size, progress=progress, what=what)


def map(fn: Callable, items: Sequence, *, workers: int | None = None, scheduler: str | None = None,  # noqa: A001
        seed=None, chunk_size: int | None = None, progress=None, what: str = "items") -> list:
    """:meth:`Engine.map` on the engine :func:`using` picks."""
    with using(workers, scheduler) as engine:
        return engine.map(fn, items, seed=seed, chunk_size=chunk_size, progress=progress, what=what)
