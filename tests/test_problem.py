"""Many data sets built as one joined table give each data set the problem it gets alone.

:func:`ambfit.estimation.problem.build_problems` numbers every data set's experiments and load groups apart in one
joined table; the reference is :func:`build_problem` of each table alone (the row-by-row definition).
"""

from pathlib import Path

import jax
import numpy as np
import pandas as pd
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from ambfit.data import zero_based
from ambfit.estimation.problem import build_problem, build_problems
from ambfit.rig import protocol
from ambfit.rig import virtual as rig

_BASE = rig.simulate(rig.PAPER_RIG, protocol.rich(biases=(1.2, 1.5), n_positions=3, masses_kg=(0.0, 0.5)),
                     seed=3).data


def _variant(seed: int, drop: frozenset, unknown: float, shared_labels: bool) -> pd.DataFrame:
    """A slice of the rig's table with some optional columns dropped and some loads unknown."""
    rng = np.random.default_rng(seed)
    lo = int(rng.integers(0, len(_BASE) // 2))
    df = _BASE.iloc[lo:lo + int(rng.integers(8, len(_BASE) // 2))].copy()
    if "load_N" in df:
        df.loc[rng.random(len(df)) < unknown, "load_N"] = np.nan
    if shared_labels:       # the same labels in every data set: nothing may be shared between them
        df["experiment"] = "E1"
        if "load_id" in df:
            df["load_id"] = np.where(df["axis"] == "v", "L1", "L2")
    return zero_based(df.drop(columns=[c for c in drop if c in df]))


def _leaves(prob):
    return {jax.tree_util.keystr(p): np.asarray(v) for p, v in jax.tree_util.tree_flatten_with_path(prob)[0]}


@settings(max_examples=15, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 10_000),
                          st.frozensets(st.sampled_from(["load_id", "experiment", "time_s", "i_top_std_A"])),
                          st.sampled_from([0.0, 0.5, 1.0]), st.booleans()), min_size=2, max_size=5))
# a later table's experiments starting before an earlier one's end: each table's clock is still its own
@example([(34, frozenset(), 0.0, False), (0, frozenset(), 0.0, False)])
def test_joined_build_is_each_tables_own(specs):
    frames = [_variant(*spec) for spec in specs]
    _, built, offsets = build_problems(frames)
    assert list(np.diff(offsets)) == [len(f) for f in frames]
    for frame, got in zip(frames, built):
        want_prob, want_meta = build_problem(frame)
        prob, meta = got
        assert meta == want_meta
        a, b = _leaves(prob), _leaves(want_prob)
        assert a.keys() == b.keys()
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_joined_table_numbers_experiments_apart():
    """Two data sets with one experiment label each get two experiment codes (seeds pair rows within one)."""
    frames = [_variant(1, frozenset(), 0.0, True), _variant(2, frozenset(), 0.0, True)]
    table, _, offsets = build_problems(frames)
    first, second = (set(table["experiment"].iloc[offsets[s]:offsets[s + 1]]) for s in range(2))
    assert len(first) == len(second) == 1 and first.isdisjoint(second)


@pytest.mark.parametrize("fill", ["load_id", "experiment"])
def test_missing_label_names_no_group(fill):
    """A row whose load-group label is missing belongs to no group in the joined build, as alone."""
    frames = [_variant(4, frozenset(), 1.0, False), _variant(5, frozenset(), 1.0, False)]
    if fill == "experiment":
        frames = [f.drop(columns="load_id") for f in frames]
    frames[1] = frames[1].astype({fill: object})
    frames[1].loc[0, fill] = None
    _, built, _ = build_problems(frames)
    want_prob, want_meta = build_problem(frames[1])
    assert built[1][1] == want_meta
    np.testing.assert_array_equal(np.asarray(built[1][0].gidx), np.asarray(want_prob.gidx))


def test_an_empty_table_in_a_study_is_an_error_in_its_place():
    """A data set without readings gets a FitError saying so; the others of the study still fit."""
    from ambfit.estimation.core import FitError
    from ambfit.estimation.fit import fit_many

    frame = _variant(6, frozenset(), 0.0, False)
    out = fit_many([frame, frame.iloc[:0], frame])
    assert isinstance(out[1], FitError) and "no readings" in str(out[1])
    assert out[0].values == pytest.approx(out[2].values, rel=1e-12)


def test_non_finite_rows_are_named_by_their_data_row():
    """A fit that gives non-finite values names the first such row as the file counts it, not its place in the
    subset fitted: the same rows kept with their file index are named 40 rows further on."""
    import re

    from ambfit.data import read_csv
    from ambfit.estimation.fit import fit_many

    frame = read_csv(Path(__file__).resolve().parents[1] / "data" / "paper_table2.csv").frame
    sub = frame.iloc[40:].copy()
    sub.loc[sub.index[5], "i_top_A"] = np.inf
    kept, renumbered = fit_many([sub, sub.reset_index(drop=True)])
    first = [int(re.search(r"the first data row (\d+)", str(e)).group(1)) for e in (kept, renumbered)]
    assert first[0] == first[1] + 40


def test_a_table_with_an_empty_std_cell_is_built_as_alone_beside_complete_ones():
    # its noise source names its own empty cell (which row, of how many): a joined build must say the same
    # (beside a table without the column, whose current noise is estimated from the residuals too)
    a, b = _variant(11, frozenset(), 0.0, False), _variant(12, frozenset({"i_top_std_A"}), 0.0, False)
    a.loc[a.index[2], "i_top_std_A"] = np.nan
    _, built, _ = build_problems([a, b])
    for frame, (prob, meta) in zip([a, b], built):
        assert meta == build_problem(frame)[1]
    assert "i_top_std_A has 1 empty cell(s)" in built[0][1].noise_source
    assert "no i_top_std_A column" in built[1][1].noise_source


def test_a_table_fitted_once_is_built_alike_and_not_kept():
    """Within ``fitted_once`` a table's problem is the one built outside it, but it is neither hashed nor kept for
    the next build of the same content."""
    from ambfit.estimation import problem

    df = rig.simulate(rig.PAPER_RIG, protocol.paper_table2(center=(-33.3e-6, 11.3e-6)), seed=11).data
    df = df.assign(i_top_A=df["i_top_A"] * (1.0 + 1e-3))          # (content no earlier test built)
    hashed = []
    digest = problem._digest
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(problem, "_digest", lambda d: hashed.append(1) or digest(d))
        with problem.fitted_once():
            once, meta_once = build_problem(df)
        assert not hashed
        kept, meta = build_problem(df)          # built again: the first was not kept
        assert hashed and build_problem(df)[0] is kept
    for a, b in zip(jax.tree.leaves(once), jax.tree.leaves(kept)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert meta_once == meta and once is not kept
