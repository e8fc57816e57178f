"""From section contexts to text: the Jinja2 environment, figures as embedded PNG, tables as HTML or Markdown.

Templates live in ``templates/``: ``page.html.j2`` is the layout and style sheet,
``data.html.j2`` and ``paper.html.j2`` the two reports, ``*_sections.html.j2`` one
macro per section, ``paper_readme.md.j2`` the Markdown summary.  HTML templates
(``*.html.j2``) are autoescaped; every number reaches them as a value and is
formatted there (``{{ x | fmt(".2f") }}``).

Example
-------
>>> str(section("data_sections.html.j2", "skipped", {"reason": "--no-posterior"}))
'<p>Skipped (--no-posterior).</p>'
"""

from __future__ import annotations

import base64
import html
import io
import re
import time

import jinja2
import numpy as np
import pandas as pd
from markupsafe import Markup


def fmt(value, spec: str = ".2f") -> str:
    """``format(value, spec)``; an empty string for a missing or non-finite number."""
    if value is None or (isinstance(value, (float, np.floating)) and not np.isfinite(value)):
        return ""
    return format(value, spec)


def and_join(items, last: str = "and") -> str:
    """``["1", "3", "4"]`` as ``"1, 3 and 4"``."""
    items = [str(i) for i in items]
    if len(items) < 2:
        return "".join(items)
    return f"{', '.join(items[:-1])} {last} {items[-1]}"


def ordinal(value) -> str:
    """``95`` as ``"95th"``, ``33.3`` as ``"33rd"`` (rounded); a non-integer setting such as ``2.5`` as ``"2.5th"``."""
    value = float(value)
    if value != round(value) and abs(value) < 10:
        return f"{value:g}th"
    n = int(round(value))
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


ENV = jinja2.Environment(
    loader=jinja2.PackageLoader("ambfit.faces.report"),
    # HTML is escaped; the Markdown summary is plain text
    autoescape=jinja2.select_autoescape(enabled_extensions=("html.j2",), default_for_string=True, default=False),
    undefined=jinja2.StrictUndefined,          # a missing value fails the report instead of leaving a blank
    trim_blocks=True, lstrip_blocks=True,
)
ENV.filters.update(fmt=fmt, and_join=and_join, ordinal=ordinal)


def render(template: str, **context) -> str:
    """One whole template rendered with ``context``."""
    return ENV.get_template(template).render(**context)


def section(template: str, name: str, context: dict) -> Markup:
    """The macro ``name`` of ``template`` applied to one section's context (the unit the tests render)."""
    return getattr(ENV.get_template(template).module, name)(context)


def png_bytes(obj, dpi: int = 110) -> bytes:
    """A matplotlib Figure/Axes or ArviZ plot collection rendered to PNG (by :func:`ambfit.faces.plots.save`);
    closes it."""
    from ambfit.faces.plots import save

    buf = io.BytesIO()
    save(obj, buf, dpi=dpi, close=True)
    return buf.getvalue()


def img(data: bytes) -> Markup:
    """PNG bytes as an embedded ``<img>`` (base64): the page needs no other file."""
    return Markup('<img alt="figure" src="data:image/png;base64,{}">').format(base64.b64encode(data).decode())


def figure(obj, dpi: int = 110) -> Markup:
    """A figure as an embedded ``<img>``; closes it."""
    return img(png_bytes(obj, dpi))


def _cell(v, digits: int) -> str:
    if isinstance(v, (float, np.floating)):
        if not np.isfinite(v):
            return ""
        return f"{v:.{digits}f}" if 1e-3 <= abs(v) < 1e5 or v == 0 else f"{v:.4g}"
    return str(v)


def _unsigned_zero(text: str) -> str:
    """``-0.000`` (a tiny negative rounded away) as ``0.000``."""
    return text[1:] if re.fullmatch(r"-0(\.0*)?", text) else text


def table(df: pd.DataFrame, digits: int = 2) -> Markup:
    """A DataFrame as an HTML table, one number format per column: ``digits`` decimals when the column's
    numbers are of ordinary size (so a shrink of 1e-9 reads 0.000 beside 0.975), 4 significant digits when
    they are all tiny or huge (force constants); NaN as blank; ``-0.000`` as ``0.000``; cells escaped.  Estimates
    with errors go in as text (:func:`ambfit.estimation.units.pm`), not as two number columns."""
    def formatter(column):
        values = pd.to_numeric(df[column], errors="coerce").abs()
        ordinary = bool(((values >= 1e-3) & (values < 1e5)).any())
        return lambda v: _unsigned_zero(f"{v:.{digits}f}" if ordinary and isinstance(v, (float, np.floating))
                                        and np.isfinite(v) and abs(v) < 1e5 else _cell(v, digits))

    return Markup(df.to_html(index=False, border=0, formatters={c: formatter(c) for c in df.columns},
                             escape=True, na_rep=""))


def markdown(df: pd.DataFrame, digits: int = 2) -> str:
    """A DataFrame as a Markdown table (floats to ``digits`` decimals, NaN as blank)."""
    lines = ["| " + " | ".join(map(str, df.columns)) + " |", "|" + "---|" * len(df.columns)]
    lines += ["| " + " | ".join("" if isinstance(v, (float, np.floating)) and not np.isfinite(v) else
                                (f"{v:.{digits}f}" if isinstance(v, (float, np.floating)) else str(v))
                                for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join(lines)


def plain(markup: str) -> str:
    """HTML prose as plain text (tags dropped, entities decoded) for the Markdown summary."""
    return re.sub(r"\s+", " ", html.unescape(re.sub(r"<[^>]+>", "", str(markup)))).strip()


def footer(command: str, seconds: float) -> dict:
    """The page footer's context: version, command, run time and date."""
    from ambfit import __version__

    return {"version": __version__, "command": command, "seconds": seconds,
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
