"""Command line: simulate -> identify round trip, contract JSON, clear errors, help with units."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from ambfit.faces.cli import app

runner = CliRunner()
ROOT = Path(__file__).resolve().parents[1]


def test_simulate_identify_round_trip(tmp_path):
    csv, truth, out = tmp_path / "d.csv", tmp_path / "t.json", tmp_path / "o.json"
    r = runner.invoke(app, ["simulate", "-o", str(csv), "--preset", "perturbation", "--iterations", "3",
                            "--current-noise-ma", "0", "--position-noise-um", "0", "--gap-um", "800,790",
                            "--origin-um", "-20,15", "--truth", str(truth)])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["identify", str(csv), "--method", "closed-form", "--json", str(out)])
    assert r.exit_code == 0, r.output
    js = json.loads(out.read_text())
    assert js["method"] == "closed_form" and js["converged"] is True and js["n_rows"] == 24
    p = js["params"]
    assert p["g_v0_um"]["value"] == pytest.approx(800.0, rel=1e-6)
    assert p["w0_um"]["value"] == pytest.approx(15.0, abs=1e-4)
    assert json.loads(truth.read_text())["params"]["0"]["g_w0_um"] == pytest.approx(790.0)
    assert "gap [µm]" in r.output


def test_simulate_with_effects_and_toml(tmp_path):
    toml = tmp_path / "p.toml"
    toml.write_text('[loads.heavy]\nmass_kg = 2.0\n\n[[block]]\nkind = "perturbation"\nbiases_A = [1.2, 1.5]\n'
                    'offsets_um = [30]\niterations = 2\nload = "heavy"\nexperiment = "toml"\n\n'
                    '[[effect]]\nname = "current_offset"\ntop = 0.01\nbottom = 0.0\n')
    csv = tmp_path / "d.csv"
    # ±30 µm about the sensor origin puts the rotor 66.0 µm (hypot(63.3, 18.7)) from the centre of the default rig (true origin
    # (33.3, -11.3) µm): beyond the 60 µm back-up clearance, refused unless asked for
    r = runner.invoke(app, ["simulate", "-o", str(csv), "--protocol", str(toml)])
    assert r.exit_code == 2 and not csv.exists(), r.output
    assert "step 1 " in r.output and "(30.0, 30.0) µm" in r.output and "66.0 µm from the bearing centre" in r.output
    assert "back-up clearance of 60.0 µm" in r.output and "4 of 8 steps" in r.output
    r = runner.invoke(app, ["simulate", "-o", str(csv), "--protocol", str(toml), "--allow-beyond-limits"])
    assert r.exit_code == 0 and "warning" in r.output and csv.exists(), r.output
    toml.write_text(toml.read_text().replace('experiment = "toml"', 'experiment = "toml"\ncenter_um = [-33.3, 11.3]'))
    r = runner.invoke(app, ["simulate", "-o", str(csv), "--protocol", str(toml),
                            "--effect", "saturation:b_sat=1.1", "--effect", "hysteresis"])
    assert r.exit_code == 0 and "warning" not in r.output, r.output
    r = runner.invoke(app, ["identify", str(csv), "--by", "experiment"])
    assert r.exit_code == 0 and "toml" in r.output
    r = runner.invoke(app, ["simulate", "-o", str(csv), "--protocol", str(toml),
                            "--current-noise-ma", "0", "--position-noise-um", "0"])
    ref = tmp_path / "ref.csv"
    toml.write_text(toml.read_text().replace("top = 0.01", "top = 0.0"))
    runner.invoke(app, ["simulate", "-o", str(ref), "--protocol", str(toml), "--current-noise-ma", "0",
                        "--position-noise-um", "0"])
    import pandas as pd
    diff = pd.read_csv(csv).i_top_A - pd.read_csv(ref).i_top_A
    assert diff.to_numpy() == pytest.approx(0.01, abs=1e-12)   # the [[effect]] table was applied


def test_bad_effect_and_bad_data_give_clear_errors(tmp_path):
    r = runner.invoke(app, ["simulate", "-o", str(tmp_path / "x.csv"), "--effect", "gremlins"])
    assert r.exit_code == 2 and "unknown effect 'gremlins'" in r.output and "Traceback" not in r.output
    bad = tmp_path / "bad.csv"
    bad.write_text("axis,bias_A,i_top_A,i_bottom_A,v_um,w_um\nv,1.4,1.5,1.3,20,20\nq,1.4,1.5,1.3,20,20\n")
    r = runner.invoke(app, ["identify", str(bad)])
    assert r.exit_code == 2
    assert "bad.csv" in r.output and "row 2" in r.output and "'axis'" in r.output and "'q'" in r.output


def test_unidentifiable_design_exits_non_zero(tmp_path):
    one = tmp_path / "one.csv"
    one.write_text("axis,bias_A,i_top_A,i_bottom_A,v_um,w_um\nv,1.4,1.52,1.27,20,20\nv,1.6,1.68,1.51,20,20\n")
    r = runner.invoke(app, ["identify", str(one), "--method", "closed-form"])
    assert r.exit_code == 3 and "two positions" in r.output
    r = runner.invoke(app, ["identify", str(one)])
    assert r.exit_code == 3 and "does not identify" in r.output and "Traceback" not in r.output


def test_least_squares_is_the_default_and_writes_contract_json(tmp_path):
    out = tmp_path / "o.json"
    r = runner.invoke(app, ["identify", str(ROOT / "data" / "paper_table2.csv"), "--json", str(out)])
    assert r.exit_code == 0, r.output
    js = json.loads(out.read_text())
    assert js["method"] == "least_squares" and js["converged"] is True and js["n_rows"] == 80
    for key in ("g_v0_um", "v0_um", "g_w0_um", "w0_um", "k_v_Nm2_per_A2", "k_w_Nm2_per_A2"):
        assert set(js["params"][key]) >= {"value", "std"}
    truth = json.loads((ROOT / "data" / "paper_table2.truth.json").read_text())["params"]["0"]
    for key in ("g_v0_um", "v0_um", "g_w0_um", "w0_um", "k_v_Nm2_per_A2"):
        assert abs(js["params"][key]["value"] - truth[key]) < 4 * js["params"][key]["std"], key
    assert "χ²/dof" in r.output


def test_least_squares_without_known_loads_does_not_report_k(tmp_path):
    import pandas as pd
    df = pd.read_csv(ROOT / "data" / "paper_table2.csv")
    df["load_N"] = float("nan")
    csv, out = tmp_path / "u.csv", tmp_path / "u.json"
    df.to_csv(csv, index=False)
    r = runner.invoke(app, ["identify", str(csv), "--json", str(out)])
    assert r.exit_code == 0 and "k_v not identified" in r.output
    assert "k_v_Nm2_per_A2" not in json.loads(out.read_text())["params"]
    r = runner.invoke(app, ["identify", str(csv), "--require-k"])
    assert r.exit_code == 3 and "k is not identifiable" in r.output


def test_by_experiment_table(tmp_path):
    csv = tmp_path / "t1.csv"
    r = runner.invoke(app, ["simulate", "-o", str(csv), "--protocol", str(_table1_toml(tmp_path))])
    assert r.exit_code == 0, r.output
    out = tmp_path / "t1.json"
    r = runner.invoke(app, ["identify", str(csv), "--by", "experiment", "--json", str(out)])
    assert r.exit_code == 0, r.output
    js = json.loads(out.read_text())
    # one entry per experiment, no pooled fit unless asked for (--pooled)
    assert [g["group"] for g in js["groups"]] == ["1", "2"] and "pooled" not in js and "params" not in js
    assert all(g["converged"] and g["status"] == "ok" and g["by"] == "experiment" for g in js["groups"])


def _table1_toml(tmp_path):
    p = tmp_path / "t1.toml"
    p.write_text('[[block]]\nkind = "perturbation"\nbiases_A = [1.4, 1.5]\niterations = 3\nexperiment = "1"\n'
                 'center_um = [-33.3, 11.3]\n\n[[block]]\nkind = "perturbation"\nbiases_A = [1.4, 1.6]\n'
                 'iterations = 3\nexperiment = "2"\ncenter_um = [-33.3, 11.3]\n')
    return p


@pytest.mark.parametrize("cmd, unit", [("simulate", "[mA]"), ("identify", "[µm]"), ("origin-search", "[µm]")])
def test_help_explains_units(cmd, unit):
    r = runner.invoke(app, [cmd, "--help"], env={"COLUMNS": "200"})
    assert r.exit_code == 0 and unit in r.output


def test_origin_search_command(tmp_path):
    out, js = tmp_path / "s.csv", tmp_path / "s.json"
    r = runner.invoke(app, ["origin-search", "--iterations", "3", "--current-noise-ma", "0",
                            "--position-noise-um", "0", "-o", str(out), "--json", str(js)])
    assert r.exit_code == 0, r.output
    traj = json.loads(js.read_text())
    assert traj["converged"] and traj["iterations"][1]["v_center_um"] == pytest.approx(-33.3)


def test_installed_entry_point_identifies_the_default_data(tmp_path):
    exe = Path(sys.executable).with_name("ambfit")
    out = tmp_path / "o.json"
    r = subprocess.run([str(exe), "identify", str(ROOT / "data" / "paper_table2.csv"), "--method", "closed-form",
                        "--json", str(out)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    js = json.loads(out.read_text())
    for key in ("g_v0_um", "v0_um", "g_w0_um", "w0_um"):
        assert set(js["params"][key]) >= {"value", "std"}
    # 10 iterations with ~35 µm scatter: the mean lies within 4 standard errors of the truth
    assert abs(js["params"]["g_v0_um"]["value"] - 775.0) < 4 * js["params"]["g_v0_um"]["std"]
    assert abs(js["params"]["v0_um"]["value"] - 33.3) < 4 * js["params"]["v0_um"]["std"]


@pytest.mark.parametrize("how", ["script", "module"])
def test_the_command_ends_with_its_exit_code_and_its_output_written(tmp_path, how):
    # the installed script and python -m ambfit end the process at once (no interpreter teardown): the exit code,
    # the messages, the tables and the files must all be there
    start = [str(Path(sys.executable).with_name("ambfit"))] if how == "script" else [sys.executable, "-m", "ambfit"]
    missing = subprocess.run([*start, "identify", str(tmp_path / "none.csv")], capture_output=True, text=True,
                             timeout=120)
    assert missing.returncode == 2 and "none.csv" in missing.stderr and "Traceback" not in missing.stderr
    out = tmp_path / "o.json"
    done = subprocess.run([*start, "identify", str(ROOT / "data" / "paper_table2.csv"), "--json", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "least squares, paper_table2.csv" in done.stdout and "uncertainty" in done.stdout
    assert set(json.loads(out.read_text())["params"]) >= {"g_v0_um", "v0_um", "g_w0_um", "w0_um"}


def test_a_profiler_and_a_closed_output_still_get_a_normal_end(tmp_path):
    # the quick end gives way to Python's own where something runs after it (a profiler writes its statistics),
    # and a command whose standard output is closed still ends as it went
    data = str(ROOT / "data" / "paper_table2.csv")
    stats = tmp_path / "p.prof"
    r = subprocess.run([sys.executable, "-m", "cProfile", "-o", str(stats), "-m", "ambfit", "identify", data,
                        "--method", "closed-form"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and stats.exists(), r.stderr
    exe = Path(sys.executable).with_name("ambfit")
    out = tmp_path / "o.json"
    r = subprocess.run(["bash", "-c", f"'{exe}' identify '{data}' --method closed-form --json '{out}' >&-"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and "Traceback" not in r.stderr and out.exists(), r.stderr


def test_origin_search_failure_is_a_message_not_a_traceback():
    # biases too close for the noise: Eq. 6's radicand goes negative at some iteration
    r = runner.invoke(app, ["origin-search", "--biases-a", "1.4,1.401", "--current-noise-ma", "5", "--iterations", "5"])
    assert r.exit_code == 2 and "origin search iteration" in r.output and "Traceback" not in r.output


def test_check_lists_every_problem_at_once(tmp_path):
    # three planted errors in one file: an unknown axis, text in a current, a negative current
    bad = tmp_path / "bad.csv"
    bad.write_text("axis,bias_A,i_top_A,i_bottom_A,v_um,w_um\n"
                   "v,1.4,1.6,1.2,20,0\nq,1.4,1.6,1.2,20,0\nv,1.4,abc,1.2,20,0\nw,1.4,1.6,-1.2,20,0\n")
    r = CliRunner().invoke(app, ["check", str(bad)])
    assert r.exit_code == 2, r.output
    assert "3 problem(s)" in r.output
    for text in ("'q'", "'abc'", "-1.2", "unknown axis", "not a finite number", "negative current"):
        assert text in r.output, text
    assert "np.float64" not in r.output and "Traceback" not in r.output


def test_check_passes_a_good_file_and_names_duplicates(tmp_path):
    good = tmp_path / "good.csv"
    good.write_text("axis,bias_A,i_top_A,i_bottom_A,v_um,w_um\n"
                    "v,1.4,1.6,1.2,20,0\nv,1.6,1.8,1.4,-20,0\nv,1.4,1.6,1.2,20,0\n")
    r = CliRunner().invoke(app, ["check", str(good)])
    assert r.exit_code == 0, r.output
    assert "row 3 repeats row 1" in r.output and "1 duplicate reading(s)" in r.output


def test_design_stays_inside_the_bearings_clearance_and_current_limit(tmp_path):
    # a bearing with a 30 µm back-up clearance and a 1.5 A coil limit: no recommended set-point puts the rotor
    # beyond 30 µm from the bearing centre (the estimated one, at the sensor reading (-v0, -w0)), no bias or
    # predicted coil current exceeds 1.5 A
    bearing = tmp_path / "b.toml"
    bearing.write_text("backup_clearance_um = 30.0\nmax_current_A = 1.5\n")
    js = tmp_path / "rec.json"
    args = ["design", str(ROOT / "data" / "paper_table2.csv"), "--steps", "4", "--bearing", str(bearing), "--json",
            str(js)]
    r = CliRunner().invoke(app, args)
    # the data's coil currents reach 1.85 A, beyond 1.2 x this bearing's limit: implausible unless accepted
    assert r.exit_code == 3 and "coil limit 1.5 A" in r.output, r.output
    r = CliRunner().invoke(app, [*args, "--accept-implausible"])
    assert r.exit_code == 0, r.output
    steps = json.loads(js.read_text())["steps"]
    assert len(steps) == 4
    for s in steps:   # the data's origin is (33.3, -11.3) µm to well under a µm
        assert ((s["v_set_um"] + 33.3) ** 2 + (s["w_set_um"] - 11.3) ** 2) ** 0.5 <= 30.0 and s["bias_A"] < 1.5, s


def test_simulate_presets_stay_inside_the_bearings_limits(tmp_path):
    # the presets are centred on the rig's effective origin (the paper's Table 2 ran after the origin search)
    for preset in ("table2", "rich"):
        r = runner.invoke(app, ["simulate", "-o", str(tmp_path / f"{preset}.csv"), "--preset", preset])
        assert r.exit_code == 0, r.output
    import pandas as pd

    df = pd.read_csv(tmp_path / "rich.csv")
    physical = np.hypot(df["v_set_um"] + 33.3, df["w_set_um"] - 11.3)
    assert physical.max() <= 60.0 and physical.max() > 50.0
    assert np.allclose([df["v_set_um"].mean(), df["w_set_um"].mean()], [-33.3, 11.3], atol=1e-9)
    # the rich sweep about the sensor origin reaches 73.3 µm from the centre: refused, the step named
    r = runner.invoke(app, ["simulate", "-o", str(tmp_path / "x.csv"), "--preset", "rich", "--center-um", "0,0"],
                      env={"COLUMNS": "400"})
    assert r.exit_code == 2 and not (tmp_path / "x.csv").exists()
    assert "beyond the back-up clearance of 60.0 µm" in r.output and "--allow-beyond-limits" in r.output
    # a bearing with a 1.5 A coil limit refuses the 1.6 A biases of the Table 2 preset
    bearing = tmp_path / "b.toml"
    bearing.write_text("max_current_A = 1.5\n")
    r = runner.invoke(app, ["simulate", "-o", str(tmp_path / "y.csv"), "--bearing", str(bearing)],
                      env={"COLUMNS": "400"})
    assert r.exit_code == 2 and "bias of axis v 1.6 A, beyond the coil current limit of 1.5 A" in r.output, r.output
