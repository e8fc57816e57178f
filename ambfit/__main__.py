"""``python -m ambfit``: the command line (same as the ``ambfit`` script)."""

from ambfit.faces.cli import entry

entry()
