"""``python -m ambfit``: the command line (same as the ``ambfit`` script)."""

from ambfit.faces.cli import entry

if __name__ == "__main__":
    entry()
