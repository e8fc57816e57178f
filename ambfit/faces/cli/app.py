"""The ``ambfit`` command line's plumbing: the Typer app, messages, options shared by commands, safe output.

Thin by design: commands parse options (units in their names and help), call the
public API and write files; results format themselves (``summary()``,
``display_row()``, ``to_dataframe()``, ``to_json()``).  Errors in the data or the fit
end in a one-line message and exit code 2 (input) or 3 (fit), never a traceback.
Nothing heavy is imported at module level, so ``ambfit --help`` is fast.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console, ConsoleDimensions
from rich.markup import escape

from ambfit._output import OutputError, unwritable
from ambfit._output import write_json as _write_json

# The command line draws into files: the headless backend, unless the user chose one.  (The library itself never
# switches backends, so figures show in notebooks.)
os.environ.setdefault("MPLBACKEND", "Agg")

PIPE_WIDTH = 100_000
"""Columns of the console when its stream is not a terminal (a pipe, a file, a test): wide enough that no table
cell (a long file name) is cut and no line is wrapped."""


class StreamError(Exception):
    """Standard output or error could not be written (a full device, a reader that closed the pipe)."""

    def __init__(self, exc: OSError):
        super().__init__(exc.strerror or str(exc))
        self.errno = exc.errno


class _Stream:
    """A console's stream whose failures to write are :class:`StreamError` s, told apart from the files a
    command reads and writes."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text: str):
        try:
            return self._stream.write(text)
        except OSError as exc:
            raise StreamError(exc) from exc

    def flush(self):
        try:
            return self._stream.flush()
        except OSError as exc:
            raise StreamError(exc) from exc

    def __getattr__(self, name):
        return getattr(self._stream, name)


class _Console(Console):
    """A rich Console as wide as the terminal, or unbounded when its stream is not one (judged at each print, so
    a stream redirected later is served too), whose stream's failures are :class:`StreamError` s."""

    @property
    def file(self):
        return _Stream(Console.file.fget(self))

    @file.setter
    def file(self, new_file) -> None:
        Console.file.fset(self, new_file)

    @property
    def size(self) -> ConsoleDimensions:
        size = super().size
        return size if self.is_terminal else ConsoleDimensions(PIPE_WIDTH, size.height)

    @size.setter
    def size(self, new_size) -> None:
        Console.size.fset(self, new_size)


INTERRUPTED = "interrupted; no output was written half-way (outputs are written atomically)"


class _App(typer.Typer):
    """The Typer app whose commands end an output that cannot be written (a full disk, a file vanished after the
    checks) in one line and exit 2, and Ctrl-C in one line and exit 130, whichever command it is."""

    def command(self, *args, **kwargs):
        register = super().command(*args, **kwargs)

        def wrap(fn):
            @functools.wraps(fn)
            def run(*a, **kw):
                try:
                    return fn(*a, **kw)
                except OutputError as exc:
                    fail(str(exc))
                except KeyboardInterrupt:       # (Typer would end it in silence)
                    fail(INTERRUPTED, 130)

            register(run)
            return fn

        return wrap


app = _App(
    help="Identify active magnetic bearing parameters (effective gap, origin, force constant) from "
    "current-position perturbation data, and simulate a virtual test rig.",
    no_args_is_help=True, add_completion=False, rich_markup_mode=None,  # keep "[mA]" literal in help texts
)
console = _Console()
err = _Console(stderr=True)


PLAIN = {"µ": "u", "μ": "u", "σ": "sigma", "χ": "chi", "Δ": "d", "α": "alpha", "β": "beta", "θ": "theta",
         "Ω": "Ohm", "±": "+/-", "≤": "<=", "≥": ">=", "≈": "~", "×": "x", "·": "*", "→": "->", "←": "<-",
         "—": "--", "–": "-", "…": "...", "°": " deg", "²": "^2", "³": "^3", "√": "sqrt", "∞": "inf", "‖": "||",
         "‘": "'", "’": "'", "“": '"', "”": '"', "≠": "!="}
"""How the command line writes what a terminal or pipe without those characters cannot show (an ASCII or
Latin-1 stream: ``LANG=C`` on an old system, ``PYTHONIOENCODING=ascii``): µm as "um", χ² as "chi^2"."""


def plain_text(text: str, encoding: str) -> str:
    """``text`` with every character ``encoding`` cannot write spelled as :data:`PLAIN` says, else by its
    compatibility decomposition without accents, else "?"."""
    import unicodedata

    try:
        text.encode(encoding)
        return text
    except (UnicodeEncodeError, LookupError):
        pass
    out = []
    for ch in text:
        bare = "".join(c for c in unicodedata.normalize("NFKD", ch) if not unicodedata.combining(c))
        for spelling in (ch, PLAIN.get(ch), bare or None, "?"):
            try:
                if spelling is not None and spelling.encode(encoding):
                    break
            except (UnicodeEncodeError, LookupError):
                continue
        out.append(spelling)
    return "".join(out)


def plain(error: UnicodeEncodeError) -> tuple[str, int]:
    """The ``ambfit.plain`` codec error handler: :func:`plain_text` of what the stream's encoding lacks."""
    return plain_text(error.object[error.start:error.end], error.encoding), error.end



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
    err.print(f"[bold red]error:[/] {escape(msg)}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def warn(msg: str):
    err.print(f"[bold yellow]warning:[/] {escape(msg)}", highlight=False, soft_wrap=True)


def note(msg: str):
    console.print(msg, markup=False, highlight=False, soft_wrap=True)


def bearing_of(path: Path | None):
    """The bearing description from ``--bearing`` (the paper's rig when not given); a bad file exits 2."""
    from ambfit.physics.bearing import PAPER_BEARING, Bearing, BearingError

    if path is None:
        return PAPER_BEARING
    try:
        bearing = Bearing.from_toml(path)
    except BearingError as exc:
        fail(f"--bearing: {exc}")
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
            err.print(f"[bold red]implausible:[/] {escape(str(f))}", highlight=False, soft_wrap=True)
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
    for line in ds.notes:
        note(line)
    judge(plausibility.check_data(ds.frame, bearing, str(path)), accept, f"{Path(path).name}: the data are")
    return ds


def check_output(*paths: Path | None, folder: bool = False, parents: bool = False, inputs=()):
    """Fail before any work when an output cannot be written (:func:`ambfit._output.unwritable`: a missing or
    read-only folder, a file where a folder should be, a directory where a file should go), when two outputs are
    one file, or when an output is one of the ``inputs`` (it would overwrite the data).  ``folder``: the paths are
    folders, created when missing; ``parents``: files in such a folder."""
    from ambfit._output import destination

    read = {destination(p): Path(p) for p in inputs if p is not None}
    written = {}
    for p in paths:
        if p is None:
            continue
        why = unwritable(p, folder=folder, parents=parents)
        if why:
            fail(why)
        dest = destination(p)
        if dest in read:
            fail(f"{p}: is the input {read[dest]}; writing there would overwrite it")
        if dest in written and not (dest.exists() and not dest.is_file()):     # (/dev/null twice is fine)
            fail(f"{p}: given for two outputs ({written[dest]}); give each output its own file")
        written[dest] = Path(p)


def write_json(record: dict, path: Path):
    """Write ``record`` as JSON (:mod:`ambfit._output`: atomically, through links, into devices)."""
    _write_json(path, record)
    console.print(f"wrote {path}", markup=False, highlight=False)


def show_table(rows: list[dict], title: str, left: tuple[str, ...] = ()):
    """A list of ``{column: text}`` rows (as results give them) as a console table."""
    from rich.table import Table
    from rich.text import Text

    def cell(text) -> Text:     # spelled so that the stream can write it, before widths are measured; literal
        return Text(plain_text(str(text), console.encoding))

    t = Table(title=cell(title))
    columns = list(dict.fromkeys(c for r in rows for c in r))
    for c in columns:     # a cell too wide for a terminal folds onto the next line: a file name is never cut
        t.add_column(cell(c), justify="left" if c in left else "right", overflow="fold")
    for r in rows:
        t.add_row(*(cell(r.get(c, "")) for c in columns))
    console.print(t)


def parse_effect(text: str, bearing=None):
    """``NAME`` or ``NAME:param=value,param=value`` (SI units) -> Effect; facts of the bearing (the iron path)
    default to ``bearing``'s."""
    import math

    from ambfit.physics.effects import effect_by_name

    name, _, rest = text.partition(":")
    params = {}
    for item in filter(None, rest.split(",")):
        key, sep, val = item.partition("=")
        if not sep:
            raise ValueError(f"effect option {text!r}: expected param=value, got {item!r}")
        try:
            params[key.strip()] = float(val)
        except ValueError:
            raise ValueError(f"{key.strip()}={val!r} is not a number") from None
        if not math.isfinite(params[key.strip()]):
            raise ValueError(f"{key.strip()}={val} is not a finite number")
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
