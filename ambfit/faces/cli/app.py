"""The ``ambfit`` command line's plumbing: the Typer app, messages, options shared by commands, safe output.

Thin by design: commands parse options (units in their names and help), call the
public API and write files; results format themselves (``summary()``,
``display_row()``, ``to_dataframe()``, ``to_json()``).  Errors in the data or the fit
end in a one-line message and exit code 2 (input) or 3 (fit), never a traceback.
Nothing heavy is imported at module level, so ``ambfit --help`` is fast.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

# The command line draws into files: the headless backend, unless the user chose one.  (The library itself never
# switches backends, so figures show in notebooks.)
os.environ.setdefault("MPLBACKEND", "Agg")

app = typer.Typer(
    help="Identify active magnetic bearing parameters (effective gap, origin, force constant) from "
    "current-position perturbation data, and simulate a virtual test rig.",
    no_args_is_help=True, add_completion=False, rich_markup_mode=None,  # keep "[mA]" literal in help texts
)
# Wide enough for the identification tables when output is piped (CI logs, files).
console = Console(width=None if sys.stdout.isatty() else 140)
err = Console(stderr=True, width=None if sys.stderr.isatty() else 140)


def _version(value: bool):
    if value:
        from ambfit import __version__

        console.print(f"ambfit {__version__}")
        raise typer.Exit()


@app.callback()
def _main(version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                                help="Print the version and exit.")] = False):
    """Identify active magnetic bearing parameters from current-position perturbation data."""


BearingOption = Annotated[Path | None, typer.Option(
    "--bearing", help="Bearing description TOML (pole angle, turns, pole area, nominal gap, clearance, current "
                      "limit, ...; see ambfit/docs/data-format.md). Default: the seed paper's rig.")]


def fail(msg: str, code: int = 2):
    """A one-line error and exit ``code`` (2: input, 3: fit)."""
    err.print(f"[bold red]error:[/] {msg}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def warn(msg: str):
    err.print(f"[bold yellow]warning:[/] {msg}", highlight=False, soft_wrap=True)


def note(msg: str):
    console.print(msg, highlight=False, soft_wrap=True)


def bearing_of(path: Path | None):
    """The bearing description from ``--bearing`` (the paper's rig when not given); a bad file exits 2."""
    from ambfit.physics.bearing import PAPER_BEARING, Bearing, BearingError

    if path is None:
        return PAPER_BEARING
    try:
        bearing = Bearing.from_toml(path)
    except BearingError as exc:
        fail(str(exc))
    if bearing.extra_keys:
        warn(f"{path}: keys not used by ambfit: {', '.join(bearing.extra_keys)}")
    return bearing


AcceptOption = Annotated[bool, typer.Option(
    "--accept-implausible", help="Go on when the bearing description rules the data or the result out (k a "
                                 "million times off, a negative k, a gap at 40 % of the drawn one, currents beyond "
                                 "the coil limit) and exit 0 instead of 3.")]


def judge(flags, accept: bool, what: str = "the result is"):
    """Print implausibility flags (:mod:`ambfit.estimation.plausibility`); exit 3 unless ``accept``."""
    for f in flags:
        if accept:
            warn(str(f))
        else:
            err.print(f"[bold red]implausible:[/] {f}", highlight=False, soft_wrap=True)
    if flags and not accept:
        fail(f"{what} implausible for this bearing (see above); check units and signs, or give the right "
             "--bearing; --accept-implausible goes on anyway", 3)


def read_data(path: Path, bearing, accept: bool = False, max_position_um: float | None = None):
    """Read and check a data file (exit 2 naming file, row, column and value) and judge it against the bearing
    (exit 3 unless ``accept``)."""
    from ambfit.data import DataError, read_csv
    from ambfit.estimation import plausibility

    try:
        ds = read_csv(path, max_position_um=max_position_um or bearing.nominal_gap * 1e6)
    except DataError as exc:
        fail(str(exc))
    judge(plausibility.check_data(ds.frame, bearing, str(path)), accept, f"{Path(path).name}: the data are")
    return ds


def check_output(*paths: Path | None, folder: bool = False):
    """Fail before any work when an output cannot be written: missing or read-only folder, a directory
    where a file should go."""
    for p in paths:
        if p is None:
            continue
        p = Path(p)
        if folder:
            parent = p if p.exists() else p.parent
            if p.exists() and not p.is_dir():
                fail(f"{p}: exists and is not a folder")
        else:
            if p.is_dir():
                fail(f"{p}: is a directory; give a file name")
            parent = p.parent
        parent = parent if str(parent) else Path(".")
        if not parent.exists() and not folder:
            fail(f"{p}: the folder {parent} does not exist")
        probe = parent
        while not probe.exists():
            probe = probe.parent
        if not os.access(probe, os.W_OK):
            fail(f"{p}: the folder {probe} is not writable")


def write_json(record: dict, path: Path):
    """Write ``record`` atomically (a temporary file in the same folder, then a rename)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent if str(path.parent) else ".", prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(record, f, indent=2)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)     # mkstemp makes 0600; an output file gets the usual permissions
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    console.print(f"wrote {path}")


def show_table(rows: list[dict], title: str, left: tuple[str, ...] = ()):
    """A list of ``{column: text}`` rows (as results give them) as a console table."""
    from rich.table import Table

    t = Table(title=title)
    columns = list(dict.fromkeys(c for r in rows for c in r))
    for c in columns:
        t.add_column(c, justify="left" if c in left else "right")
    for r in rows:
        t.add_row(*(str(r.get(c, "")) for c in columns))
    console.print(t)


def parse_effect(text: str, bearing=None):
    """``NAME`` or ``NAME:param=value,param=value`` (SI units) -> Effect; facts of the bearing (the iron path)
    default to ``bearing``'s."""
    from ambfit.physics.effects import effect_by_name

    name, _, rest = text.partition(":")
    params = {}
    for item in filter(None, rest.split(",")):
        key, sep, val = item.partition("=")
        if not sep:
            raise ValueError(f"effect option {text!r}: expected param=value, got {item!r}")
        params[key.strip()] = float(val)
    return effect_by_name(name.strip(), bearing=bearing, **params)


def pair(text: str | None, scale: float):
    """``'v,w'`` or one value for both axes, times ``scale``."""
    if text is None:
        return None
    parts = [float(p) * scale for p in text.split(",")]
    if len(parts) == 1:
        parts = parts * 2
    if len(parts) != 2:
        raise ValueError(f"expected one value or 'v,w', got {text!r}")
    return tuple(parts)
