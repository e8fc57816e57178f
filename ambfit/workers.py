"""Worker processes of :class:`ambfit.engine.Engine`: how they are set up and how one task runs in them.

A worker process (a ``distributed.LocalCluster`` worker on this machine, or one of any Dask
cluster) is prepared once, by a worker plugin, also when it joins later: JAX in float64 and,
unless switched off, the persistent compilation cache of :mod:`ambfit._jaxcache`, so that a
worker reads the code another run already compiled.  Local workers get their own Dask and XLA
settings (:data:`WORKER_CONFIG`, :data:`KEEP_MALLOC_DEFAULTS`, :data:`WORKER_XLA_FLAGS`).  One
task is one call of the mapped function on a chunk of items (:func:`_run_chunk`).

Dask is imported only here, and only when work leaves this process.
"""

from __future__ import annotations

import os

INSTALL_HINT = "install ambfit[dask] (pip install 'ambfit[dask]', i.e. dask[distributed])"

WORKER_CONFIG = {"distributed.worker.profile.enabled": False}
"""Dask settings of local worker processes: no statistical profiler (it samples every worker thread's stack, which on
this Python-heavy work takes about a third of the workers' CPU: ``benchmarks/scale.py``).  Workers of a cluster you
start yourself take it from their own configuration (``distributed.worker.profile.enabled: false``)."""

KEEP_MALLOC_DEFAULTS = ("MALLOC_TRIM_THRESHOLD_",)
"""Environment variables Dask sets for its worker processes that local workers go without.  Dask sets
``MALLOC_TRIM_THRESHOLD_=65536`` to hand freed memory back sooner; setting it also switches off glibc's dynamic
mmap threshold, so every array above 128 kB is mapped and unmapped afresh: on the many mid-sized arrays of a
vmapped batch fit that costs about a tenth of the workers' CPU (``benchmarks/scale.py``)."""

WORKER_XLA_FLAGS = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
"""XLA flags of local worker processes: one compute thread each, so N workers use N cores and do not fight over
them (XLA's default thread pool in every process would use every core)."""


class EngineError(RuntimeError):
    """The engine cannot run: Dask is not installed, or the scheduler cannot be reached; the message says what to do."""


def _import_distributed():
    try:
        import distributed
    except ImportError as exc:
        raise EngineError(f"running on worker processes or a cluster needs Dask: {INSTALL_HINT} ({exc})") from None
    return distributed


def _run_chunk(fn, chunk, seeds, *, prepare: bool, compilation_cache: bool = True) -> list:
    """One task: ``fn`` on one chunk, checked to give one result per item."""
    if prepare:
        prepare_worker(compilation_cache)
    out = list(fn(chunk) if seeds is None else fn(chunk, seeds))
    if len(out) != len(chunk):
        raise EngineError(f"{getattr(fn, '__name__', fn)!r} returned {len(out)} results for a chunk of {len(chunk)} "
                          "items; a chunk function must return one result per item")
    return out


def _call_prepared(fn, compilation_cache: bool):
    prepare_worker(compilation_cache)
    return fn()


_PREPARED: dict = {}


def prepare_worker(compilation_cache: bool = True) -> dict:
    """Make this (worker) process ready for ambfit: JAX in float64 and, if asked, the persistent compilation cache.

    Idempotent.  Returns what it found: ``{"x64": bool, "cache": path or None, "pid": int}``.
    """
    key = bool(compilation_cache)
    if key not in _PREPARED:
        import jax

        # (importing this module ran ambfit/__init__.py, which switches JAX to float64 before it makes an array;
        # this makes sure, should anything have imported JAX without it first)
        jax.config.update("jax_enable_x64", True)
        if compilation_cache:
            from ambfit._jaxcache import enable_compilation_cache

            enable_compilation_cache()
        _PREPARED[key] = True
    import jax

    return {"x64": bool(jax.config.jax_enable_x64), "cache": jax.config.jax_compilation_cache_dir,
            "pid": os.getpid()}


def _worker_plugin(compilation_cache: bool):
    """A ``distributed.WorkerPlugin`` that prepares every worker, also those that join later (adaptive clusters)."""
    distributed = _import_distributed()

    class AmbfitSetup(distributed.WorkerPlugin):
        def __init__(self, cache):
            self.cache = cache

        def setup(self, worker):
            prepare_worker(self.cache)

    return AmbfitSetup(compilation_cache)
