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
from ambfit.faces.cli.app import app, err


def main():  # pragma: no cover - entry point
    """Run the command line; an unexpected error (a bug) ends in one line and exit 3, its traceback in a file."""
    try:
        app()
    except KeyboardInterrupt:
        err.print("[bold red]error:[/] interrupted; no output was written half-way (outputs are written "
                  "atomically)", highlight=False)
        raise SystemExit(130) from None
    except Exception as exc:  # noqa: BLE001 - nothing but a message reaches the user
        log = _log_traceback()
        err.print(f"[bold red]error:[/] unexpected {type(exc).__name__}: {exc}. This is a bug in ambfit, not in "
                  f"your data or options; please report it with the traceback in {log}", highlight=False,
                  soft_wrap=True)
        raise SystemExit(3) from None


def _log_traceback() -> str:
    import os
    import tempfile
    import traceback

    folder = os.path.join(os.path.expanduser("~"), ".cache", "ambfit")
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError:
        folder = tempfile.gettempdir()
    path = os.path.join(folder, "last-error.txt")
    try:
        with open(path, "w") as f:
            traceback.print_exc(file=f)
    except OSError:
        return "(the traceback could not be written)"
    return path


__all__ = ["app", "main"]
