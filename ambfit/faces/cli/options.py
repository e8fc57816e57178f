"""Checks of option values, run while the command line is parsed (before any work): each bad value ends in one
line naming the option and the value, and exit 2.

Each factory returns a Typer ``callback``: ``typer.Option(callback=number(low=0, low_open=True), ...)``.  Numbers
must be finite (``nan`` and ``inf`` parse as floats, and would pass a plain range check); lists of numbers are
the comma-separated text options (``--biases-a 1.4,1.6``); a span is ``'low,high'`` with ``low < high``.

Example
-------
>>> number(low=1)(_Param("--steps"), 8)
8
>>> span_problem("1000,600")
"must be 'low,high' with low < high"
"""

from __future__ import annotations

import dataclasses
import math

import typer


@dataclasses.dataclass(frozen=True)
class _Param:
    """Stands in for click's parameter in examples and tests: what the callbacks read of it."""

    name: str

    @property
    def opts(self) -> list[str]:
        return [self.name]


def _name(param) -> str:
    """The option as the user writes it: its long name."""
    return max(param.opts, key=len)


def _fail(param, value, problem: str):
    from ambfit.faces.cli.app import fail

    shown = value if isinstance(value, str) else f"{value:g}" if isinstance(value, float) else value
    fail(f"{_name(param)} {shown}: {problem}")


def bound_problem(x: float, low=None, high=None, *, low_open: bool = False) -> str | None:
    """Why ``x`` is not a finite number in the range, or ``None``."""
    if not math.isfinite(x):
        return "must be a finite number"
    if low is not None and (x <= low if low_open else x < low):
        return f"must be {'>' if low_open else 'at least'} {low:g}"
    if high is not None and x > high:
        return f"must be at most {high:g}"
    return None


def number(low=None, high=None, *, low_open: bool = False):
    """A callback: the value (int or float; ``None`` passes: not given) is finite and within ``[low, high]``
    (``(low, high]`` with ``low_open``)."""
    def callback(param: typer.CallbackParam, value):
        if value is not None:
            problem = bound_problem(value, low, high, low_open=low_open)
            if problem:
                _fail(param, value, problem)
        return value

    return callback


def debias_choice(most: int):
    """A callback for ``--debias``: 'second-order', 'none' or a number of bootstrap data sets within ``[0, most]``
    (0 is 'none'); returns the name or the number, as :func:`ambfit.fit` takes it."""
    def callback(param: typer.CallbackParam, value: str):
        text = value.strip().lower()
        if text in ("second-order", "none"):
            return text
        try:
            n = int(text)
        except ValueError:
            _fail(param, value, "must be 'second-order', 'none' or a number of synthetic data sets")
        if not 0 <= n <= most:
            _fail(param, value, f"a number of synthetic data sets must be within [0, {most}]")
        return n or "none"

    return callback


def parse_numbers(text: str) -> list[float]:
    """``'1.4,1.6'`` as numbers; raises ValueError naming the part that is not one."""
    parts = [p.strip() for p in text.split(",")]
    out = []
    for p in parts:
        try:
            out.append(float(p))
        except ValueError:
            raise ValueError(f"{p!r} is not a number" if p else "expected comma-separated numbers") from None
    return out


def numbers_problem(text: str, low=None, high=None, *, low_open: bool = False, count: tuple = ()) -> str | None:
    """Why ``text`` is not a comma-separated list of finite numbers in range (of a length in ``count``)."""
    try:
        values = parse_numbers(text)
    except ValueError as exc:
        return str(exc)
    if count and len(values) not in count:
        return f"expected {' or '.join(map(str, count))} comma-separated number(s), got {len(values)}"
    for x in values:
        problem = bound_problem(x, low, high, low_open=low_open)
        if problem:
            return f"each value {problem}, got {x:g}"
    return None


def numbers(low=None, high=None, *, low_open: bool = False, count: tuple = (), also: tuple = ()):
    """A callback: the text is comma-separated finite numbers within the range (``count``: allowed lengths;
    ``also``: words allowed instead, e.g. ``'origin'``)."""
    def callback(param: typer.CallbackParam, value):
        if value is not None and value.strip().lower() not in also:
            problem = numbers_problem(value, low, high, low_open=low_open, count=count)
            if problem:
                _fail(param, value, problem)
        return value

    return callback


def span_problem(text: str, low=None, *, low_open: bool = False) -> str | None:
    """Why ``text`` is not ``'low,high'`` of finite numbers with ``low < high`` (and ``low`` above the bound)."""
    problem = numbers_problem(text, low, low_open=low_open, count=(2,))
    if problem:
        return problem
    a, b = parse_numbers(text)
    return None if a < b else "must be 'low,high' with low < high"


def span(low=None, *, low_open: bool = False):
    """A callback: the text is a range ``'low,high'`` (see :func:`span_problem`)."""
    def callback(param: typer.CallbackParam, value):
        if value is not None:
            problem = span_problem(value, low, low_open=low_open)
            if problem:
                _fail(param, value, problem)
        return value

    return callback


def text(param: typer.CallbackParam, value):
    """A callback: the text is not blank."""
    if value is not None and not value.strip():
        _fail(param, repr(value), "must not be empty")
    return value
