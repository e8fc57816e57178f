"""Campaigns: windows of time, drift with its error, change points; the rig's campaign, the CLI, the paper section.

Reference values state where they come from: slope errors from numpy's weighted polyfit, jump statistics from the
likelihood-ratio identity z² = χ²(no step) - χ²(step) for known errors, calibration from synthetic series.
"""

import json

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from ambfit.data import DataError, write_csv
from ambfit.faces.cli import app
from ambfit.faces.report import paper_sections as ps
from ambfit.faces.report.render import plain, section
from ambfit.rig.campaign import HOUR, TimeDrift, simulate_campaign
from ambfit.studies import campaign as C
from ambfit.studies import paper as study
from ambfit.studies.campaign.series import _line

runner = CliRunner()


@pytest.fixture(scope="module")
def sim():
    """The default campaign: 12 experiments 2 h apart, steady drift, a +3/-2 µm origin jump at E7 (seeded)."""
    return simulate_campaign(seed=3)


@pytest.fixture(scope="module")
def result(sim):
    return C.analyse(sim.data)


# --- the rig's campaign ----------------------------------------------------------------------------------------

def test_rig_campaign_runs_on_one_clock_with_drift_and_jump(sim):
    d = sim.data
    spans = d.groupby("experiment", sort=False)["time_s"].agg(["min", "max"])
    assert list(spans.index) == [f"E{j}" for j in range(1, 13)]
    assert np.all(spans["min"].to_numpy()[1:] > spans["max"].to_numpy()[:-1])      # one clock, in order
    assert sim.truth["jump"] == {"experiment": "E7", "dv0_um": 3.0, "dw0_um": -2.0}
    before, after = sim.true_params(sim.starts[6] - 1.0), sim.true_params(sim.starts[6])
    assert (after["v0"] - before["v0"]) * 1e6 == pytest.approx(3.0, abs=1e-3)
    assert sim.true_rates()["v0"] * HOUR * 1e6 == pytest.approx(0.2)
    slow = TimeDrift(dg_dt=1e-9, dx0_dt=2e-9, tau_s=100.0)
    assert float(slow.shape(1e6)) == pytest.approx(100.0)      # exponential growth settles at rate x tau


def test_noise_free_campaign_is_identified_at_each_experiments_mid_time():
    from ambfit.rig.virtual import NOISE_FREE

    sim = simulate_campaign(experiments=3, iterations=2, jump_at=2, noise=NOISE_FREE, seed=0)
    res = C.analyse(sim.data)
    for w in res.windows:
        truth = sim.true_params(w.centre_s)
        for name in ("g_v0", "v0", "g_w0", "w0"):
            # within 0.05 µm (the drift over one hour is 0.2 µm, the jump 3 µm): the rig's clock, the drift and
            # the jump are where the truth says (a drift inside an experiment costs least squares about 0.01 µm)
            assert w.estimate(name)[0] == pytest.approx(float(truth[name]), abs=5e-8), (w.label, name)


# --- on a simulated campaign ------------------------------------------------------------------------------------

def test_drift_recovered_within_its_error(sim, result):
    rates = sim.true_rates()
    for name in C.PARAMS:
        d = result.drifts[name]
        est, err = d.per_hour()
        z = (est - rates[name] * HOUR) / err
        assert abs(z) < 3, (name, est * 1e6, err * 1e6, rates[name] * HOUR * 1e6)
    assert result.drifts["v0"].z > 4 and result.drifts["v0"].steps == ("E7",)   # drift seen, jump fitted with it


def test_jump_flagged_at_the_right_experiment(result):
    assert set(result.jumps) == {"E7"}
    assert "v0" in result.jumps["E7"]
    step = result.changes["v0"].flagged[0]
    assert step.size * 1e6 == pytest.approx(3.0, abs=4 * step.std * 1e6)


def test_no_flag_without_a_jump():
    res = C.analyse(simulate_campaign(jump_at=None, seed=4).data)
    assert res.jumps == {}
    assert all(isinstance(d, C.Drift) and not d.steps for d in res.drifts.values())


def test_rolling_windows_match_experiments_and_overlap_is_handled(sim, result):
    res = C.analyse(sim.data, width_s=HOUR)
    assert [w.experiments for w in res.windows] == [(f"E{j}",) for j in range(1, 13)]
    assert res.jumps == {w: n for w, n in ((f"{res.windows[6].label} (E7)", result.jumps["E7"]),)}
    overlapping = C.windows(sim.data, 4 * HOUR, 2 * HOUR)
    keep = C.independent(overlapping)
    assert len(keep) < len(overlapping)
    assert all(overlapping[b].start_s >= overlapping[a].end_s for a, b in zip(keep, keep[1:]))


def test_a_window_too_small_to_identify_is_reported(sim):
    small = sim.data[(sim.data["experiment"] != "E3") | (sim.data.index.isin(sim.data.index[sim.data["experiment"]
                                                                                              == "E3"][:4]))]
    res = C.analyse(small)
    e3 = next(w for w in res.windows if w.label == "E3")
    assert not e3.identified and e3.n_rows == 4
    assert "4 readings for" in e3.problem
    row = res.table().set_index("window").loc["E3"]
    assert not row["identified"] and not row["used"] and "4 readings" in row["problem"]
    assert np.isnan(row["v0_um"])
    assert len(res.used) == 11 and isinstance(res.drifts["v0"], C.Drift)
    assert "E3" in res.summary() and "4 readings for" in res.summary()
    assert next(w for w in res.to_json()["windows"] if w["label"] == "E3")["identified"] is False


# --- the statistics, on synthetic series (fast) ---------------------------------------------------------------

def _series(y, s, t=None, **kw):
    t = np.arange(len(y), dtype=float) if t is None else np.asarray(t, float)
    return C.Series("v0", t, np.asarray(y, float), np.asarray(s, float), **kw)


def test_drift_slope_and_error_match_weighted_polyfit():
    rng = np.random.default_rng(0)
    t = np.sort(rng.uniform(0, 50, 9))
    s = rng.uniform(0.5, 2.0, 9)
    y = 0.3 * t + rng.normal(0, s)
    d = C.drift(_series(y, s, t), inflate=False)
    coef, cov = np.polyfit(t, y, 1, w=1 / s, cov="unscaled")         # numpy: weights 1/sigma, errors as given
    assert d.slope == pytest.approx(coef[0], rel=1e-10)
    assert d.stated_std == pytest.approx(np.sqrt(cov[0, 0]), rel=1e-10)
    assert d.std == d.stated_std
    chi2 = np.sum(((y - np.polyval(coef, t)) / s) ** 2)
    assert d.reduced_chi2 == pytest.approx(chi2 / 7, rel=1e-9)


def test_drift_error_is_inflated_only_when_the_scatter_exceeds_the_error_bars():
    rng = np.random.default_rng(1)
    t = np.arange(12.0)
    y = 0.1 * t + rng.normal(0, 3.0, 12)                     # scatter 3, error bars 1
    d = C.drift(_series(y, np.ones(12), t))
    assert d.inflated and d.std == pytest.approx(d.stated_std * np.sqrt(d.reduced_chi2))
    assert "error scaled by sqrt(χ²/dof)" in d.note()
    d = C.drift(_series(0.1 * t + rng.normal(0, 0.3, 12), np.ones(12), t))   # scatter well inside the bars
    assert not d.inflated and d.std == d.stated_std and d.note() == ""


def test_drift_pulls_are_calibrated():
    # 2000 synthetic campaigns of 10 windows with known errors: pulls (estimate - truth) / error have sd 1
    # (the Birge scaling makes intervals at least as wide as needed: sd a little under 1, coverage >= 95 %)
    rng = np.random.default_rng(2)
    t = np.linspace(0, 20, 10)
    s = np.linspace(0.5, 1.5, 10)
    pulls, plain_pulls = [], []
    for _ in range(2000):
        ser = _series(0.25 * t + rng.normal(0, s), s, t)
        d = C.drift(ser)
        pulls.append((d.slope - 0.25) / d.std)
        plain_pulls.append((d.slope - 0.25) / d.stated_std)
    assert np.std(plain_pulls) == pytest.approx(1.0, abs=0.05)
    assert 0.8 < np.std(pulls) < 1.0 and np.mean(np.abs(pulls) < 1.96) >= 0.95


def test_jump_statistic_is_the_likelihood_ratio():
    rng = np.random.default_rng(3)
    t = np.arange(10.0)
    s = rng.uniform(0.5, 1.0, 10)
    ser = _series(0.2 * t + 2.0 * (t >= 6) + rng.normal(0, s), s, t)
    cp = C.change_points(ser, inflate=False)
    null = _line(ser)
    for step in cp.scan:
        alt = _line(ser, [step.index])
        assert step.z**2 == pytest.approx(null.chi2 - alt.chi2, rel=1e-8)     # known errors: z² = Δχ²
    assert cp.tests[0].p_bound == pytest.approx(min(1.0, len(cp.scan) * cp.tests[0].p), rel=1e-12)
    assert [s.at for s in cp.flagged] == ["7"]


def test_change_points_false_alarms_and_power_on_synthetic_campaigns():
    rng = np.random.default_rng(4)
    t = np.arange(12.0)
    s = np.full(12, 0.3)
    false, hits = 0, 0
    for _ in range(400):
        false += bool(C.change_points(_series(0.2 * t + rng.normal(0, s), s, t)).flagged)
        cp = C.change_points(_series(0.2 * t + 2.0 * (t >= 7) + rng.normal(0, s), s, t))  # 2 µm = 5.7 se
        hits += [x.at for x in cp.flagged] == ["8"]
    assert false <= 10                # Bonferroni at 1 %: at most 1 %, 4 of 400 expected; 10 is 3 sd above
    assert hits >= 380


def test_a_drift_given_from_elsewhere_enters_with_its_error():
    ser = _series([35.08, 31.75, 28.77], [0.27] * 3, [5.5, 15.5, 25.5], labels=("1", "2", "3"),
                  groups=("1", "2", "3"))
    alone = C.differences(ser)
    assert alone.tests[0].z == pytest.approx(-3.33 / np.sqrt(2 * 0.27**2))
    given = C.differences(ser, drift=(-0.08, 0.11))
    d = -3.33 + 0.08 * 10
    assert given.tests[0].z == pytest.approx(d / np.sqrt(2 * 0.27**2 + (10 * 0.11) ** 2))
    assert [s.at for s in alone.flagged] == ["2", "3"] and not given.flagged
    with pytest.raises(ValueError, match="drift"):
        C.differences(ser, drift="fit")


def test_too_few_windows_and_bad_input_are_named():
    with pytest.raises(C.CampaignError, match="at least 2"):
        C.drift(_series([1.0], [1.0]))
    frame = pd.DataFrame({"axis": ["v"], "experiment": ["E1"]})
    with pytest.raises(DataError, match="time_s"):
        C.by_experiment(frame)
    clash = pd.DataFrame({"experiment": ["A", "A", "B", "B"], "time_s": [0.0, 10.0, 5.0, 20.0]})
    with pytest.raises(DataError, match="restart"):
        C.windows(clash, 60.0)


# --- the command line ------------------------------------------------------------------------------------------

def test_cli_writes_json_and_table(sim, tmp_path):
    csv = tmp_path / "camp.csv"
    write_csv(sim.data, csv)
    out, tab = tmp_path / "c.json", tmp_path / "w.csv"
    r = runner.invoke(app, ["campaign", str(csv), "--json", str(out), "--table", str(tab)])
    assert r.exit_code == 0, r.output
    assert "E7" in r.output and "drift" in r.output and "Traceback" not in r.output
    rec = json.loads(out.read_text())
    assert rec["jumps"] == {"E7": rec["jumps"]["E7"]} and "v0" in rec["jumps"]["E7"]
    assert rec["drift"]["v0"]["slope_um_per_h"] == pytest.approx(0.2, abs=4 * rec["drift"]["v0"]["std_um_per_h"])
    table = pd.read_csv(tab)
    assert len(table) == 12 and {"v0_um", "v0_std_um", "problem"} <= set(table.columns)
    r = runner.invoke(app, ["campaign", str(csv), "--window", "3600"])
    assert r.exit_code == 0, r.output


def test_cli_bad_input_exits_2_naming_file_and_column(sim, tmp_path):
    csv = tmp_path / "no_time.csv"
    write_csv(sim.data.drop(columns=["time_s"]).iloc[:40], csv)
    r = runner.invoke(app, ["campaign", str(csv)])
    assert r.exit_code == 2 and "no_time.csv" in r.output and "'time_s'" in r.output and "Traceback" not in r.output
    restart = sim.data.iloc[:160].copy()
    restart.loc[restart["experiment"] == "E2", "time_s"] -= sim.starts[1]        # a clock per experiment
    csv = tmp_path / "restart.csv"
    write_csv(restart, csv)
    r = runner.invoke(app, ["campaign", str(csv)])
    assert r.exit_code == 2 and "restart.csv" in r.output and "'time_s'" in r.output
    r = runner.invoke(app, ["campaign", str(csv), "--by", "bearing"])
    assert r.exit_code == 2 and "'bearing'" in r.output
    r = runner.invoke(app, ["campaign", str(csv), "--window", "60", "--by", "experiment"])
    assert r.exit_code == 2
    r = runner.invoke(app, ["campaign", str(tmp_path / "missing.csv")])
    assert r.exit_code == 2 and "missing.csv" in r.output


def test_cli_exits_3_when_too_few_windows_are_identified(sim, tmp_path):
    csv = tmp_path / "two.csv"
    write_csv(sim.data[sim.data["experiment"].isin(["E1", "E2"])], csv)
    r = runner.invoke(app, ["campaign", str(csv)])
    assert r.exit_code == 3 and "only 2 window(s) identified" in r.output


# --- the paper report's section ---------------------------------------------------------------------------------

def test_origins_over_time_section_follows_the_paper_tables(monkeypatch):
    s = ps.origins_over_time()
    text = plain(section("paper_sections.html.j2", "origins_over_time", s))
    assert "35.08 → 31.75 → 28.77 µm" in text
    assert [(f["quantity"], f["at"]) for f in s["flagged_moves"]][:2] == [("v0", "2"), ("v0", "3")]
    assert not s["flagged_changes"] and "no move is flagged" in text
    v0 = s["drift"]["v0"]
    assert f"v0 {v0['slope']:+.2f} ± {v0['se']:.2f} µm per iteration" in text
    original = study.load_table

    def edited(n, averages=False):
        t = original(n, averages)
        if n == 1 and not averages:
            t["v0_um"] = [36.0, 32.0, 20.0]
        return t

    monkeypatch.setattr(study, "load_table", edited)
    s = ps.origins_over_time()
    text = plain(section("paper_sections.html.j2", "origins_over_time", s))
    assert "36.00 → 32.00 → 20.00 µm" in text and "35.08" not in text
    assert [(f["quantity"], f["at"]) for f in s["flagged_changes"]] == [("v0", "3")]   # -12 µm: beyond any drift
    assert "still flagged: v0 at experiment 3" in text


def test_the_example_campaign_runs_on_the_bearing_given(tmp_path):
    # a 500 µm / 5 A / 40 µm-clearance bearing of a user's: its biases and pairs scaled to it, every window
    # identified and the jump found at E7 (on the paper's rig settings the windows were all rejected)
    toml = tmp_path / "mine.toml"
    toml.write_text('name = "mine"\nnominal_gap_um = 500.0\nmax_current_A = 5.0\nturns_per_pole = 200\n'
                    'backup_clearance_um = 40.0\n')
    out, js = tmp_path / "c.csv", tmp_path / "c.json"
    r = runner.invoke(app, ["campaign", "--example", str(out), "--bearing", str(toml), "--json", str(js),
                            "--current-noise-ma", "0.3"])
    assert r.exit_code == 0, r.output
    rec = json.loads(js.read_text())
    assert len(rec["used"]) == 12 and "E7" in rec["jumps"]
    data = pd.read_csv(out)
    assert data["bias_A"].max() == pytest.approx(1.6 * 5 / 3) and data["i_top_std_A"].iloc[0] == pytest.approx(3e-4)
