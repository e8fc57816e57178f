"""The paper's tables as data and their reproduction on the rig (the HTML reports: tests/test_report.py)."""

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from ambfit.rig import protocol
from ambfit.studies import paper, paper_gap

ROOT = Path(__file__).resolve().parents[1]
Q = list(paper.QUANTITIES)


@pytest.mark.parametrize("n, rows", [(1, 3), (2, 10), (3, 4), (4, 6)])
def test_transcribed_rows_reproduce_the_printed_averages(n, rows):
    t, avg = paper.load_table(n), paper.load_table(n, averages=True)
    assert len(t) == rows and len(avg) == 1
    assert {"source_table", "source_row"} <= set(t.columns)
    assert (t["source_table"] == n).all()
    # the paper prints two decimals. If it averaged unrounded row values, the mean of the printed rows can
    # differ from the printed average by up to 0.005 (row rounding) + 0.005 (average rounding) = 0.01; Table 4's
    # g_w0 does (763.5917 vs 763.60). A transcription slip of one digit moves the mean by >= 0.01 / 6.
    np.testing.assert_allclose(t[Q].mean().to_numpy(), avg[Q].iloc[0].to_numpy(float), atol=0.0101)


def test_columns_carry_units_and_settings_have_sources():
    for n in (1, 2, 3, 4):
        cols = [c for c in paper.load_table(n).columns if c not in ("source_table", "source_row", "source_no",
                                                                   "iteration", "note")]
        assert all(re.search(r"_(um|A)$", c) for c in cols), cols
    s = paper.settings().set_index("quantity")
    assert float(s.loc["nominal_gap", "value"]) == 762 and s.loc["nominal_gap", "unit"] == "um"
    assert float(s.loc["load_capacity", "value"]) == 53.4 and float(s.loc["saturation_current", "value"]) == 3.0
    assert s["source"].str.len().min() > 10


def test_rows_follow_the_tables_protocols():
    rs = paper.rows()
    assert [(r.table, r.row) for r in rs] == [(1, 1), (1, 2), (1, 3)] + [(3, i) for i in range(1, 5)] + \
        [(4, i) for i in range(1, 7)]
    assert [r.biases for r in rs if r.table == 1] == [(1.4, 1.5), (1.4, 1.6), (1.5, 1.6)]
    np.testing.assert_allclose([r.start for r in rs if r.table == 3], protocol.PAPER_TABLE3_STARTS)
    t4 = [r for r in rs if r.table == 4]
    assert [round(r.offset * 1e6) for r in t4] == [30, 40, 50, 30, 40, 50]
    assert all(r.origin_shift == paper.TABLE4_SHIFT for r in t4)


@pytest.fixture(scope="module")
def rep():
    return paper.reproduce(replicates=6, seed=3)


def test_reproduction_covers_every_row_and_matches_the_rig(rep):
    comp = rep.comparison()
    # every numbered row of Tables 1-4 and each printed average, four quantities each
    assert len(comp) == (3 + 10 + 4 + 6 + 4) * 4
    for t in (1, 2, 3, 4):
        sub = comp[(comp["table"] == t) & (comp["row"] > 0)]
        np.testing.assert_allclose(sub.pivot(index="row", columns="quantity", values="paper")[Q].to_numpy(),
                                   paper.load_table(t)[Q].to_numpy(float))
    assert (comp["rig_sd"] > 0).all()
    # the rig's truth: 775/763 µm, 33.3/-11.3 µm (Table 4: origin shifted by the reassembly)
    rows = comp[(comp["row"] > 0) & (comp["table"] != 2)]
    truth = {"v0_um": 33.3, "w0_um": -11.3, "g_v0_um": 775.0, "g_w0_um": 763.0}
    shift = {"v0_um": paper.TABLE4_SHIFT[0] * 1e6, "w0_um": paper.TABLE4_SHIFT[1] * 1e6}
    for r in rows.itertuples():
        t = truth[r.quantity] + (shift.get(r.quantity, 0.0) if r.table == 4 else 0.0)
        # + 2 µm: Eq. 7 is nonlinear in the currents, its 10-iteration mean of the gap is biased by about
        # +1.4 µm at 0.6 mA (reports/benchmarks/closed_form_scatter.md: rig mean 776.4 for a true 775)
        assert abs(r.rig_run - t) < 6 * r.rig_sd + 2.0, (r.label, r.quantity, r.rig_run, t)
        assert abs(r.ls - t) < 6 * r.ls_std, (r.label, r.quantity, r.ls, t)


def test_spread_is_the_between_row_sd_of_each_replicate(rep):
    sp = rep.spread().set_index(["table", "quantity"])
    idx = [j for j, r in enumerate(rep.rows) if r.table == 3]
    q = paper.QUANTITIES.index("g_v0_um")
    by_hand = [np.std([np.mean(rep.replicates[k, j, :, q]) for j in idx], ddof=1)
               for k in range(rep.replicates.shape[0])]
    assert sp.loc[(3, "g_v0_um"), "rig_median"] == pytest.approx(np.median(by_hand))
    assert sp.loc[(3, "g_v0_um"), "rig_hi"] == pytest.approx(np.quantile(by_hand, 0.95))


def test_noise_calibrated_on_table2_matches_its_scatter(rep):
    sp = rep.spread().set_index(["table", "quantity"])
    for q in ("g_v0_um", "g_w0_um"):
        # 0.6 mA was chosen so that Eq. 7's per-iteration gap scatter is the paper's (36.5 / 44.3 µm)
        assert 1 / 1.6 < sp.loc[(2, q), "ratio"] < 1.6
    assert set(sp["role"]) == {"calibration", "prediction"}


def test_published_gap_names_the_candidates_with_magnitudes():
    pg = {e["parameter"]: e for e in paper_gap.published_gap()}
    avgs = pd.concat([paper.load_table(t, averages=True) for t in (1, 3, 4)])
    diff_v = avgs["g_v0_um"].mean() - 762.0
    # 13 µm (1.7 %) is many standard errors from the drawn number, yet inside a sound bearing's machining and
    # iron-reluctance band (±2 %): an effective value to explain, not a flag
    assert pg["g_v0_um"]["differs"] and not pg["g_v0_um"]["flagged"] and not pg["g_w0_um"]["differs"]
    assert pg["g_v0_um"]["difference"] == pytest.approx(diff_v)
    could = {c["effect"]: c for c in pg["g_v0_um"]["could_be"]}
    mu = 0.080 / (2 * diff_v * 1e-6)
    assert f"{mu:.0f}" in could["iron_reluctance"]["needs"]
    assert could["position_gain"]["plausible"] is False   # 1.6 % against a 0.25 % micrometer calibration


def test_design_stays_within_the_back_up_bearing(tmp_path):
    from ambfit.data import read_csv
    from ambfit.estimation import design

    # the distance is the rotor's from the bearing centre: the set-point plus the estimated origin
    rec = design.recommend(read_csv(ROOT / "data" / "paper_table2.csv"), n_steps=4, max_radius_um=50.0)
    centre = rec.centre_um
    assert (np.hypot(rec.steps["v_set_um"] - centre[0], rec.steps["w_set_um"] - centre[1]) <= 50.0).all()
    assert centre == pytest.approx((-33.3, 11.3), abs=1.0)


def test_table2_trend_is_the_least_squares_slope(rep):
    tr = rep.trend().set_index("quantity")
    for q in ("v0_um", "w0_um"):
        y = paper.load_table(2)[q].to_numpy(float)[1:]
        assert tr.loc[q, "paper_slope"] == pytest.approx(np.polyfit(np.arange(len(y)), y, 1)[0])
        assert tr.loc[q, "paper_se"] > 0 and tr.loc[q, "rig_lo"] < tr.loc[q, "rig_hi"]


def test_noise_calibration_from_table2(rep):
    cal = rep.noise_calibration()
    lo, hi = cal["interval_mA"]
    assert lo < cal["calibrated_current_noise_mA"] < hi
    # the rig's default level is one Table 2 supports
    assert cal["rig_level_inside"], cal


def test_eq7_gap_scatter_is_proportional_to_current_noise():
    # noise_calibration rescales the current noise by the ratio of scatters: check the proportionality
    from ambfit import rig
    from ambfit.estimation import closed_form

    proto = protocol.paper_table2(iterations=10, center=(-33.3e-6, 11.3e-6))

    def scatter(sigma_i):
        g = []
        for seed in range(20):
            res = closed_form.identify(rig.simulate(rig.PAPER_RIG, proto, noise=rig.Noise(sigma_i, 0.1e-6),
                                                    seed=seed).data)
            g += [s.g0 for s in res.estimates[("all", "v")].iterations.values()]
        return np.std(g, ddof=1)

    # 200 iterations each: the ratio of two sds has a relative standard error of about 7 %
    assert scatter(1.2e-3) / scatter(0.6e-3) == pytest.approx(2.0, rel=0.2)
