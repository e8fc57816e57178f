"""Reading, checking and writing perturbation data in the contract's CSV format.

``DATA-CONTRACT.md`` section 1 defines the columns.  :func:`read_csv` checks every
row where the data enter and raises :class:`DataError` naming the file, row,
column and offending value; it keeps extra columns untouched so that
:func:`write_csv` writes back everything it read.  :func:`ambfit.rows.readings`
turns a checked table into SI arrays for the model.

Rows are numbered from 1 for the first data row; the CSV line is one more
(the header is line 1).
"""

from __future__ import annotations

import csv
import dataclasses
import difflib
import os
import re
from pathlib import Path

import numpy as np
import pandas as pd

from ambfit.checks import CURRENTS, MAX_CURRENT_A, STD_COLUMNS, ZERO_CURRENT_NOISE_A, ranges  # noqa: F401
from ambfit.physics.bearing import AXES, PAPER_BEARING

REQUIRED = ("axis", "bias_A", "i_top_A", "i_bottom_A", "v_um", "w_um")
"""Columns every data file must have."""

NUMERIC_OPTIONAL = (
    "load_N", "v_set_um", "w_set_um", "time_s", "temperature_C",
    "i_top_std_A", "i_bottom_std_A", "v_std_um", "w_std_um",
)
"""Optional numeric columns; an empty cell means 'not known'."""

LABELS = ("load_id", "experiment")

CONTRACT_COLUMNS = (*REQUIRED, *NUMERIC_OPTIONAL, *LABELS, "iteration")
"""Every column the contract names."""

DEFAULT_MAX_POSITION_UM = PAPER_BEARING.nominal_gap * 1e6
"""Positions at least this large [µm] are rejected as 'as large as the gap' (the paper's nominal gap; the
command line passes its ``--bearing``'s)."""


class DataError(ValueError):
    """Bad input data: names the file, the row, the column and the value.

    Attributes
    ----------
    file, row, column, value :
        Where the problem is (``row`` counts data rows from 1; None when the
        problem is not tied to one row).
    """

    def __init__(self, reason: str, *, file=None, row: int | None = None, column: str | None = None, value=None):
        value = value.item() if isinstance(value, np.generic) else value    # numbers print as numbers
        self.file, self.row, self.column, self.value, self.reason = file, row, column, value, reason
        where = [str(file) if file is not None else "<data>"]
        if row is not None:
            where.append(f"row {row} (line {row + 1})")
        if column is not None:
            where.append(f"column {column!r}")
        if value is not None:
            where.append(f"value {value!r}")
        super().__init__(", ".join(where) + ": " + reason)


@dataclasses.dataclass(frozen=True)
class Dataset:
    """A checked data table and where it came from.

    ``frame`` holds the contract's numeric columns as floats (NaN where a cell was
    empty) and every other column exactly as read (strings).
    """

    frame: pd.DataFrame
    source: str = "<memory>"
    notes: tuple = ()
    """What reading the file took in its stride, in words (a semicolon-separated export, blank rows skipped)."""

    def __len__(self) -> int:
        return len(self.frame)


class _Problems:
    """Where the checks report: the first problem raises (``lazy=False``), or every problem is collected."""

    def __init__(self, source: str, lazy: bool, limit: int = 20):
        self.source, self.lazy, self.limit, self.items = source, lazy, limit, []

    def add(self, reason, row=None, column=None, value=None):
        err = DataError(reason, file=self.source, row=None if row is None else int(row) + 1, column=column, value=value)
        if not self.lazy:
            raise err
        self.items.append(err)

    def rows(self, mask, reason, column, values):
        """Report the rows where ``mask`` holds (all of them up to ``limit`` when lazy, else the first)."""
        idx = np.nonzero(np.asarray(mask))[0]
        # rows as the file counts them: a frame whose blank rows were skipped keeps the file's positions as labels
        labels = values.index if pd.api.types.is_integer_dtype(values.index) else pd.RangeIndex(len(values))
        for r in idx[: self.limit]:
            self.add(reason, int(labels[r]), column, values.iloc[r])
        if len(idx) > self.limit:
            self.add(f"{len(idx) - self.limit} more rows with the same problem", None, column)


def read_csv(path: str | os.PathLike, *, max_position_um: float = DEFAULT_MAX_POSITION_UM) -> Dataset:
    """Read and check a contract CSV file.

    Parameters
    ----------
    path : path-like
    max_position_um : float
        Positions of at least this magnitude [µm] are rejected (likely a unit error).

    Raises
    ------
    DataError
        On the first of the contract's error cases, naming file, row, column and value
        (:func:`inspect` lists them all).
    """
    raw = _read_raw(path)
    ds = check(raw, source=str(path), max_position_um=max_position_um)
    return dataclasses.replace(ds, notes=tuple(raw.attrs.get("notes", ())))


def inspect(path: str | os.PathLike, *, max_position_um: float = DEFAULT_MAX_POSITION_UM) -> list[DataError]:
    """Every problem of a contract CSV file at once (empty when it is valid): what ``ambfit check`` lists."""
    try:
        raw = _read_raw(path)
    except DataError as exc:
        return [exc]
    problems = _Problems(str(path), lazy=True)
    _check(raw, problems, max_position_um)
    return sorted(problems.items, key=lambda e: -1 if e.row is None else e.row)   # file problems, then by row


def _read_raw(path) -> pd.DataFrame:
    """The file's cells as text, the contract's CSV or what a spreadsheet exports instead: a semicolon- or
    tab-separated file (a German or French Excel's "CSV") is read as such, its decimal commas as points; rows with
    every cell empty are skipped.  What was taken in stride is listed in ``frame.attrs["notes"]``."""
    source = str(path)
    p = Path(path)
    if p.is_dir():
        raise DataError("is a directory, not a data file", file=source)
    if not p.is_file():
        raise DataError("no such file", file=source)
    try:
        header, sep = _scan(p, source)
    except UnicodeDecodeError as exc:
        raise DataError(f"not a UTF-8 text file ({exc.reason})", file=source) from None
    dupes = sorted({c for c in header if header.count(c) > 1})
    if dupes:
        raise DataError(f"duplicate column name(s) {dupes} in the header", file=source, row=None)
    if len(header) == 1 and "|" in header[0]:
        raise DataError("the header is one column that contains '|': the file looks pipe-separated; ambfit reads "
                        "comma-separated files (or semicolon- or tab-separated ones)", file=source)
    try:
        # index_col=False: data rows with a trailing separator must not shift every column by one
        raw = pd.read_csv(p, sep=sep, dtype=str, keep_default_na=False, skipinitialspace=True, index_col=False)
    except (pd.errors.ParserError, ValueError) as exc:
        raise DataError(f"not a valid CSV table: {exc}", file=source) from None
    notes = []
    if sep != ",":
        decimal = raw.apply(lambda col: col.str.strip().str.fullmatch(_DECIMAL_COMMA))
        comma = bool(decimal.to_numpy().any())
        if comma:
            raw = raw.mask(decimal, raw.apply(lambda col: col.str.replace(",", ".", regex=False)))
        notes.append(f"{source}: read as {_SEPARATORS[sep]}-separated" + (" with decimal commas" if comma else "")
                     + " (a spreadsheet's export; the contract's CSV is comma-separated with decimal points)")
    blank = raw.apply(lambda col: col.str.strip().eq("")).all(axis=1).to_numpy() if len(raw.columns) else None
    if blank is not None and blank.any():
        rows = np.nonzero(blank)[0] + 1
        shown = ", ".join(map(str, rows[:8])) + (" ..." if len(rows) > 8 else "")
        notes.append(f"{source}: {len(rows)} blank row(s) skipped (data rows {shown})")
        raw = raw[~blank]                        # the labels keep the file's row positions for messages
    raw.attrs["notes"] = notes
    return raw


_DECIMAL_COMMA = r"[-+]?\d+,\d*([eE][-+]?\d+)?"
"""A number written with a decimal comma (``1,4``, ``-0,05``, ``3,2e-3``)."""


_SEPARATORS = {";": "semicolon", "\t": "tab", "|": "pipe"}

MAX_LINE_CHARS = 1 << 16
"""Longest line accepted [characters]: a contract row is a few hundred; longer lines are refused before any
parsing, so a pathological file costs bounded time and memory."""


def _scan(p: Path, source: str) -> tuple[list[str], str]:
    """The header's column names and the field separator (``,`` unless the header holds none and holds semicolons
    or tabs), after checking every line's length and field count (bounded memory)."""
    with open(p, newline="", encoding="utf-8") as f:
        first = f.readline(MAX_LINE_CHARS + 1)
        if not first.strip():
            raise DataError("the file is empty (no header line)", file=source)
        if len(first) > MAX_LINE_CHARS:
            raise DataError(f"the header line is longer than {MAX_LINE_CHARS} characters; not a contract CSV file",
                            file=source)
        sep = "," if "," in first else next((s for s in (";", "\t") if s in first), ",")
        header = next(csv.reader([first], delimiter=sep))
        width = len(header) + 1            # one trailing comma is tolerated
        row = 0
        while line := f.readline(MAX_LINE_CHARS + 1):
            row += 1
            if len(line) > MAX_LINE_CHARS and not line.endswith("\n"):
                raise DataError(f"line longer than {MAX_LINE_CHARS} characters (a contract row has "
                                f"{len(header)} fields); the file is damaged or not a data file", file=source,
                                row=row)
            if not line.strip() or '"' in line:     # blank lines are skipped; quoted fields are left to the parser
                continue
            fields = line.count(sep) + 1
            if fields > width:
                raise DataError(f"{fields} fields where the header has {len(header)}", file=source, row=row)
            if fields < len(header):
                cut = "" if line.endswith("\n") else " and no line end: the file was cut short"
                raise DataError(f"{fields} fields where the header has {len(header)}{cut} (a missing value "
                                "still needs its comma)", file=source, row=row)
    return [h.strip() for h in header], sep


def check(raw: pd.DataFrame, *, source: str = "<memory>", max_position_um: float = DEFAULT_MAX_POSITION_UM) -> Dataset:
    """Check a table (cells as strings or numbers) against the contract; see :func:`read_csv`."""
    return Dataset(frame=_check(raw, _Problems(source, lazy=False), max_position_um), source=source)


def _bare(name: str) -> str:
    """A column name without case, spaces, brackets and underscores (``"I_top [A]"`` -> ``"itopa"``)."""
    return re.sub(r"[^0-9a-z]", "", str(name).lower())


def _near_names(missing: list, others: list) -> str:
    """``"; did you mean ..."``: the file's columns that look like the missing contract columns (``i_top [A]`` for
    ``i_top_A``, ``bias_mA`` for ``bias_A``, with the unit it must be in), or ""."""
    pairs = []
    bare = {_bare(c): c for c in others}
    for want in missing:
        near = difflib.get_close_matches(_bare(want), list(bare), n=1, cutoff=0.7)
        if near:
            pairs.append(f"{bare[near[0]]!r} for {want!r}")
    if not pairs:
        return ""
    return ("; did you mean " + ", ".join(pairs) + " (rename the column; the contract's names carry their unit, "
            "so convert the values if the unit differs)")


def _check(raw: pd.DataFrame, problems: _Problems, max_position_um: float) -> pd.DataFrame:
    """The contract's checks on ``raw``; returns the typed table (numeric columns as floats)."""
    missing = [c for c in REQUIRED if c not in raw.columns]
    if missing:
        problems.add(f"missing required column(s) {missing}; the file has {list(raw.columns)}"
                     + _near_names(missing, [c for c in raw.columns if c not in CONTRACT_COLUMNS]))
    if len(raw) == 0:
        problems.add("the file has a header but no data rows")
        return raw
    df = raw.copy()
    if "axis" in df:
        df["axis"] = df["axis"].astype(str).str.strip()
        problems.rows(~df["axis"].isin(AXES), "unknown axis; valid axes are 'v' and 'w'", "axis", df["axis"])
    _numeric(df, problems)
    ranges(df, problems, max_position_um)
    _consistency(df, problems)
    return df


def _numeric(df: pd.DataFrame, problems: _Problems):
    for col in [c for c in REQUIRED[1:] + NUMERIC_OPTIONAL if c in df.columns]:
        text = df[col].astype(str).str.strip()
        # (a frame's missing value stays missing as text; a file's empty cell or "nan" is text)
        empty = df[col].isna() | text.eq("") | text.str.lower().isin(("nan", "na", "none"))
        if col in REQUIRED:
            problems.rows(empty, "empty cell in a required column", col, df[col])
        num = pd.to_numeric(text.where(~empty, None), errors="coerce").astype(float)
        problems.rows((~empty) & ~np.isfinite(num), "not a finite number", col, df[col])
        df[col] = num
    if "iteration" in df.columns:
        text = df["iteration"].astype(str).str.strip()
        given = df["iteration"].notna() & (text != "")
        num = pd.to_numeric(text.where(given, None), errors="coerce")
        problems.rows(given & ~(np.isfinite(num) & (num == np.round(num))), "iteration must be an integer",
                      "iteration", df["iteration"])


def _consistency(df: pd.DataFrame, problems: _Problems):
    if "time_s" in df.columns and pd.api.types.is_float_dtype(df["time_s"]):
        exp = df["experiment"] if "experiment" in df.columns else pd.Series("", index=df.index)
        for _, idx in df.groupby(exp, sort=False).groups.items():
            t = df.loc[idx, "time_s"].to_numpy()
            ok = ~np.isnan(t)
            dec = np.nonzero(np.diff(t[ok]) < 0)[0]
            if dec.size:
                r = int(np.asarray(idx)[ok][dec[0] + 1])
                problems.add("time goes backwards within an experiment (time_s must be monotone)", r, "time_s",
                             df["time_s"].iloc[r])
    if "load_N" in df.columns and "axis" in df.columns and pd.api.types.is_float_dtype(df["load_N"]):
        for key, idx in df.groupby(load_groups(df), sort=False).groups.items():
            loads = df.loc[idx, "load_N"].to_numpy()
            known = loads[~np.isnan(loads)]
            if known.size and not np.allclose(known, known[0], rtol=1e-9, atol=1e-12):
                pos = np.asarray(idx)[~np.isnan(loads)]
                r = int(pos[np.argmax(~np.isclose(known, known[0], rtol=1e-9, atol=1e-12))])
                problems.add(f"known load differs from {float(known[0])!r} N given on row {int(pos[0]) + 1} for the same "
                             f"load group {key!r} (load_id, axis); rows sharing a load_id must share its load",
                             r, "load_N", df["load_N"].iloc[r])


NEAR = {"i_top_A": 1e-5, "i_bottom_A": 1e-5, "v_um": 1e-3, "w_um": 1e-3, "bias_A": 1e-5, "load_N": 1e-6}
"""How close a reading's numbers must be to another's, with the same labels, to be a copy [the column's unit]:
10 µA and 1 nm, a hundredth of the finest noise a rig reads (0.1 mA, 0.1 µm), so two real readings agree this
closely on all four channels with a chance below 1e-8; a copy exported again at another precision (or nudged to
pass as new) does."""


def duplicate_rows(df: pd.DataFrame) -> list[tuple[int, int]]:
    """Duplicate readings as ``(row, first row it repeats)``, rows counted from 1 as in messages: the same labels
    (axis, load, experiment, iteration, time) and every number within :data:`NEAR` of the first's.

    A duplicated reading counts twice in a fit and makes its error bars too small by up to sqrt(2).
    """
    labels = [c for c in ("axis", "load_id", "experiment", "iteration", "time_s") if c in df.columns]
    numbers = [c for c in NEAR if c in df.columns]
    values = df[numbers].apply(pd.to_numeric, errors="coerce").to_numpy(float)
    tol = np.array([NEAR[c] for c in numbers])
    if len(df) < 2 or not numbers:
        return []
    # labels compared as text; a missing one (None, NaN) is a value of its own, whatever the pandas version
    group = (joint_codes(*(df[c].astype(str).where(df[c].notna()).to_numpy() for c in labels), own_missing=True)
             if labels else np.zeros(len(df), int))
    first = values[:, 0]
    order = np.lexsort((first, group))       # by group, then by the first number (stable): copies are neighbours
    later, earlier = [], []
    for d in range(1, len(df)):
        # each reading against the one d places on in that order, while any pair is still close in the first
        # number (the order is ascending: further ones are further away; NaN is last and close to nothing)
        i, j = order[:-d], order[d:]
        near = (group[i] == group[j]) & (first[j] - first[i] <= tol[0])
        if not near.any():
            break
        i, j = i[near], j[near]
        same = ((np.abs(values[j] - values[i]) <= tol) | (np.isnan(values[j]) & np.isnan(values[i]))).all(axis=1)
        later.append(np.maximum(i, j)[same])
        earlier.append(np.minimum(i, j)[same])
    if not later or not sum(map(len, later)):
        return []
    # each repeat named once, against the earliest reading it repeats
    pairs = pd.Series(np.concatenate(earlier)).groupby(np.concatenate(later)).min()
    return [(int(r) + 1, int(f) + 1) for r, f in pairs.items()]


def file_rows(df: pd.DataFrame) -> np.ndarray:
    """The data row of each row of ``df`` as messages count them (from 1): its index label plus one when the
    frame keeps the file's integer index (a group, or a file with duplicates dropped), else its position."""
    if pd.api.types.is_integer_dtype(df.index):
        return np.asarray(df.index, dtype=int) + 1
    return np.arange(1, len(df) + 1)


def zero_based(df: pd.DataFrame) -> pd.DataFrame:
    """``df`` indexed 0..n-1: itself when it already is (no copy: a table fitted many times keeps its identity,
    see :func:`ambfit.estimation.problem.owned`), else ``reset_index(drop=True)``."""
    return df if df.index.equals(pd.RangeIndex(len(df))) else df.reset_index(drop=True)


def group_labels(column: pd.Series) -> pd.Series:
    """A label column for grouping rows: as text (so 1 and "1" are one label), except integer codes, which
    stand for themselves (a study's joined table numbers its data sets' experiments)."""
    return column if pd.api.types.is_integer_dtype(column) else column.astype(str)


def joint_codes(*keys, own_missing: bool = False) -> np.ndarray:
    """Rows numbered by several key columns at once (arrays or Series of one length), in order of first appearance:
    rows equal in every key share a number.  A missing key (NaN, None) puts its row in no group (-1), or with
    ``own_missing`` in a group of the missing value."""
    code = np.zeros(len(keys[0]), dtype=np.int64)
    for key in keys:
        part, _ = pd.factorize(key, use_na_sentinel=not own_missing)
        width = int(part.max(initial=0)) + 1
        if int(code.max(initial=0)) >= 2**62 // width:          # (dense again before the product could overflow)
            code[code >= 0] = pd.factorize(code[code >= 0])[0]
        code = np.where((code >= 0) & (part >= 0), code * width + part, -1)
    code[code >= 0] = pd.factorize(code[code >= 0])[0]
    return code


def load_groups(df: pd.DataFrame) -> pd.Series:
    """The static-load group of each row: ``load_id`` and axis, or experiment and axis when no ``load_id``."""
    if "load_id" in df.columns:
        base = df["load_id"].astype(str)
    elif "experiment" in df.columns:
        base = "experiment:" + df["experiment"].astype(str)
    else:
        base = pd.Series("all", index=df.index)
    return base + "|" + df["axis"].astype(str)


def write_csv(data: Dataset | pd.DataFrame, path: str | os.PathLike) -> None:
    """Write a table in the contract format (floats at full precision, NaN as empty); atomically, through links,
    into devices (:mod:`ambfit._output`)."""
    from ambfit._output import write_text

    frame = data.frame if isinstance(data, Dataset) else data
    write_text(path, frame.to_csv(index=False, na_rep="", float_format=None))
