"""JAX's persistent compilation cache for ambfit: compiled fits kept between runs and processes.

The command line and the engine's worker processes both call :func:`enable_compilation_cache`, so a
cold ``ambfit identify`` (or a fresh worker) reads the code another run already compiled instead of
compiling it again.  The cache lives in ``$AMBFIT_JAX_CACHE`` (default ``~/.cache/ambfit/jax``;
``off``, ``0``, ``none`` or an empty value disable it).  JAX is imported only when the cache is
enabled, so importing this module costs nothing.
"""

from __future__ import annotations

import os
from pathlib import Path


def enable_compilation_cache():
    """Persist JAX's compiled fits between runs (``$AMBFIT_JAX_CACHE``, default ``~/.cache/ambfit/jax``):
    a cold ``ambfit identify`` then skips most of its compile time."""
    import jax

    path = os.environ.get("AMBFIT_JAX_CACHE", os.path.join(os.path.expanduser("~"), ".cache", "ambfit", "jax"))
    if path.lower() in ("", "0", "off", "none"):
        return
    try:
        os.makedirs(path, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", path)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    except OSError:  # read-only home: run without the cache
        return
    _replace_corrupt_entries(Path(path))


def _replace_corrupt_entries(path: Path):
    """A cache entry that cannot be read (a crash while writing, a full disk) is deleted and compiled afresh.

    JAX warns about such an entry and compiles, but never overwrites it, so without this every later run
    warns again.  Guarded: if JAX's internals change, the cache simply works as JAX ships it.
    """
    try:
        from jax._src import compilation_cache as cc
    except ImportError:  # pragma: no cover - a JAX without this module
        return
    original = getattr(cc, "get_executable_and_time", None)
    if original is None or getattr(original, "_ambfit_guard", False):
        return

    def guarded(cache_key, *args, **kwargs):
        try:
            return original(cache_key, *args, **kwargs)
        except Exception:        # noqa: BLE001 - any unreadable entry: drop it, JAX then compiles and stores anew
            for entry in path.glob(f"{cache_key}*"):
                entry.unlink(missing_ok=True)
            return None, None

    guarded._ambfit_guard = True
    cc.get_executable_and_time = guarded
