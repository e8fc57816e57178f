"""``ambfit identify`` on many files and groups: one estimate per group, each judged on its own, a table and a JSON
entry per group, a pooled fit only when asked, and an exit code that says whether every group is fine."""

import json
from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from ambfit.faces.cli import app

ROOT = Path(__file__).resolve().parents[1]
TABLE2 = ROOT / "data" / "paper_table2.csv"
WIDE = {"COLUMNS": "400"}


def runs(table2, *labels):
    """The default data once per label, as separate runs (experiment and column ``run`` = the label)."""
    return pd.concat([table2.assign(run=x, experiment=f"table2-{x}") for x in labels])


def run(*args):
    return CliRunner().invoke(app, ["identify", *map(str, args)], env=WIDE)


@pytest.fixture(scope="module")
def table2():
    return pd.read_csv(TABLE2)


@pytest.fixture
def bearings(tmp_path, table2):
    """One file, three bearings: A (the default data), B (loads typed in mN: implausible), C (two readings at one
    position: the design does not identify the gap)."""
    a = table2.assign(bearing="A")
    b = table2.assign(bearing="B", load_N=table2["load_N"] * 1e3, load_id="B" + table2["load_id"].astype(str),
                      experiment="B")
    c = table2[table2["axis"] == "v"].head(2).assign(bearing="C", experiment="C", load_id="C")
    path = tmp_path / "bearings.csv"
    pd.concat([a, b, c]).to_csv(path, index=False)
    return path


def test_one_file_without_by_keeps_the_contract_json(tmp_path):
    out = tmp_path / "o.json"
    r = run(TABLE2, "--json", out)
    assert r.exit_code == 0, r.output
    js = json.loads(out.read_text())
    assert "groups" not in js and js["method"] == "least_squares" and js["n_rows"] == 80
    assert set(js["params"]) >= {"g_v0_um", "v0_um", "g_w0_um", "w0_um"}


def test_several_files_and_a_glob_give_one_row_each_and_an_unreadable_file_exits_2(tmp_path, table2):
    runs = tmp_path / "runs"
    runs.mkdir()
    table2.to_csv(runs / "a.csv", index=False)
    table2[table2["iteration"] <= 5].to_csv(runs / "b.csv", index=False)
    (runs / "c.csv").write_text("axis,bias_A,i_top_A,i_bottom_A,v_um,w_um\nq,1.4,1.5,1.3,20,20\n")
    table, out = tmp_path / "t.csv", tmp_path / "g.json"
    # the glob quoted (as a shell would pass 'runs/*.csv'), a.csv also named on its own: identified once
    r = run(runs / "a.csv", str(runs / "*.csv"), "--table", table, "--json", out)
    assert r.exit_code == 2, r.output
    assert "c.csv" in r.output and "row 1" in r.output and "'q'" in r.output          # the DataError, in full
    assert "1 of 3 group(s) not fine" in r.output and "(unreadable)" in r.output
    t = pd.read_csv(table)
    assert [Path(f).name for f in t["file"]] == ["a.csv", "b.csv", "c.csv"]
    assert t["status"].tolist() == ["ok", "ok", "unreadable"] and t["n_rows"].tolist()[:2] == [80, 40]
    assert {"g_v0_um", "g_v0_std_um", "v0_um", "k_v_Nm2_per_A2", "k_v_std_Nm2_per_A2", "reduced_chi2", "converged",
            "well_conditioned", "adequate", "outliers", "implausible", "error"} <= set(t.columns)
    js = json.loads(out.read_text())
    assert "pooled" not in js and js["n_groups"] == 3 and js["n_ok"] == 2
    a = js["groups"][0]
    assert a["params"]["g_v0_um"]["value"] == pytest.approx(t["g_v0_um"][0])
    assert a["params"]["g_v0_um"]["std"] == pytest.approx(t["g_v0_std_um"][0])
    # fewer iterations, larger error bar: each file is its own fit
    assert t["g_v0_std_um"][1] > 1.3 * t["g_v0_std_um"][0]
    assert "c.csv" in js["groups"][2]["error"]


def test_a_pattern_that_matches_nothing_is_named(tmp_path):
    r = run(TABLE2, str(tmp_path / "nothing*.csv"))
    assert r.exit_code == 2 and "no file matches this pattern" in r.output


def test_by_any_column_judges_each_group_on_its_own(bearings, tmp_path):
    table, out = tmp_path / "t.csv", tmp_path / "g.json"
    r = run(bearings, "--by", "bearing", "--table", table, "--json", out)
    assert r.exit_code == 3, r.output
    t = pd.read_csv(table)
    assert t["group"].tolist() == ["A", "B", "C"] and t["bearing"].tolist() == ["A", "B", "C"]
    assert t["status"].tolist() == ["ok", "implausible", "failed"]
    # B's loads are 1000 x too large (mN typed as N): k comes out 1000 x too large, and the cause says mN
    assert t["implausible"].tolist() == [False, True, False] and "loads given in mN" in t["implausible_why"][1]
    assert "does not identify" in t["error"][2]
    # A is the default data's fit, untouched by B and C; B's gap is estimated (only its loads are wrong)
    assert run(TABLE2, "--json", tmp_path / "a.json").exit_code == 0
    alone = json.loads((tmp_path / "a.json").read_text())
    assert t["g_v0_um"][0] == pytest.approx(alone["params"]["g_v0_um"]["value"], rel=1e-9)
    # the same optimum, reached in another scaling (k 1000 x): equal to the fit's convergence tolerance, which
    # stops a round within 1e-4 standard errors of its optimum (core.EDM_ROUND); measured 5e-6 µm = 4e-6 sd
    assert abs(t["g_v0_um"][1] - t["g_v0_um"][0]) < 1e-4 * alone["params"]["g_v0_um"]["std"]
    assert "2 of 3 group(s) not fine: B (implausible); C (fit failed)" in r.output
    js = json.loads(out.read_text())
    assert js["by"] == "bearing" and [g["value"] for g in js["groups"]] == ["A", "B", "C"]
    # --accept-implausible lets B pass; C still fails the fit
    r = run(bearings, "--by", "bearing", "--accept-implausible")
    assert r.exit_code == 3 and "1 of 3 group(s) not fine: C (fit failed)" in r.output


def test_pooled_only_when_asked(bearings, tmp_path, table2):
    out = tmp_path / "g.json"
    data = tmp_path / "two.csv"
    runs(table2, "1", "2").to_csv(data, index=False)
    r = run(data, "--by", "run", "--pooled", "--json", out)
    assert r.exit_code == 0, r.output
    js = json.loads(out.read_text())
    assert [g["group"] for g in js["groups"]] == ["1", "2"]
    pooled = js["pooled"]
    assert pooled["group"] == "(pooled)" and pooled["n_rows"] == 160 and pooled["status"] == "ok"


def test_a_missing_by_column_names_the_columns(tmp_path):
    r = run(TABLE2, "--by", "operator")
    assert r.exit_code == 2 and "no column 'operator'" in r.output and "experiment" in r.output


def test_duplicates_in_a_group_are_named_by_their_file_rows(tmp_path, table2):
    both = runs(table2, "1", "2").drop(columns="time_s")     # a repeat at the end would run time backwards
    data = tmp_path / "d.csv"
    pd.concat([both, both.iloc[[80]]]).to_csv(data, index=False)          # file row 161 repeats row 81
    r = run(data, "--by", "run")
    assert r.exit_code == 0, r.output
    assert "rows 161 repeats 81" in r.output


def test_closed_form_per_group(tmp_path, table2):
    data = tmp_path / "two.csv"
    runs(table2, "1", "2").to_csv(data, index=False)
    out = tmp_path / "g.json"
    r = run(data, "--by", "run", "--method", "closed-form", "--json", out)
    assert r.exit_code == 0, r.output
    js = json.loads(out.read_text())
    assert js["method"] == "closed_form"
    g1, g2 = (g["params"]["g_v0_um"]["value"] for g in js["groups"])
    assert g1 == pytest.approx(g2, rel=1e-12)         # the same data twice: the same estimate


# --- the groups on worker processes (ambfit.engine): the same entries as in this process ---------------------

def test_workers_and_scheduler_exclude_each_other_and_need_dask(tmp_path, table2, monkeypatch):
    data = tmp_path / "two.csv"
    runs(table2, "1", "2").to_csv(data, index=False)
    r = run(data, "--by", "run", "--workers", "2", "--scheduler", "tcp://localhost:8786")
    assert r.exit_code == 2 and "not both" in r.output
    import sys

    monkeypatch.setitem(sys.modules, "distributed", None)          # as if dask were not installed
    r = run(data, "--by", "run", "--workers", "2")
    assert r.exit_code == 2 and "install ambfit[dask]" in r.output


@pytest.mark.skipif(__import__("importlib").util.find_spec("distributed") is None,
                    reason="dask[distributed] is not installed (pip install 'ambfit[dask]')")
@pytest.mark.slow          # two worker processes
def test_a_fleet_on_two_worker_processes_gives_the_same_table(bearings, tmp_path, table2):
    # A (fine), B (implausible), C (not identifiable), D (one reading 50 mA off: named and left out), E (a duplicate)
    d = table2.assign(bearing="D", experiment="D", load_id="D" + table2["load_id"].astype(str))
    d.loc[d.index[5], "i_top_A"] += 0.05
    e = table2.head(40).assign(bearing="E", experiment="E", load_id="E" + table2["load_id"].head(40).astype(str),
                               time_s=table2["time_s"].head(40) + 1e5)
    fleet = tmp_path / "fleet.csv"
    pd.concat([pd.read_csv(bearings), d, e, e.iloc[[39]]]).to_csv(fleet, index=False)
    here, there = tmp_path / "here.csv", tmp_path / "there.csv"
    r1 = run(fleet, "--by", "bearing", "--table", here)
    r2 = run(fleet, "--by", "bearing", "--table", there, "--workers", "2")
    assert r1.exit_code == r2.exit_code == 3, r2.output
    a, b = pd.read_csv(here), pd.read_csv(there)
    assert a["status"].tolist() == ["ok", "implausible", "failed", "ok", "ok"]
    assert a["outliers"].tolist() == [0, 0, 0, 1, 0] and a["duplicates_dropped"].tolist() == [0, 0, 0, 0, 1]
    numbers = a.select_dtypes("number").columns
    pd.testing.assert_frame_equal(a.drop(columns=numbers), b.drop(columns=numbers))
    # the batch and the single fit stop within the same convergence test (core.EDM_MAX): same numbers to 1e-8
    pd.testing.assert_frame_equal(a[numbers], b[numbers], rtol=1e-8)
    # every message of every group, in the groups' order (only the written file's name differs)
    assert r1.output.replace("here.csv", "T") == r2.output.replace("there.csv", "T")


def test_a_group_whose_law_does_not_fit_is_not_called_fine(tmp_path, table2):
    # group "noisy": its std columns a third of the real noise (chi2/dof about 9): estimates stand, but the summary
    # says the law does not fit it instead of "all fine"
    good = table2.assign(run="good")
    noisy = table2.assign(run="noisy", experiment="noisy", load_id="noisy" + table2["load_id"].astype(str),
                          **{c: table2[c] / 3 for c in ("i_top_std_A", "i_bottom_std_A", "v_std_um", "w_std_um")})
    path = tmp_path / "two.csv"
    pd.concat([good, noisy]).to_csv(path, index=False)
    r = run(path, "--by", "run")
    assert r.exit_code == 0, r.output
    assert "1 group(s) whose model does not fit its readings" in r.output and "noisy (χ²/dof" in r.output
    assert "all 2 group(s) fitted, 1 of them not fitting their readings" in r.output
    assert "fine" not in r.output
    assert r.output.count("ok, misfit") == 1          # the table's status says it too
