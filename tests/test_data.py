"""Contract CSV: every error case names file, row, column and value; round trips lose nothing."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ambfit import data as D
from ambfit import rig
from ambfit import rows as R
from ambfit.rig import protocol as P


@pytest.fixture
def table():
    sim = rig.simulate(rig.PAPER_RIG, P.paper_table2(iterations=2), seed=1)
    df = sim.data.copy()
    df["operator"] = "alice"          # extra columns must survive
    df["note"] = ["x,y"] + [""] * (len(df) - 1)
    return df


def _write(df, tmp_path, name="d.csv"):
    p = tmp_path / name
    df.to_csv(p, index=False)
    return p


def test_round_trip_keeps_everything(table, tmp_path):
    p = _write(table, tmp_path)
    ds = D.read_csv(p)
    out = tmp_path / "out.csv"
    D.write_csv(ds, out)
    back = D.read_csv(out)
    assert list(back.frame.columns) == list(table.columns)
    for col in ("i_top_A", "i_bottom_A", "v_um", "w_um", "load_N", "time_s"):
        np.testing.assert_array_equal(back.frame[col].to_numpy(float), table[col].to_numpy(float))
    assert back.frame["operator"].tolist() == ["alice"] * len(table)
    assert back.frame["note"].iloc[0] == "x,y"


def _expect(tmp_path, df, *, row, column, value, match):
    p = _write(df, tmp_path)
    with pytest.raises(D.DataError, match=match) as info:
        D.read_csv(p)
    e = info.value
    assert e.file == str(p) and e.row == row and e.column == column
    if value is not None:
        assert str(e.value) == str(value)
    msg = str(e)
    assert str(p) in msg and (row is None or f"row {row}" in msg) and (column is None or column in msg)
    return e


def test_missing_required_column(table, tmp_path):
    e = _expect(tmp_path, table.drop(columns=["i_bottom_A"]), row=None, column=None, value=None,
                match="missing required column")
    assert "i_bottom_A" in str(e)


@pytest.mark.parametrize("bad", ["abc", "1.2.3", "inf", "-inf", "nan"])
def test_non_numeric_or_non_finite(table, tmp_path, bad):
    df = table.astype({"i_top_A": object})
    df.loc[3, "i_top_A"] = bad
    # NaN written as an empty cell in a required column is reported as empty
    match = "empty cell|not a finite number"
    _expect(tmp_path, df, row=4, column="i_top_A", value=None, match=match)


# One corrupted cell per case: (index, column, new value, expected value in the error or None, message).
CELL_CASES = {
    "empty required cell": (6, "v_um", "", None, "empty cell"),
    "negative current": (5, "i_bottom_A", -0.25, -0.25, "negative current"),
    "unknown axis": (2, "axis", "x", "x", "unknown axis"),
    # e.g. nanometres written into a µm column
    "position as large as the gap": (7, "w_um", 20000.0, 20000.0, "as large as the air gap"),
    "time backwards": (10, "time_s", 0.5, 0.5, "time goes backwards"),
    "non-integer iteration": (4, "iteration", "2.5", "2.5", "integer"),
    "non-positive std": (1, "i_top_std_A", 0.0, 0.0, "must be positive"),
}


@pytest.mark.parametrize("case", list(CELL_CASES))
def test_bad_cell(table, tmp_path, case):
    index, column, new, value, match = CELL_CASES[case]
    df = table.astype({column: object}) if isinstance(new, str) else table.copy()
    df.loc[index, column] = new
    _expect(tmp_path, df, row=index + 1, column=column, value=value, match=match)


def test_inconsistent_known_load(table, tmp_path):
    df = table.copy()
    v_rows = df.index[df.axis == "v"]
    df.loc[v_rows[3], "load_N"] = 9.5
    e = _expect(tmp_path, df, row=int(v_rows[3]) + 1, column="load_N", value=9.5, match="known load differs")
    assert "rotor" in str(e)


def test_known_load_differs_between_axes_is_fine(table, tmp_path):
    df = table.copy()
    df.loc[df.axis == "w", "load_N"] = 3.0  # one load_id, different projections on v and w
    assert len(D.read_csv(_write(df, tmp_path))) == len(df)


def test_empty_optional_cells_mean_unknown(table, tmp_path):
    df = table.astype({"load_N": object})
    df["load_N"] = ""
    ds = D.read_csv(_write(df, tmp_path))
    assert ds.frame["load_N"].isna().all()


def test_file_level_errors(tmp_path):
    with pytest.raises(D.DataError, match="no such file"):
        D.read_csv(tmp_path / "nope.csv")
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(D.DataError, match="empty"):
        D.read_csv(tmp_path / "empty.csv")
    (tmp_path / "header.csv").write_text("axis,bias_A,i_top_A,i_bottom_A,v_um,w_um\n")
    with pytest.raises(D.DataError, match="no data rows"):
        D.read_csv(tmp_path / "header.csv")
    (tmp_path / "dup.csv").write_text("axis,bias_A,i_top_A,i_bottom_A,v_um,w_um,v_um\nv,1,1,1,0,0,0\n")
    with pytest.raises(D.DataError, match="duplicate column"):
        D.read_csv(tmp_path / "dup.csv")


def test_readings_in_si_units(table, tmp_path):
    ds = D.read_csv(_write(table, tmp_path))
    r = R.readings(ds)
    w = table.axis.to_numpy() == "w"
    np.testing.assert_allclose(np.asarray(r.x)[w], table.w_um.to_numpy()[w] * 1e-6)
    np.testing.assert_allclose(np.asarray(r.y)[w], table.v_um.to_numpy()[w] * 1e-6)
    assert set(np.unique(np.asarray(r.dir_top))) <= {-1.0, 1.0}


def test_approach_direction_follows_the_order():
    df = pd.DataFrame({"axis": ["v"] * 5, "i_top_A": [1.0, 1.2, 1.4, 1.2, 1.0], "experiment": "e"})
    np.testing.assert_array_equal(R.approach_direction(df, "i_top_A"), [1, 1, 1, -1, -1])


def test_a_zero_current_read_through_its_noise_is_accepted(table, tmp_path):
    # a coil at 0 A whose sensor (0.6 mA noise) reads -0.2 mA is a zero current, not a unit or sign error;
    # without std columns down to -3 mA; beyond 5 sigma it is refused as before
    df = table.copy()
    df.loc[4, "i_bottom_A"] = -0.0002
    path = tmp_path / "near_zero.csv"
    df.to_csv(path, index=False)
    assert D.read_csv(path).frame.loc[4, "i_bottom_A"] == -0.0002
    df.loc[4, "i_bottom_A"] = -0.0031
    df.to_csv(path, index=False)
    with pytest.raises(D.DataError, match="negative current"):
        D.read_csv(path)


# --- the vectorised row-order functions against their definitions, row by row --------------------------------

def _experiments(df):
    """Each row's experiment as a label (a missing one is one label of its own)."""
    if "experiment" not in df.columns:
        return [""] * len(df)
    return [None if pd.isna(e) else str(e) for e in df["experiment"]]


def _one_clock_by_definition(df):
    """clock's docstring: each timed experiment, in the order the file lists them, starts after the one before ends
    (rows of no experiment are in none)."""
    if "time_s" not in df.columns:
        return False
    exp = _experiments(df)
    spans = []
    for e in dict.fromkeys(x for x in exp if x is not None):        # in the order the file lists them
        times = [t for x, t in zip(exp, df["time_s"]) if x == e and not np.isnan(t)]
        if times:
            spans.append((min(times), max(times)))
    return all(b[0] >= a[1] for a, b in zip(spans, spans[1:]))


def _direction_by_definition(df, column, threshold=2e-3):
    """approach_direction's docstring, one row at a time: within each run, the sign of a change of at least
    ``threshold`` from the previous reading, else the previous direction; the first reading rises.  A run is an
    experiment and axis, or, when the experiments share one clock, an axis' timed experiments one after another (a
    missing label is an experiment of its own, on no clock)."""
    exp = _experiments(df)
    timed = ({e for e, t in zip(exp, df["time_s"]) if not np.isnan(t) and e is not None} if "time_s" in df.columns
             else set())
    chained = _one_clock_by_definition(df)
    listed = list(dict.fromkeys(exp))
    key_of = [("clock", ax) if chained and e in timed else (e, ax) for e, ax in zip(exp, df["axis"])]
    rows = sorted(range(len(df)), key=lambda j: (listed.index(exp[j]), j))
    out, prev_row, prev_dir = np.zeros(len(df)), {}, {}
    for j in rows:
        key, i = key_of[j], df[column].iloc[j]
        if key in prev_row and abs(i - prev_row[key]) >= threshold:
            prev_dir[key] = float(np.sign(i - prev_row[key]))
        prev_dir.setdefault(key, 1.0)
        prev_row[key] = i
        out[j] = prev_dir[key]
    return out


def test_experiments_run_on_in_the_order_the_file_lists_them():
    """An experiment listed first but timed after the next one started: its clock restarted, so nothing chains; read
    one after another, each axis' coil history runs on from one experiment into the next."""
    df = pd.DataFrame({"axis": "v", "experiment": ["b", "a", "a", "b", "b"], "time_s": [np.nan, 0.0, 1.0, 2.0, 3.0],
                       "i_top_A": [1.0, 1.0, 2.0, 1.5, 1.6], "i_bottom_A": 1.0})
    np.testing.assert_array_equal(R.approach_direction(df, "i_top_A"), _direction_by_definition(df, "i_top_A"))
    np.testing.assert_array_equal(R.approach_direction(df, "i_top_A"), [1, 1, 1, 1, 1])
    chained = df.assign(experiment=["a", "a", "a", "b", "b"], time_s=[0.0, 1.0, 2.0, 3.0, 4.0])
    np.testing.assert_array_equal(R.approach_direction(chained, "i_top_A"), [1, 1, 1, -1, 1])


def _other_by_definition(df):
    """other_axis_currents' docstring, one row at a time: the first row of the other axis with the same experiment
    and time."""
    it, ib = np.full(len(df), np.nan), np.full(len(df), np.nan)
    if "time_s" not in df.columns:
        return it, ib
    exp = _experiments(df)
    for j in range(len(df)):
        for k in range(len(df)):
            if exp[k] == exp[j] and df["time_s"].iloc[k] == df["time_s"].iloc[j] and \
                    df["axis"].iloc[k] != df["axis"].iloc[j]:
                it[j], ib[j] = df["i_top_A"].iloc[k], df["i_bottom_A"].iloc[k]
                break
    return it, ib


@settings(max_examples=100, deadline=None)
@given(st.integers(1, 30), st.integers(0, 2**31 - 1),
       st.sampled_from([None, "text", "numbers", "integers", "missing"]), st.booleans())
def test_row_order_functions_follow_their_definitions(n, seed, experiment, one_clock):
    rng = np.random.default_rng(seed)
    df = pd.DataFrame({"axis": rng.choice(["v", "w"], n), "time_s": rng.choice([0.0, 0.5, 1.0, np.nan], n),
                       "i_top_A": np.round(rng.normal(1.5, 0.004, n), 4), "i_bottom_A": rng.normal(1.5, 0.1, n)})
    if experiment is not None:
        if experiment == "integers":                 # an integer column (a study's joined table numbers them)
            df["experiment"] = rng.integers(0, 3, n).astype(np.int64)
        else:
            labels = {"text": ["a", "b"], "numbers": [1, 2], "missing": ["a", None]}[experiment]
            df["experiment"] = pd.Series(rng.choice(np.array(labels, dtype=object), n))
        if one_clock:                                # experiments read one after another on one clock
            df = df.sort_values("experiment", kind="stable", key=lambda e: e.astype(str)).reset_index(drop=True)
            df["time_s"] = np.where(rng.random(n) < 0.1, np.nan, np.arange(n) // 2 * 0.5)
    np.testing.assert_array_equal(R.approach_direction(df, "i_top_A"), _direction_by_definition(df, "i_top_A"))
    for got, want in zip(R.other_axis_currents(df), _other_by_definition(df)):
        np.testing.assert_array_equal(got, want)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(["a", "b", None, "1"]), st.sampled_from([1.0, 2.0, float("nan")]),
                          st.sampled_from(["v", "w"])), min_size=1, max_size=40))
def test_joint_codes_number_rows_as_a_groupby_does(rows):
    """joint_codes is pandas' groupby(sort=False).ngroup() over the keys: groups in order of first appearance, a row
    with a missing key in none (-1), or with own_missing in the group of the missing value."""
    from ambfit.data import joint_codes

    df = pd.DataFrame(rows, columns=["e", "i", "a"])
    want = df.groupby(["e", "i", "a"], sort=False).ngroup().to_numpy()
    np.testing.assert_array_equal(joint_codes(df["e"], df["i"], df["a"]), np.where(np.isnan(want), -1, want))
    want = df.groupby(["e", "i", "a"], sort=False, dropna=False).ngroup().to_numpy()
    np.testing.assert_array_equal(joint_codes(df["e"], df["i"], df["a"], own_missing=True), want)


def test_play_states_follow_the_play_operator():
    # width 0.15 A: the current rises from zero to 1.0 (state +1), falls 0.1 (inside the band: (0.9 - 0.85) / 0.15),
    # falls 0.3 more (the play follows: -1), rises 0.1 ((0.7 - 0.75) / 0.15), stays; experiment b starts from zero
    df = pd.DataFrame({"axis": ["v"] * 6, "experiment": ["a"] * 5 + ["b"],
                       "i_top_A": [1.0, 0.9, 0.6, 0.7, 0.7, 0.1]})
    s = R.play_states(df, "i_top_A", [0.15, 1e-6])
    np.testing.assert_allclose(s[:, 0], [1.0, (0.9 - 0.85) / 0.15, -1.0, (0.7 - 0.75) / 0.15,
                                         (0.7 - 0.75) / 0.15, 0.1 / 0.15])
    # a vanishing width is the approach direction
    np.testing.assert_allclose(s[:, 1], R.approach_direction(df, "i_top_A", threshold=1e-9))


def test_fading_states_follow_an_exponential_memory_of_the_current():
    # memories of 1 and 3 readings, half-widths 0.2 A and 10 A (memory outer, width inner); run (a, v) steps 0 ->
    # 1.0 -> 1.0 -> 0.5 (from zero current), a w row between its readings runs on its own, experiment b starts again
    df = pd.DataFrame({"axis": ["v", "w", "v", "v", "v"], "experiment": ["a", "a", "a", "a", "b"],
                       "i_top_A": [1.0, 0.2, 1.0, 0.5, 0.3]})
    s = R.fading_states(df, "i_top_A", [1.0, 3.0], [0.2, 10.0])
    for k, memory in enumerate((1.0, 3.0)):
        a = np.exp(-1.0 / memory)
        q, want = 0.0, []
        for i in (1.0, 1.0, 0.5):
            q = a * q + (1.0 - a) * i
            want.append(i - q)
        want = np.array(want)
        for j, width in enumerate((0.2, 10.0)):
            col = s[:, 2 * k + j]
            np.testing.assert_allclose(col[[0, 2, 3]], np.clip(want / width, -1.0, 1.0))
            np.testing.assert_allclose(col[[1, 4]], np.clip(np.array([0.2, 0.3]) * a / width, -1.0, 1.0))
    assert s[3, 0] < 0.0 < s[3, 2]       # after the fall the current sits below a short memory; a long one still rises


def test_a_spreadsheet_export_is_read_and_said(tmp_path):
    # a German Excel's "CSV": semicolons, decimal commas, a blank row of separators; the same numbers as the
    # contract's file, and what was taken in stride said as notes
    from ambfit.data import read_csv

    default = Path(__file__).resolve().parents[1] / "data" / "paper_table2.csv"
    d = pd.read_csv(default)
    lines = d.to_csv(sep=";", index=False, decimal=",").splitlines()
    lines.insert(5, ";" * (len(d.columns) - 1))
    path = tmp_path / "excel.csv"
    path.write_text("\n".join(lines) + "\n")
    ds, want = read_csv(path), read_csv(default)
    pd.testing.assert_frame_equal(ds.frame.reset_index(drop=True), want.frame.reset_index(drop=True))
    assert [n.split(": ", 1)[1] for n in ds.notes] == [
        "read as semicolon-separated with decimal commas (a spreadsheet's export; the contract's CSV is "
        "comma-separated with decimal points)", "1 blank row(s) skipped (data rows 5)"]


def test_rows_after_a_skipped_blank_row_keep_their_file_numbers(tmp_path):
    from ambfit.data import DataError, read_csv

    default = Path(__file__).resolve().parents[1] / "data" / "paper_table2.csv"
    lines = default.read_text().splitlines()
    lines.insert(3, "," * lines[0].count(","))              # blank data row 3
    cells = lines[10].split(",")
    cells[2] = "oops"                                        # data row 10 (line 11), its i_top_A
    lines[10] = ",".join(cells)
    path = tmp_path / "blank.csv"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"row 10\b.*i_top_A.*oops"):
        read_csv(path)


def test_a_frames_missing_values_in_optional_columns_are_missing_not_errors():
    """A frame built in memory holds a missing optional value as NaN (an unknown load), which stays NaN as text;
    a file's empty cell is the empty string.  Both are a missing value, not a number that is not finite."""
    df = rig.simulate(rig.PAPER_RIG, P.rich(), seed=1).data
    df.loc[:5, "load_N"] = np.nan
    df["iteration"] = df["iteration"].astype(float)
    df.loc[7, "iteration"] = np.nan
    ds = D.check(df)
    assert ds.frame["load_N"].isna().sum() == 6 and ds.frame["iteration"].isna().sum() == 1
