"""No wrong answer leaves with exit 0: the probes of the robustness issue, outliers, plausibility, corruption.

Every probe starts from the bundled default data (``data/paper_table2.csv``, the paper's Table 2 protocol on
the virtual rig) and damages it the way a real file gets damaged.  Each must end in exit 2 (input) or 3
(fit) with a message naming the likely cause, or in exit 0 with the damage named and the answer right.
"""

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import given
from hypothesis import strategies as st
from typer.testing import CliRunner

from ambfit.estimation import closed_form, plausibility, robust
from ambfit.faces.cli import app
from ambfit.physics.bearing import PAPER_BEARING

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT / "data" / "paper_table2.csv"
runner = CliRunner()


@pytest.fixture(scope="module")
def clean():
    return pd.read_csv(DEFAULT)


def run(tmp_path, frame: pd.DataFrame, *args):
    path = tmp_path / "probe.csv"
    frame.to_csv(path, index=False)
    out = tmp_path / "probe.json"
    r = runner.invoke(app, ["identify", str(path), "--json", str(out), *args])
    return r, (json.loads(out.read_text()) if out.exists() else None)


def _flip_load(d):
    d["load_N"] = -d["load_N"]


def _milliamps(d):
    for c in ("bias_A", "i_top_A", "i_bottom_A", "i_top_std_A", "i_bottom_std_A"):
        d[c] = d[c] * 1e3


def _metres(d):
    for c in ("v_um", "w_um", "v_set_um", "w_set_um"):
        d[c] = d[c] * 1e-6


def _huge_load(d):
    d.loc[6, "load_N"] = -1e6
    d.loc[6, "load_id"] = "hung"


def _zero_currents(d):
    d.loc[3, ["i_top_A", "i_bottom_A"]] = 0.0


def _huge_current(d):
    d.loc[3, "i_top_A"] = 1e300


PROBES = [
    # (name, damage, extra args, exit code, words the message must contain)
    ("load sign flipped", _flip_load, (), 3, "sign of load_N is flipped"),
    ("load sign flipped, closed form", _flip_load, ("--method", "closed-form"), 3, "sign of load_N is flipped"),
    ("currents in mA", _milliamps, (), 3, "mA instead of A"),
    ("positions in metres", _metres, (), 3, "metres"),
    ("one load of -1e6 N", _huge_load, (), 3, "typing error in load_N"),
    ("both currents 0", _zero_currents, (), 2, "both coil currents are 0"),
    ("a current of 1e300", _huge_current, (), 2, "not a coil current"),
]


@pytest.mark.parametrize("name,damage,args,code,words", PROBES, ids=[p[0] for p in PROBES])
def test_probe_exits_with_the_cause(tmp_path, clean, name, damage, args, code, words):
    d = clean.copy()
    damage(d)
    r, _ = run(tmp_path, d, *args)
    assert r.exit_code == code, r.output
    assert words in r.output
    assert "Traceback" not in r.output


def test_accept_implausible_reports_and_exits_0(tmp_path, clean):
    d = clean.copy()
    _flip_load(d)
    r, js = run(tmp_path, d, "--accept-implausible")
    assert r.exit_code == 0, r.output
    assert js["params"]["k_v_Nm2_per_A2"]["value"] < 0 and js["implausible"]


def test_one_mistyped_position_is_named_and_left_out(tmp_path, clean, clean_fit):
    d = clean.copy()
    d.loc[4, "v_um"] = 0.0          # read -19.92 µm, typed 0
    r, js = run(tmp_path, d)
    assert r.exit_code == 0, r.output
    assert "row 5" in r.output and "left out" in r.output
    (out,) = js["outliers"]
    assert out["row"] == 5 and abs(out["t"]) > 10
    # the value that would make the row fit is the one that was read (within the position noise of a few µm)
    assert out["fits_with"]["v_um"] == pytest.approx(clean.loc[4, "v_um"], abs=2.0)
    g, ref = js["params"]["g_v0_um"], clean_fit["params"]["g_v0_um"]
    assert abs(g["value"] - ref["value"]) < ref["std"]                   # plain least squares: 17 σ off
    assert abs(js["outlier_shift_sigma"]["v0"]) > 10


def test_loss_linear_keeps_the_outlier_but_names_it(tmp_path, clean, clean_fit):
    d = clean.copy()
    d.loc[4, "v_um"] = 0.0
    r, js = run(tmp_path, d, "--loss", "linear")
    assert r.exit_code == 0 and "kept in the fit" in r.output
    assert abs(js["params"]["v0_um"]["value"] - clean_fit["params"]["v0_um"]["value"]) > 5 * clean_fit["params"]["v0_um"]["std"]


@pytest.mark.parametrize("loss", ["huber", "cauchy"])
def test_robust_losses_resist_the_outlier(tmp_path, clean, clean_fit, loss):
    d = clean.copy()
    d.loc[4, "v_um"] = 0.0
    r, js = run(tmp_path, d, "--loss", loss)
    assert r.exit_code == 0, r.output
    ref = clean_fit["params"]["v0_um"]
    assert abs(js["params"]["v0_um"]["value"] - ref["value"]) < 2 * ref["std"]


def test_clean_data_have_no_outliers(clean_fit):
    assert clean_fit["outliers"] == [] and clean_fit["implausible"] == [] and clean_fit["loss"] == "auto"


def test_duplicates_are_counted_once_and_named(tmp_path, clean, clean_fit):
    d = pd.concat([clean, clean]).sort_index(kind="stable").reset_index(drop=True)
    r, js = run(tmp_path, d)
    assert r.exit_code == 0 and "80 duplicate reading(s) counted once" in r.output
    assert js["params"]["g_v0_um"]["std"] == pytest.approx(clean_fit["params"]["g_v0_um"]["std"], rel=1e-6)
    assert js["duplicates_dropped"][:2] == [2, 4]
    r, js = run(tmp_path, d, "--keep-duplicates")
    ratio = clean_fit["params"]["g_v0_um"]["std"] / js["params"]["g_v0_um"]["std"]
    assert ratio == pytest.approx(math.sqrt(2), rel=0.02) and "kept" in r.output


def test_check_lists_duplicates(tmp_path, clean):
    path = tmp_path / "dup.csv"
    pd.concat([clean.iloc[:8], clean.iloc[[7]], clean.iloc[8:]]).to_csv(path, index=False)
    r = runner.invoke(app, ["check", str(path)])
    assert r.exit_code == 0 and "row 9 repeats row 8" in r.output


def test_noisy_closed_form_is_not_trusted(tmp_path):
    from ambfit.rig import protocol
    from ambfit.rig import virtual as rig

    sim = rig.simulate(rig.PAPER_RIG, protocol.paper_table2(center=(-33.3e-6, 11.3e-6)), seed=0,
                       noise=rig.Noise(current=0.06, position=10e-6))       # 100 x the paper's noise
    r, _ = run(tmp_path, sim.data, "--method", "closed-form")
    assert r.exit_code == 3 and "ill conditioned" in r.output


def test_closed_form_health_flags_scatter_beyond_the_noise():
    from ambfit.rig import protocol
    from ambfit.rig import virtual as rig

    sim = rig.simulate(rig.PAPER_RIG, protocol.paper_table2(center=(-33.3e-6, 11.3e-6)), seed=3)
    res = closed_form.identify(sim.data)
    assert res.trusted, res.health()
    est = res.estimates[("all", "v")]
    # the predicted scatter explains the observed one (0.6 mA noise: about 35 µm per iteration, the paper's)
    assert 0.5 < est.g0_std / est.g0_std_predicted < 2.0
    df = sim.data.copy()
    df["i_top_std_A"] = df["i_bottom_std_A"] = 0.6e-4         # std columns claiming 10 x less noise
    res = closed_form.identify(df)
    assert not res.trusted and any("scatter" in h for h in res.health())


def test_plausibility_names_the_cause():
    k = PAPER_BEARING.force_constant()
    flags = plausibility.check_result({"k_v": k * 1e-6, "g_v0": 0.4 * PAPER_BEARING.nominal_gap}, PAPER_BEARING)
    assert [f.quantity for f in flags] == ["k_v", "g_v0 [µm]"]
    assert "mA" in flags[0].cause
    assert plausibility.check_result({"k_v": k, "g_v0": PAPER_BEARING.nominal_gap, "v0": 33e-6}, PAPER_BEARING) == []
    # loads typed in mN are 1000 x larger numbers, so k comes out 1000 x larger; kN the other way
    assert "mN" in plausibility.check_result({"k_w": k * 1e3}, PAPER_BEARING)[0].cause
    assert "kN" in plausibility.check_result({"k_w": k * 1e-3}, PAPER_BEARING)[0].cause


def test_outlier_bound_and_false_alarms():
    # Bonferroni: P(max |t| > bound) <= alpha for n independent N(0, 1); checked on 4000 simulated files
    rng = np.random.default_rng(0)
    n = 80
    bound = robust.threshold(n)
    alarms = np.mean(np.max(np.abs(rng.standard_normal((4000, n))), axis=1) > bound)
    assert bound == pytest.approx(3.84, abs=0.01)
    assert alarms <= 0.01 + 3 * math.sqrt(0.01 / 4000)


def test_fits_with_inverts_the_force_law():
    g0, x0, k, c = 775e-6, 33e-6, 3.46e-6, PAPER_BEARING.cos_alpha
    it, ib, x = 1.6, 1.2, -20e-6
    load = k * (it**2 / (g0 - (x0 + x) * c) ** 2 - ib**2 / (g0 + (x0 + x) * c) ** 2)
    alt = robust.fits_with(it * 1.05, ib, x, load, g0, x0, k, c)
    assert alt["i_top_A"] == pytest.approx(it, rel=1e-9)
    alt = robust.fits_with(it, ib, 0.0, load, g0, x0, k, c)
    assert alt["x_um"] == pytest.approx(-20.0, abs=1e-6)


# --- random corruption: exit 2 or 3, or an answer within the error bars, or a warning; never a traceback ---------

COLUMNS = ["bias_A", "i_top_A", "i_bottom_A", "v_um", "w_um", "load_N"]
BAD_CELLS = ["", "abc", "nan", "inf", "-1", "0", "1e300", "-1e6", "1,5", "   ", "\x00"]


@st.composite
def corruptions(draw):
    kind = draw(st.sampled_from(["cell", "scale", "swap", "drop_column", "duplicate", "truncate", "bytes"]))
    row = draw(st.integers(0, 79))
    col = draw(st.sampled_from(COLUMNS))
    return kind, row, col, draw(st.sampled_from(BAD_CELLS)), draw(st.sampled_from([1e-3, 1e-6, 10.0, 1e3, -1.0]))


def _corrupt(text: str, corruption) -> str:
    kind, row, col, cell, factor = corruption
    lines = text.splitlines()
    header = lines[0].split(",")
    j = header.index(col)
    fields = lines[row + 1].split(",")
    if kind == "cell":
        fields[j] = cell
    elif kind == "scale":
        fields[j] = repr(float(fields[j]) * factor)
    elif kind == "swap":
        k = header.index("i_bottom_A" if col != "i_bottom_A" else "i_top_A")
        fields[j], fields[k] = fields[k], fields[j]
    elif kind == "drop_column":
        lines = [",".join(f for i, f in enumerate(line.split(",")) if i != j) for line in lines]
        return "\n".join(lines) + "\n"
    elif kind == "duplicate":
        lines.insert(row + 1, lines[row + 1])
        return "\n".join(lines) + "\n"
    elif kind == "truncate":
        return "\n".join(lines[: row + 1] + [lines[row + 1][: len(lines[row + 1]) // 2]]) + "\n"
    elif kind == "bytes":
        return "\n".join(lines[: row + 1]) + "\n\udcff\udcfe" + "\n".join(lines[row + 1:]) + "\n"
    lines[row + 1] = ",".join(fields)
    return "\n".join(lines) + "\n"


@given(corruptions())
def test_random_corruption_never_silently_changes_the_answer(tmp_path_factory, clean_fit, corruption):
    tmp = tmp_path_factory.mktemp("corrupt")
    path, out = tmp / "c.csv", tmp / "c.json"
    path.write_bytes(_corrupt(DEFAULT.read_text(), corruption).encode("utf-8", "surrogateescape"))
    r = runner.invoke(app, ["identify", str(path), "--json", str(out)])
    assert r.exception is None or isinstance(r.exception, SystemExit), repr(r.exception)
    assert r.exit_code in (0, 2, 3), r.output
    if r.exit_code != 0:
        assert "error:" in r.output
        return
    js = json.loads(out.read_text())
    warned = "warning:" in r.output
    for key, ref in clean_fit["params"].items():
        if key in js["params"]:
            # "larger than the error bars": 2 sigma of the reported result or of the clean one, whichever is
            # larger (a file cut short has fewer readings and honestly wider bars)
            new = js["params"][key]
            moved = abs(new["value"] - ref["value"]) > 2 * max(ref["std"], new["std"])
            assert not moved or warned, (key, new, ref, r.output)


def test_a_corrupted_compilation_cache_entry_is_replaced(tmp_path):
    import os
    import subprocess
    import sys

    env = {**os.environ, "AMBFIT_JAX_CACHE": str(tmp_path / "cache")}
    cmd = [sys.executable, "-m", "ambfit", "identify", str(DEFAULT)]
    subprocess.run(cmd, env=env, capture_output=True, check=True)
    entries = sorted((tmp_path / "cache").glob("*-cache"))
    assert entries
    for e in entries:
        e.write_bytes(b"garbage")            # a crash while writing, a full disk
    # the next run neither warns nor leaves a corrupt entry behind (so no later run can warn either)
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    assert "Error reading persistent compilation cache" not in r.stderr
    assert not any(e.read_bytes() == b"garbage" for e in (tmp_path / "cache").glob("*-cache"))


def test_an_output_into_a_read_only_folder_fails_before_any_work(tmp_path, monkeypatch):
    import os

    ro = tmp_path / "ro"
    ro.mkdir()
    real = os.access
    # (tests may run as root, for whom every folder is writable: the permission answer is what is under test)
    monkeypatch.setattr(os, "access", lambda p, mode: False if Path(p) == ro and mode == os.W_OK else real(p, mode))
    calls = []
    monkeypatch.setattr("ambfit.estimation.bayes.sample", lambda *a, **k: calls.append(1))
    r = runner.invoke(app, ["sample", str(DEFAULT), "--out", str(ro / "x.nc")])
    assert r.exit_code == 2 and f"the folder {ro} is not writable" in r.output and not calls


def test_a_fit_with_effects_still_names_the_outliers_it_inherits(clean):
    import ambfit
    from ambfit.physics.effects import CurrentGain

    d = clean.copy()
    d.loc[4, "v_um"] = 0.0
    res = ambfit.fit(d, [CurrentGain()], throw=False)
    checks = {name: ok for name, ok, _ in res.checks()}
    assert [o.row for o in res.outliers] == [5] and checks["no_outliers"] is False     # named, and it says so


def test_robust_losses_judge_the_fit_by_the_weighted_chi2(clean):
    import ambfit

    d = clean.copy()
    d.loc[4, "v_um"] = 0.0
    # χ² is Σ w z²: the down-weighted reading no longer makes the model look inadequate (unweighted: χ²/dof 78).
    cauchy = ambfit.fit(d, loss="cauchy")
    assert cauchy.reduced_chi2 < 1.5 and cauchy.adequate
    # Huber's weight c/|z| still lets a 70 σ reading add c|z| ≈ 100 to χ² (its loss grows linearly): far below
    # the unweighted 5800, not on the floor
    huber = ambfit.fit(d, loss="huber")
    assert 1.0 < huber.reduced_chi2 < 5.0
