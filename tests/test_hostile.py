"""What a careful tester throws at the command line: each ends in one line naming the cause (exit 2, 3 for an
implausible answer, 130 for Ctrl-C), never a traceback, never damage outside the outputs asked for.

Most probes run the Typer app in this process; those that need a real process (an ASCII or a full standard
output, a bad JAX environment, Ctrl-C) run the installed ``ambfit`` entry point.
"""

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from ambfit import _output
from ambfit.faces import cli
from ambfit.faces.cli import app
from ambfit.faces.cli.app import plain_text

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT / "data" / "paper_table2.csv"
EXE = str(Path(sys.executable).with_name("ambfit"))
runner = CliRunner()


def _run(*args, env=None, **kw):
    return subprocess.run([EXE, *map(str, args)], capture_output=True, text=True, timeout=300,
                          env={**os.environ, **(env or {})}, **kw)


def _one_line_error(r, *words, code=2):
    assert r.exit_code == code, r.output
    assert "Traceback" not in r.output and "unexpected" not in r.output, r.output
    for w in words:
        assert w in r.output, r.output


# --- text a terminal cannot show ----------------------------------------------------------------------------------

def test_plain_spellings_by_hand():
    assert plain_text("g_v0 [µm] 774.5 ± 1.4, χ²/dof", "ascii") == "g_v0 [um] 774.5 +/- 1.4, chi^2/dof"
    assert plain_text("k [N·m²/A²]", "ascii") == "k [N*m^2/A^2]"
    assert plain_text("µm ± χ²", "latin-1") == "µm ± chi²"        # Latin-1 has µ, ± and ², not χ
    assert plain_text("β→ü", "ascii") == "beta->u"                # ü by its decomposition u + diaeresis
    assert plain_text("☃", "ascii") == "?"
    assert plain_text("plain", "ascii") == "plain"


def test_an_ascii_terminal_gets_um_not_a_crash():
    r = _run("identify", DEFAULT, env={"PYTHONIOENCODING": "ascii"})
    assert r.returncode == 0, r.stderr
    assert "g_v0 [um]" in r.stdout and "+/-" in r.stdout and "µ" not in r.stdout


def test_a_full_standard_output_ends_in_one_line(tmp_path):
    with open(os.devnull if not os.path.exists("/dev/full") else "/dev/full", "w") as full:
        r = subprocess.run([EXE, "identify", str(DEFAULT)], stdout=full, stderr=subprocess.PIPE, text=True,
                           timeout=300)
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full on this system")
    assert r.returncode == 2, r.stderr
    assert "cannot write the output" in r.stderr and "Traceback" not in r.stderr and "unexpected" not in r.stderr


def test_markup_like_names_are_printed_literally(tmp_path):
    missing = tmp_path / "run[um].csv"
    r = runner.invoke(app, ["identify", str(missing)])
    assert "run[um].csv" in r.output


# --- files that are not what they say -----------------------------------------------------------------------------

@pytest.mark.parametrize("text,words", [
    ("pole_angle_deg = 120\n", ["pole_angle_deg must lie between 0 and 90", "120"]),
    ("lamination = 1.5\n", ["lamination", "(0, 1]"]),
    ("current_gain_tolerance = -0.1\n", ["current_gain_tolerance", "[0, 1)"]),
    ("a = " + "[" * 3000 + "]" * 3000 + "\n", ["nest too deeply"]),
    ("nominal_gap_um = " + "9" * 5000 + "\n", ["digits"]),
    ("nominal_gap_um = " + "9" * 400 + "\n", ["nominal_gap_um", "beyond any physical value"]),
], ids=["pole-angle-120", "lamination", "tolerance", "nested", "5000-digits", "400-digits"])
def test_a_bearing_file_that_cannot_be_one_is_named(tmp_path, text, words):
    toml = tmp_path / "bearing.toml"
    toml.write_text(text)
    _one_line_error(runner.invoke(app, ["identify", str(DEFAULT), "--bearing", str(toml)]), "bearing.toml", *words)


def test_a_nested_protocol_file_is_named(tmp_path):
    toml = tmp_path / "protocol.toml"
    toml.write_text("a = " + "[" * 3000 + "]" * 3000 + "\n")
    _one_line_error(runner.invoke(app, ["simulate", "--protocol", str(toml), "-o", str(tmp_path / "x.csv")]),
                    "--protocol", "nest too deeply")


def test_model_files_a_reader_cannot_parse_are_named(tmp_path, clean_fit):
    digits = tmp_path / "digits.json"
    digits.write_text(json.dumps(clean_fit).replace('"pole_angle_deg": 22.5', '"pole_angle_deg": ' + "9" * 5000))
    _one_line_error(runner.invoke(app, ["force", str(digits), "--axis", "v", "--i-top", "1.5", "--i-bottom", "0.5"]),
                    "digits.json", "digits")
    groups = tmp_path / "groups.json"
    groups.write_text(json.dumps(clean_fit | {"groups": 3}))
    _one_line_error(runner.invoke(app, ["force", str(groups), "--axis", "v", "--i-top", "1.5", "--i-bottom", "0.5"]),
                    "groups = 3", "one fit per group")


# --- force judges what it is given as identify does ---------------------------------------------------------------

@pytest.mark.parametrize("i_top,words", [(1500.0, ["i_top_A", "mA instead of A"]),
                                         (30.0, ["i_top_A", "coil limit"])], ids=["mA", "30A"])
def test_force_refuses_currents_the_bearing_cannot_carry(clean_fit, tmp_path, i_top, words):
    path = tmp_path / "m.json"
    path.write_text(json.dumps(clean_fit))
    args = ["force", str(path), "--axis", "v", "--i-top", str(i_top), "--i-bottom", "0.5"]
    _one_line_error(runner.invoke(app, args), *words, code=3)
    assert runner.invoke(app, [*args, "--accept-implausible"]).exit_code == 0


def test_force_refuses_a_model_edited_to_five_times_the_force(clean_fit, tmp_path):
    edited = json.loads(json.dumps(clean_fit))
    state = edited["model_state"]
    at = [state["names"].index(n) for n in ("k_v", "k_w")]
    for i in at:
        state["values"][i] *= 5
        state["covariance"][i] = [c * 5 for c in state["covariance"][i]]
        for row in state["covariance"]:
            row[i] *= 5
    for key in ("k_v_Nm2_per_A2", "k_w_Nm2_per_A2"):
        edited["params"][key] = {k: 5 * v for k, v in edited["params"][key].items()}
    path = tmp_path / "k5.json"
    path.write_text(json.dumps(edited))
    _one_line_error(runner.invoke(app, ["force", str(path), "--axis", "v", "--i-top", "1.5", "--i-bottom", "0.5"]),
                    "k_v", "implausible", code=3)


# --- options that would size work or memory beyond the machine ----------------------------------------------------

@pytest.mark.parametrize("args,words", [
    (["--window", "1e-9"], ["windows", "at most 2,000"]),
    (["--window", "36000", "--step", "1"], ["windows", "at most 2,000"]),
    (["--window", "70000", "--step", "4000"], ["readings together", "at most 5,000"]),
], ids=["nano-window", "second-step", "overlap"])
def test_campaign_windows_are_bounded(tmp_path, monkeypatch, args, words):
    # the example campaign has 960 readings: its 2,000 windows could hold 1.9 million, under the real bound of
    # readings held together, so that bound is lowered here to reach it with 20 windows
    from ambfit.studies.campaign import window

    monkeypatch.setattr(window, "MAX_WINDOW_ROWS", 5_000)
    example = tmp_path / "campaign.csv"
    _one_line_error(runner.invoke(app, ["campaign", "--example", str(example), *args]), "time_s", *words)


def test_simulated_protocols_are_bounded(tmp_path):
    many = ",".join(f"{1 + 0.001 * i:.3f}" for i in range(200))
    out = str(tmp_path / "x.csv")
    _one_line_error(runner.invoke(app, ["simulate", "--preset", "perturbation", "--biases-a", many, "-o", out]),
                    "--biases-a: 200 values; at most 100")
    biases = ",".join(f"{1 + 0.005 * i:.3f}" for i in range(100))
    offsets = ",".join(f"{1 + 0.2 * i:.1f}" for i in range(100))
    r = runner.invoke(app, ["simulate", "--preset", "perturbation", "--biases-a", biases, "--offsets-um", offsets,
                            "--iterations", "100", "-o", out])
    _one_line_error(r, "2,000,000 steps", "at most 1,000,000")


def test_walkers_are_bounded():
    _one_line_error(runner.invoke(app, ["sample", str(DEFAULT), "--walkers", "20000"]), "--walkers 20000",
                    "at most 1024")


# --- what a crash or a kill leaves behind ---------------------------------------------------------------------------

def test_the_crash_log_never_follows_a_planted_link(tmp_path, monkeypatch):
    home = tmp_path / "home"
    (home / ".cache" / "ambfit").mkdir(parents=True)
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    (home / ".cache" / "ambfit" / "last-error.txt").symlink_to(victim)
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))         # the private file is left here, not in /tmp
    try:
        raise RuntimeError("a bug")
    except RuntimeError:
        where = cli._log_traceback()
    assert victim.read_text() == "precious"
    assert "RuntimeError: a bug" in Path(where).read_text() and Path(where).parent == tmp_path
    assert (Path(where).stat().st_mode & 0o077) == 0                  # a private file of its own


def test_the_crash_log_goes_to_a_private_file_when_the_cache_cannot_be_made(tmp_path, monkeypatch):
    home = tmp_path / "home"
    home.mkdir()
    (home / ".cache").write_text("a file where the folder should be")
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    try:
        raise ValueError("another bug")
    except ValueError:
        where = cli._log_traceback()
    assert "ValueError: another bug" in Path(where).read_text() and Path(where).name.startswith("ambfit-error-")
    os.unlink(where)


def test_temporary_files_of_a_killed_write_are_cleaned_by_the_next(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()                                       # a process number that no longer runs
    left = tmp_path / f".out.json.{dead.pid}.abcd1234.tmp"
    left.write_text("half")
    alive = tmp_path / f".out.json.{os.getppid()}.efgh5678.tmp"     # a running process's write: kept
    alive.write_text("being written")
    other = tmp_path / f".other.json.{dead.pid}.abcd1234.tmp"       # another output's: not this write's business
    other.write_text("half")
    _output.write_json(tmp_path / "out.json", {"a": 1})
    assert not left.exists() and alive.exists() and other.exists()
    assert json.loads((tmp_path / "out.json").read_text()) == {"a": 1}


def test_an_output_name_longer_than_the_file_system_allows_fails_before_work(tmp_path):
    r = runner.invoke(app, ["identify", str(DEFAULT), "--json", str(tmp_path / ("a" * 300 + ".json"))])
    _one_line_error(r, "cannot be written")
    r = runner.invoke(app, ["identify", str(DEFAULT), "--json", str(tmp_path / ("a" * 245 + ".json"))])
    _one_line_error(r, "file name is 250 bytes long")


def test_spreadsheet_formulas_in_labels_are_quoted_in_tables(tmp_path):
    df = pd.read_csv(DEFAULT)
    df["experiment"] = "=cmd|' /C calc'!A0"
    data = tmp_path / "labels.csv"
    df.to_csv(data, index=False)
    table = tmp_path / "table.csv"
    r = runner.invoke(app, ["identify", str(data), "--by", "experiment", "--table", str(table)])
    assert r.exit_code == 0, r.output
    got = pd.read_csv(table)
    assert got["experiment"].iloc[0] == "'=cmd|' /C calc'!A0"
    assert (got["g_v0_um"] > 0).all()                  # numbers are numbers still


def test_formula_safe_leaves_numbers_alone():
    frame = pd.DataFrame({"label": ["=1+1", "-5", "+x", "@SUM(A1)", "plain", "-1e-3"], "value": [-1.0] * 6})
    got = _output.formula_safe(frame)
    assert got["label"].tolist() == ["'=1+1", "-5", "'+x", "'@SUM(A1)", "plain", "-1e-3"]
    assert got["value"].tolist() == [-1.0] * 6


# --- an environment JAX cannot start in; Ctrl-C ------------------------------------------------------------------

def test_a_missing_jax_backend_is_named():
    r = _run("identify", DEFAULT, env={"JAX_PLATFORMS": "tpu"})
    assert r.returncode == 2 and "JAX_PLATFORMS" in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_an_unknown_xla_flag_is_named_before_it_aborts(tmp_path):
    r = _run("identify", DEFAULT, env={"XLA_FLAGS": "--xla_no_such_flag_for_ambfit", "HOME": str(tmp_path)})
    assert r.returncode == 2 and "XLA_FLAGS" in r.stderr and "xla_no_such_flag_for_ambfit" in r.stderr, r.stderr


def test_ctrl_c_inside_emcee_is_held_until_the_piece_ends():
    # emcee prints every walker and a traceback for any exception in the log-probability, KeyboardInterrupt too:
    # the interrupt (here sent by the sampler's own first piece) is raised by ambfit after that piece instead
    from ambfit.estimation.ensembles import Tally, advance

    class Sampler:
        pieces = completed = 0

        def run_mcmc(self, start, k, progress=False):
            Sampler.pieces += 1
            if Sampler.pieces == 1:
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.05)                   # the signal is handled while the piece still runs
            Sampler.completed += 1

    # Python's own SIGINT handler, as in the command line (a pytest-xdist worker ignores SIGINT)
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            advance(Sampler(), None, 2000, Tally(None, 2000), "steps")
        assert Sampler.pieces == Sampler.completed == 1     # the piece it came in ran to its end, and no other
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler          # the handler is given back
    finally:
        signal.signal(signal.SIGINT, before)


def test_ctrl_c_during_a_command_ends_in_one_line(monkeypatch, tmp_path):
    # Typer would end an interrupt in silence with exit 130
    from ambfit.estimation import bayes

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(bayes, "sample", interrupted)
    r = runner.invoke(app, ["sample", str(DEFAULT), "--json", str(tmp_path / "s.json")])
    assert r.exit_code == 130 and "error: interrupted; no output was written half-way" in r.output, r.output
    assert not (tmp_path / "s.json").exists()
