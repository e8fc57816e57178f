"""The ``ambfit`` command line.

One module per group of commands (:mod:`~ambfit.faces.cli.simulate`,
:mod:`~ambfit.faces.cli.identify`, :mod:`~ambfit.faces.cli.sample`,
:mod:`~ambfit.faces.cli.explore`, :mod:`~ambfit.faces.cli.reports`,
:mod:`~ambfit.faces.cli.force`, :mod:`~ambfit.faces.cli.campaign`) registers on the Typer app of
:mod:`~ambfit.faces.cli.app`; ``identify`` shares :mod:`~ambfit.faces.cli.fitting` and
:mod:`~ambfit.faces.cli.groups` (several files or ``--by`` groups).  None of them imports JAX or
the estimation stack at module level, so ``ambfit --help`` stays fast.
"""

# Imported in the order --help lists them: the rig, estimation, exploration, reports.
from ambfit.faces.cli import simulate  # noqa: F401, I001  (registers its commands)
from ambfit.faces.cli import identify  # noqa: F401
from ambfit.faces.cli import sample  # noqa: F401
from ambfit.faces.cli import explore  # noqa: F401
from ambfit.faces.cli import reports  # noqa: F401
from ambfit.faces.cli import force  # noqa: F401
from ambfit.faces.cli import campaign  # noqa: F401
import errno
import os

from ambfit.faces.cli.app import INTERRUPTED, StreamError, app, err, escape, plain


def entry():  # pragma: no cover - entry point
    """The ``ambfit`` command (and ``python -m ambfit``): :func:`main`, then the process ends at once
    (:func:`_end`)."""
    try:
        main()
    except SystemExit as exc:
        _end(exc)
    _end(SystemExit(0))


def _end(exc: SystemExit) -> None:  # pragma: no cover - entry point
    """End the process as ``exc`` would once the output is flushed and the exit handlers have run, but without the
    interpreter's teardown (its modules and objects freed one by one, JAX's and XLA's among them), which takes
    longer than many commands' own work and is not needed at exit.  ``exc`` is raised as it is when something still
    needs the teardown or runs after it: a thread that is not a daemon (a normal exit waits for it), a profiler or
    debugger, ``python -i``, or ``AMBFIT_FAST_EXIT=0``."""
    import atexit
    import sys
    import threading

    code = exc.code
    others = [t for t in threading.enumerate() if t is not threading.main_thread() and not t.daemon]
    watched = sys.gettrace() is not None or sys.getprofile() is not None or bool(sys.flags.inspect) or \
        any(sys.monitoring.get_tool(i) is not None for i in range(6))
    if others or watched or os.environ.get("AMBFIT_FAST_EXIT", "1") == "0" or not (code is None or
                                                                                  isinstance(code, int)):
        raise exc                          # (a message, or another object: Python prints it and exits 1)
    _quiet_stdout()
    atexit._run_exitfuncs()                # (temporary folders, logging, JAX's own clean-up: as a normal exit)
    _quiet_stdout()
    os._exit(int(code or 0))


def main():  # pragma: no cover - entry point
    """Run the command line; an unexpected error (a bug) ends in one line and exit 3, its traceback in a file.
    Ends in ``SystemExit`` (the process lives on: a caller in Python, a test)."""
    _plain_where_needed()
    problem = _jax_cannot_start()
    if problem:
        err.print(f"[bold red]error:[/] {escape(problem)}", highlight=False, soft_wrap=True)
        raise SystemExit(2)
    try:
        app()
    except KeyboardInterrupt:
        err.print(f"[bold red]error:[/] {INTERRUPTED}", highlight=False)
        raise SystemExit(130) from None
    except RuntimeError as exc:
        if "Unable to initialize backend" not in str(exc):
            _unexpected(exc)
        backend = str(exc).split("'")[1] if str(exc).count("'") >= 2 else "?"
        err.print(f"[bold red]error:[/] JAX cannot start its {escape(backend)!r} backend (JAX_PLATFORMS="
                  f"{escape(repr(os.environ.get('JAX_PLATFORMS', '')))}): this machine has none; ambfit runs on "
                  "the CPU: unset JAX_PLATFORMS or set it to cpu", highlight=False, soft_wrap=True)
        raise SystemExit(2) from None
    except StreamError as exc:
        _quiet_stdout()
        if exc.errno != errno.EPIPE:      # a reader that stopped reading (| head) needs no message
            try:
                err.print(f"[bold red]error:[/] cannot write the output to the terminal or pipe ({escape(str(exc))}); "
                          "stopped there: a file it was to write after that is not written", highlight=False, soft_wrap=True)
            except StreamError:
                pass
        raise SystemExit(2) from None
    except Exception as exc:  # noqa: BLE001 - nothing but a message reaches the user
        _unexpected(exc)


def _quiet_stdout() -> None:
    """Point standard output and error at ``os.devnull``: the interpreter's last flush of a stream that cannot be
    written would fail again."""
    import sys

    for stream in (sys.stdout, sys.stderr):
        if stream is None:                 # (no stream at all: pythonw, or a closed descriptor)
            continue
        try:
            stream.flush()
        except (OSError, ValueError):
            try:
                os.dup2(os.open(os.devnull, os.O_WRONLY), stream.fileno())
            except (OSError, ValueError):
                pass


def _unexpected(exc: BaseException):
    """End a bug (``exc``, being handled) in one line and exit 3, its traceback in a file."""
    log = _log_traceback()
    err.print(f"[bold red]error:[/] unexpected {type(exc).__name__}: {escape(str(exc))}. This is a bug in ambfit, "
              f"not in your data or options; please report it with the traceback in {log}", highlight=False,
              soft_wrap=True)
    raise SystemExit(3) from None


def _cache_folder() -> str:
    """``~/.cache/ambfit``: the crash log and what the command line remembers between runs."""
    return os.path.join(os.path.expanduser("~"), ".cache", "ambfit")


def _jax_cannot_start() -> str | None:
    """Why JAX would abort in this environment, or None.  An ``XLA_FLAGS`` naming a flag XLA does not know ends
    the process from C++ beyond any handler, so it is tried in a child process first, once per value (the
    answer kept in ``~/.cache/ambfit``); ``--help`` and ``--version`` start no JAX and are not delayed."""
    import hashlib
    import subprocess
    import sys

    flags = os.environ.get("XLA_FLAGS", "").strip()
    if not flags or len(sys.argv) < 2 or {"--help", "--version"} & set(sys.argv[1:]):
        return None
    marker = os.path.join(_cache_folder(), f"xla-flags-{hashlib.sha256(flags.encode()).hexdigest()[:16]}.ok")
    if os.path.exists(marker):
        return None
    try:
        r = subprocess.run([sys.executable, "-c", "import jax; jax.devices()"], capture_output=True, text=True,
                           timeout=300)
    except (OSError, subprocess.SubprocessError):
        return None                     # cannot tell: let JAX try
    if r.returncode != 0:
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        said = next((ln for ln in lines if "XLA_FLAGS" in ln), lines[-1] if lines else f"exit {r.returncode}")
        return (f"JAX cannot start with XLA_FLAGS={flags!r} ({said.split('] ', 1)[-1].strip()}): unset XLA_FLAGS "
                "or correct it")
    try:
        os.makedirs(os.path.dirname(marker), exist_ok=True)
        open(marker, "a").close()
    except OSError:
        pass
    return None


def _plain_where_needed() -> None:
    """Standard output and error write :func:`plain` spellings where their encoding cannot write "µσχ²±"."""
    import codecs
    import sys

    codecs.register_error("ambfit.plain", plain)
    for stream in (sys.stdout, sys.stderr):
        try:
            "µσχ²±≤".encode(stream.encoding or "ascii")
        except (UnicodeEncodeError, LookupError):
            if hasattr(stream, "reconfigure"):
                stream.reconfigure(errors="ambfit.plain")
        except AttributeError:          # no stream (pythonw) or a stream without an encoding
            pass


def _log_traceback() -> str:
    """Write the traceback being handled to ``~/.cache/ambfit/last-error.txt`` (never through a link planted
    there), or to a new private file in the temporary folder when that folder cannot be made; its path."""
    import tempfile
    import traceback

    text = traceback.format_exc()
    folder = _cache_folder()
    try:
        os.makedirs(folder, mode=0o700, exist_ok=True)
        path = os.path.join(folder, "last-error.txt")
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_NOFOLLOW", 0), 0o600)
    except OSError:
        try:                            # a new file of its own (O_EXCL, mode 0600): nothing there to follow
            fd, path = tempfile.mkstemp(prefix="ambfit-error-", suffix=".txt")
        except OSError:
            return "(the traceback could not be written)"
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
    except OSError:
        return "(the traceback could not be written)"
    return path


__all__ = ["app", "entry", "main"]
