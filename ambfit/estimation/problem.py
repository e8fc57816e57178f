"""A data set's arrays for the least-squares core (SI units, one entry per row).

:func:`build_problem` turns a contract table into a :class:`Problem`: the readings,
the noise level of every reading (std columns, declared levels, or marked for
estimation), the load of every row (known, or the index of its nuisance load group)
and which rows the fit uses.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import functools
import hashlib

import equinox as eqx
import jax
import numpy as np
import pandas as pd

from ambfit._arrays import Array, frozen, traced
from ambfit._recent import Recent
from ambfit.data import Dataset, joint_codes, load_groups
from ambfit.physics.model import Readings
from ambfit.rows import readings


class _unbound:
    """A method of an ``eqx.Module`` called like any other, but bound as a plain ``functools.partial``: Equinox binds
    a method as a module of its own (``eqx.BoundMethod``, a pytree, built with the module's checks) at every attribute
    access, and an outlier test or a diagnosis' folds derive problems by the thousand.  Such a method is not a pytree:
    pass the problem to a jitted function, not its bound method."""

    def __init__(self, fn):
        self.fn = fn
        functools.update_wrapper(self, fn)

    def __get__(self, obj, cls=None):
        return self.fn if obj is None else functools.partial(self.fn, obj)


class Problem(eqx.Module):
    """Arrays of one data set, ready for the jitted residual (SI units, one entry per row).

    ``k_free[a]`` is whether axis ``a`` has a known load (so ``k`` is identifiable);
    ``gidx`` indexes the nuisance load of rows without a known load (-1 otherwise);
    ``mask`` is 1 for rows the fit uses, 0 for held-out rows; ``s_held`` is each row's force noise std [N]
    held fixed instead of propagated through the model (0: propagated, the default; nested models compared by
    their χ² rise hold the full model's, see :meth:`with_noise`).
    """

    readings: Readings
    s_top: Array
    s_bottom: Array
    s_x: Array
    load: Array
    known: Array
    gidx: Array
    k_free: Array
    mask: Array
    s_held: Array

    ax = property(lambda self: self.readings.axis)
    x = property(lambda self: self.readings.x)
    i_top = property(lambda self: self.readings.i_top)
    i_bottom = property(lambda self: self.readings.i_bottom)
    bias = property(lambda self: self.readings.bias)

    @property
    def n_loads(self) -> int:
        return int(np.max(np.asarray(self.gidx), initial=-1)) + 1

    @_unbound
    def with_mask(self, mask) -> Problem:
        """The same problem with other row weights (``mask``: 0 leaves a row out; robust losses use sqrt(w))."""
        return self._with(mask=_leaf(mask))

    @_unbound
    def with_noise(self, s) -> Problem:
        """The same problem with each row's effective force noise std ``s`` [N] held (0 where it is propagated)."""
        return self._with(s_held=_leaf(s))

    @_unbound
    def _with(self, **fields) -> Problem:
        """The same problem with these fields replaced, made as JAX's unflattening makes a module: without the
        checks of its ``__init__`` (the fields' values are the problem's own kinds; it has no converters)."""
        new, own = object.__new__(Problem), object.__getattribute__(self, "__dict__")
        for name in _FIELDS:
            object.__setattr__(new, name, fields[name] if name in fields else own[name])
        return new

    @_unbound
    def with_readings(self, i_top, i_bottom, x) -> Problem:
        """The same problem with other current and position readings (bootstrap, design)."""
        return eqx.tree_at(lambda p: (p.readings.i_top, p.readings.i_bottom, p.readings.x), self, (i_top, i_bottom, x))


_FIELDS = tuple(f.name for f in dataclasses.fields(Problem))


def _leaf(values):
    """A float row field: traced values as they are, others as a read-only NumPy array of the problem's own (the
    solve converts at its call)."""
    return values if traced(values) else frozen(values, dtype=float)


@dataclasses.dataclass(frozen=True)
class Meta:
    """What :func:`build_problem` decided about a data set."""

    load_groups: list
    k_free: tuple
    axes_present: tuple
    noise_source: str
    n_rows: int

    @property
    def noise_estimated(self) -> bool:
        return "estimated" in self.noise_source


def _empty_cells(df: pd.DataFrame, columns: tuple, ax: np.ndarray | None = None) -> str:
    """Why std columns that are there are not used: ``(i_top_std_A has 1 empty cell of 80, row 6: ...)``, or ""
    when the columns are absent.  ``ax``: position columns count only on their own axis' rows."""
    there = [c for c in columns if c in df]
    if not there:
        return ""
    parts, first = [], None
    for c in there:
        empty = df[c].isna().to_numpy() & (True if ax is None else np.asarray(ax) == columns.index(c))
        if empty.any():
            parts.append(f"{c} has {int(empty.sum())} empty cell(s) of {len(df)}")
            first = first if first is not None else int(np.argmax(empty))
    missing = [c for c in columns if c not in df]
    parts += [f"no {c} column" for c in missing]
    return (f"({'; '.join(parts)}{'' if first is None else f', first on data row {first + 1}'}: std columns are used "
            "only when complete; fill them, or declare the noise)")


def _noise(df: pd.DataFrame, ax: np.ndarray, sigma_i, sigma_x):
    n = len(df)

    def column(name):
        return df[name].to_numpy(float) if name in df else np.full(n, np.nan)

    st, sb = column("i_top_std_A"), column("i_bottom_std_A")
    sx = np.where(ax == 0, column("v_std_um"), column("w_std_um")) * 1e-6
    sources = []
    if sigma_i is not None:
        st, sb = np.full(n, float(sigma_i)), np.full(n, float(sigma_i))
        sources.append(f"current {sigma_i * 1e3:g} mA declared")
    elif np.isnan(st).any() or np.isnan(sb).any():
        gaps = _empty_cells(df, ("i_top_std_A", "i_bottom_std_A"))
        st, sb = np.full(n, 1e-3), np.full(n, 1e-3)
        sources.append("current estimated from the residuals" + (f" {gaps}" if gaps else ""))
    else:
        sources.append("current from the std columns")
    if sigma_x is not None:
        sx = np.full(n, float(sigma_x))
        sources.append(f"position {sigma_x * 1e6:g} µm declared")
    elif np.isnan(sx).any():
        gaps = _empty_cells(df, ("v_std_um", "w_std_um"), ax)
        sx = np.zeros(n)
        sources.append("position noise taken as 0 " + (gaps or "(no std column)"))
    else:
        sources.append("position from the std columns")
    return st, sb, sx, "; ".join(sources)


_BUILT = Recent(8)
"""The last few tables' problems, by content: the diagnosis and the force check fit one table dozens of times
with different masks, and building its readings (pairing the axes by time) costs more than a warm fit."""


_OWNED: contextvars.ContextVar = contextvars.ContextVar("owned", default=None)


@contextlib.contextmanager
def owned(df: pd.DataFrame):
    """Within this block ``df`` is hashed once: for a table its caller made and changes nowhere (a diagnosis fits
    its own copy of the data a hundred times, and hashing 840 rows takes 1.5 ms)."""
    token = _OWNED.set((df, _digest(df)))
    try:
        yield df
    finally:
        _OWNED.reset(token)


_ONCE: contextvars.ContextVar = contextvars.ContextVar("fitted_once", default=False)


@contextlib.contextmanager
def fitted_once():
    """Within this block a table's problem is built without being hashed or kept: for tables made to be fitted
    once (an uncertainty budget's recorded copies), whose hashing is wasted and whose problems would push the
    problems of tables fitted again out of the cache."""
    token = _ONCE.set(True)
    try:
        yield
    finally:
        _ONCE.reset(token)


def _content_key(df: pd.DataFrame, sigma_i, sigma_x) -> tuple:
    held = _OWNED.get()
    digest = held[1] if held is not None and held[0] is df else _digest(df)
    declared = tuple(None if v is None else np.asarray(v, dtype=float).tobytes() for v in (sigma_i, sigma_x))
    return digest, declared


def _digest(df: pd.DataFrame) -> tuple:
    # numeric columns by their bytes, others by their text (pandas' row hashing took 3.6 ms a call on 840 rows,
    # a tenth of a warm fit)
    digest = hashlib.blake2b(digest_size=16)
    for _, col in [("index", df.index.to_series()), *df.items()]:
        v = col.to_numpy()
        digest.update(np.ascontiguousarray(v).tobytes() if v.dtype.kind in "biufcmM"
                      else "\x1f".join(map(repr, v)).encode())
        digest.update(b"\x1e")
    return tuple(map(str, df.columns)), tuple(map(str, df.dtypes)), digest.hexdigest()


def build_problem(data: Dataset | pd.DataFrame, *, sigma_i: float | None = None, sigma_x: float | None = None,
                  mask=None) -> tuple[Problem, Meta]:
    """Arrays for :func:`residuals` from a contract table.

    ``sigma_i`` [A] and ``sigma_x`` [m] override the std columns; with neither
    columns nor declared levels the noise is marked for estimation (unit current
    weight of 1 mA, no position noise, rescaled by the fit's reduced χ²).
    ``mask``: 1 for rows to fit, 0 for rows held out (default all 1).
    """
    df = data.frame if isinstance(data, Dataset) else data
    if _ONCE.get():
        prob, meta = _build(df, sigma_i, sigma_x)
    else:
        key = _content_key(df, sigma_i, sigma_x)
        hit = _BUILT.get(key)
        if hit is None:
            hit = _build(df, sigma_i, sigma_x)
            _BUILT.put(key, hit)
        prob, meta = hit
    return (prob if mask is None else prob.with_mask(mask)), meta


def _build(df: pd.DataFrame, sigma_i, sigma_x, groups=None, sets=None) -> tuple[Problem, Meta]:
    """``groups``: the rows' load-group codes and labels when the caller numbered them (a joined table); ``sets``:
    each row's data set there (:func:`ambfit.rows.readings`)."""
    r = readings(df, sets)
    ax = np.asarray(r.axis)
    st, sb, sx, source = _noise(df, ax, sigma_i, sigma_x)
    load = df["load_N"].to_numpy(float) if "load_N" in df else np.full(len(df), np.nan)
    codes, labels = pd.factorize(load_groups(df)) if groups is None else groups      # in order of first appearance
    # the groups with a row of unknown load, numbered in order of their first such row
    free = np.isnan(load)
    present, first = np.unique(codes[free], return_index=True)
    order = present[np.argsort(first)]
    lookup = np.full(len(labels) + 1, -1)
    lookup[order] = np.arange(len(order))
    gidx = lookup[codes]
    unknown = [labels[c] for c in order]
    known = np.isfinite(load)
    k_free = tuple(bool(known[ax == a].any()) for a in range(2))
    present = tuple(bool((ax == a).any()) for a in range(2))
    m = np.ones(len(df))
    # read-only NumPy leaves of its own, as its readings' (ambfit._arrays): the problem is kept by the table's content
    prob = Problem(readings=r, s_top=frozen(st, float), s_bottom=frozen(sb, float), s_x=frozen(sx, float),
                   load=frozen(np.nan_to_num(load)), known=frozen(known), gidx=frozen(gidx), k_free=frozen(k_free),
                   mask=frozen(m), s_held=frozen(np.zeros(len(df))))
    return prob, Meta(load_groups=unknown, k_free=k_free, axes_present=present, noise_source=source, n_rows=len(df))


# --- many data sets: one joined build ---------------------------------------------------------------------------

_ROW_COLUMNS = ("axis", "bias_A", "i_top_A", "i_bottom_A", "v_um", "w_um", "load_N", "load_id", "experiment",
                "iteration", "time_s", "temperature_C", "i_top_std_A", "i_bottom_std_A", "v_std_um", "w_std_um",
                "v_set_um", "w_set_um")


def _join_keys(joined: pd.DataFrame, frames: list[pd.DataFrame], set_id: np.ndarray, sigma_i, sigma_x) -> list:
    """What :func:`build_problem` decides for each whole table: whether the current and the position noise come
    from complete std columns (or a declared level), and which of the columns that name load groups, experiments,
    times and temperatures it has.  Data sets that agree are built as one joined table."""
    n = len(frames)
    has = {c: np.array([c in f.columns for f in frames]) for c in (*_ROW_COLUMNS,)}

    def complete(values, present):
        return present & (np.bincount(set_id, weights=np.isnan(values), minlength=n) == 0)

    def col(name):
        return joined[name].to_numpy(float) if name in joined else np.full(len(joined), np.nan)

    if sigma_i is not None:
        cur = np.ones(n, bool)
    else:
        cur = complete(col("i_top_std_A"), has["i_top_std_A"]) & complete(col("i_bottom_std_A"), has["i_bottom_std_A"])
    if sigma_x is not None:
        pos = np.ones(n, bool)
    else:
        w = (joined["axis"] == "w").to_numpy()
        pos = complete(np.where(w, col("w_std_um"), col("v_std_um")), np.ones(n, bool))
    # a table whose std columns are there but incomplete is built alone: its noise source names its own empty cells
    own = np.where((~cur & (has["i_top_std_A"] | has["i_bottom_std_A"])) | (~pos & (has["v_std_um"] | has["w_std_um"])),
                   np.arange(n), -1)
    return list(zip(cur, pos, *(has[c] for c in ("load_id", "experiment", "time_s", "temperature_C")), own))


def _slicer(prob: Problem):
    """A function ``(lo, hi, k_free, gidx) -> Problem`` of rows ``lo:hi`` of ``prob`` (NumPy leaves), built from
    the flattened problem: thousands of data sets' problems without a module constructor each."""
    paths, tree = jax.tree_util.tree_flatten_with_path(prob)
    names = [jax.tree_util.keystr(path) for path, _ in paths]
    leaves = [np.asarray(leaf) for _, leaf in paths]

    k_at, g_at = (next(i for i, name in enumerate(names) if name.endswith(end)) for end in (".k_free", ".gidx"))

    def rows(lo, hi, k_free, gidx):
        out = [leaf[lo:hi] for leaf in leaves]
        out[k_at], out[g_at] = np.asarray(k_free), gidx
        return jax.tree_util.tree_unflatten(tree, out)

    return rows


def _numbered(joined: pd.DataFrame, name: str, set_id: np.ndarray) -> np.ndarray:
    """Column ``name`` as integers unique to each data set and label (a missing label is one of its own), so that no
    label is shared between data sets."""
    return joint_codes(set_id, joined[name], own_missing=True) if name in joined else set_id.astype(np.int64)


def _joined_groups(joined: pd.DataFrame, set_id: np.ndarray):
    """The rows' load groups (:func:`ambfit.data.load_groups`, numbered per data set): ``(codes, labels)`` in order
    of first appearance, each label its own data set's; a missing label names no group (-1), as there."""
    label = next((joined[c] for c in ("load_id", "experiment") if c in joined), None)
    codes = joint_codes(set_id, *([] if label is None else [label]), joined["axis"])
    first = np.full(int(codes.max(initial=-1)) + 1, len(codes))
    np.minimum.at(first, codes[codes >= 0], np.nonzero(codes >= 0)[0])
    return codes, pd.Index(load_groups(joined.iloc[first]).to_numpy())


def _build_joined(joined: pd.DataFrame, lengths: list[int], sigma_i, sigma_x):
    """:func:`build_problem` once for the rows of many data sets (``lengths`` rows each, one after another), each
    data set's experiments and load groups numbered apart so that nothing is shared.  Returns ``(Problem, Meta)``
    per data set (NumPy leaves)."""
    set_id = np.repeat(np.arange(len(lengths)), lengths)
    groups = _joined_groups(joined, set_id)
    # each data set's clock and coil histories are its own (whether its experiments ran on one clock is decided per
    # table)
    prob, meta = _build(joined.assign(experiment=_numbered(joined, "experiment", set_id)), sigma_i, sigma_x, groups,
                        sets=set_id)
    offsets = np.cumsum([0] + list(lengths))
    rows = _slicer(prob)
    gidx, known, ax = np.asarray(prob.gidx), np.asarray(prob.known), np.asarray(prob.ax)
    # each data set's load groups are numbered one after another from its first: its own numbers start at 0
    starts = offsets[:-1]
    big = np.iinfo(gidx.dtype).max
    first = np.minimum.reduceat(np.where(gidx >= 0, gidx, big), starts)
    m = np.where(first < big, np.maximum.reduceat(gidx, starts) - first + 1, 0)
    first = np.where(first < big, first, 0)
    local = np.where(gidx >= 0, gidx - np.repeat(first, lengths), -1)
    k_free = np.stack([np.add.reduceat(known & (ax == a), starts) > 0 for a in range(2)], axis=1)
    present = np.stack([np.add.reduceat(ax == a, starts) > 0 for a in range(2)], axis=1)
    out = []
    for s, (lo, hi) in enumerate(zip(offsets[:-1], offsets[1:])):
        kf = (bool(k_free[s, 0]), bool(k_free[s, 1]))
        out.append((rows(lo, hi, kf, local[lo:hi]),
                    Meta(load_groups=list(meta.load_groups[first[s]:first[s] + m[s]]), k_free=kf,
                         axes_present=(bool(present[s, 0]), bool(present[s, 1])), noise_source=meta.noise_source,
                         n_rows=int(hi - lo))))
    return out


def build_problems(frames: list[pd.DataFrame], *, sigma_i: float | None = None, sigma_x: float | None = None):
    """:func:`build_problem` of many 0-based tables: ``(table, built, offsets)`` with ``built[s]`` the ``(Problem,
    Meta)`` of ``frames[s]`` or the exception its build raised, and ``table`` the data sets' rows one after another
    (data set ``s`` at ``offsets[s]:offsets[s+1]``, no experiment label shared between data sets).

    One table is built as itself (and cached, see :func:`build_problem`); many are concatenated, and those whose
    builds decide alike (:func:`_join_keys`) are built as one table, which is what makes a study of thousands of
    small data sets cheap.  A joined build that fails is repeated per data set, so each error names its own table.
    """
    from ambfit.data import DataError

    n = len(frames)
    lengths = [len(f) for f in frames]
    offsets = np.cumsum([0] + lengths)
    built: list = [None] * n
    if n == 1:
        try:
            built[0] = build_problem(frames[0], sigma_i=sigma_i, sigma_x=sigma_x)
        except (DataError, ValueError, KeyError) as exc:
            built[0] = exc
        return frames[0], built, offsets
    joined = pd.concat(frames, ignore_index=True, sort=False)     # every column of any table; NaN where it lacks it
    set_id = np.repeat(np.arange(n), lengths)
    keys = _join_keys(joined, frames, set_id, sigma_i, sigma_x)

    def alone(members):                         # the single build names the data set and the problem
        for s in members:
            try:
                built[s] = _build(frames[s], sigma_i, sigma_x)
            except (DataError, ValueError, KeyError) as exc:
                built[s] = exc

    alone([s for s in range(n) if not lengths[s]])          # (an empty table joins nothing)
    for key in dict.fromkeys(keys):
        members = [s for s in range(n) if keys[s] == key and lengths[s]]
        if not members:
            continue
        cols = [c for c in joined.columns if any(c in frames[s].columns for s in members)]
        part = joined if len(members) == n else joined[np.isin(set_id, members)]
        try:
            for s, b in zip(members, _build_joined(part[cols].reset_index(drop=True), [lengths[s] for s in members],
                                                   sigma_i, sigma_x)):
                built[s] = b
        except (DataError, ValueError, KeyError):
            alone(members)
    return _table(joined, lengths), built, offsets


def _table(joined: pd.DataFrame, lengths: list[int]) -> pd.DataFrame:
    """The columns that name iterations, biases and positions of the joined rows, each data set's experiments
    numbered apart."""
    table = joined[[c for c in ("axis", "bias_A", "v_um", "w_um", "v_set_um", "w_set_um") if c in joined]]
    set_id = np.repeat(np.arange(len(lengths)), lengths)
    return table.assign(iteration=joined["iteration"].fillna(1).to_numpy() if "iteration" in joined else 1,
                        experiment=_numbered(joined, "experiment", set_id))
