"""The ``ambfit`` command line.

One module per group of commands (:mod:`~ambfit.faces.cli.simulate`,
:mod:`~ambfit.faces.cli.identify`, :mod:`~ambfit.faces.cli.explore`,
:mod:`~ambfit.faces.cli.reports`) registers on the Typer app of
:mod:`~ambfit.faces.cli.app`.  None of them imports JAX or the estimation stack at
module level, so ``ambfit --help`` stays fast.
"""

# Imported in the order --help lists them: the rig, estimation, exploration, reports.
from ambfit.faces.cli import simulate  # noqa: F401, I001  (registers its commands)
from ambfit.faces.cli import identify  # noqa: F401
from ambfit.faces.cli import explore  # noqa: F401
from ambfit.faces.cli import reports  # noqa: F401
from ambfit.faces.cli.app import app


def main():  # pragma: no cover - entry point
    app()


__all__ = ["app", "main"]
