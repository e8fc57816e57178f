"""Running a diagnosis' independent fits on a few threads at once, in order, with BLAS held to one thread each."""

from __future__ import annotations

import threading


class _Each:
    """``each(fn, items)``: ``[fn(x) for x in items]``, ``threads`` at a time, in order.  The compiled solves
    release the interpreter, so one thread's solve runs while another prepares its fit; every task runs in a copy
    of the caller's context (the compiled set and the owned table are context variables).  While the threads
    run, BLAS is held to one thread each (threadpoolctl): its own worker threads, spinning between the small
    matrix products of a fit, would take the core the second fit needs (``benchmarks/diagnose_speed.py`` compares
    one fit at a time with two).  The limit is process-wide: set by the first of overlapping diagnoses, restored
    by the last."""

    _lock = threading.Lock()
    _active = 0
    _limits = None

    def __init__(self, threads: int):
        if not isinstance(threads, int) or threads < 1:
            raise ValueError(f"threads must be a whole number of at least 1, got {threads!r}")
        self.threads = threads
        self.pool = None

    def __enter__(self):
        if self.threads > 1:
            from concurrent.futures import ThreadPoolExecutor

            from threadpoolctl import threadpool_limits

            with _Each._lock:
                if _Each._active == 0:
                    _Each._limits = threadpool_limits(limits=1, user_api="blas")
                _Each._active += 1
            self.pool = ThreadPoolExecutor(self.threads, thread_name_prefix="ambfit-diagnose")
        return self

    def __exit__(self, *exc):
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)
            with _Each._lock:
                _Each._active -= 1
                if _Each._active == 0:
                    _Each._limits.restore_original_limits()

    def __call__(self, fn, items) -> list:
        return [f.result() for f in [self.submit(fn, x) for x in items]]

    def submit(self, fn, *args):
        """``fn(*args)`` as a future: queued on the pool (a task may queue more), or run now without one."""
        if self.pool is None:
            from concurrent.futures import Future

            done = Future()
            done.set_result(fn(*args))
            return done
        import contextvars

        return self.pool.submit(contextvars.copy_context().run, fn, *args)
