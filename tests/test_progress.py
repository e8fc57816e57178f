"""Progress: library functions report through an optional callback and never draw; the command line draws a rich
bar on stderr only when it is a terminal."""

import io
import subprocess
import sys
from pathlib import Path

from typer.testing import CliRunner

from ambfit.faces.cli import app
from ambfit.faces.cli.progress import Bar, progress_bar
from ambfit.rig import virtual as rig
from ambfit.studies import origin

ROOT = Path(__file__).resolve().parents[1]


def recorder():
    calls = []
    return calls, lambda what, done, total: calls.append((what, done, total))


def test_origin_search_reports_each_iteration(capsys):
    calls, cb = recorder()
    origin.search(rig.PAPER_RIG, iterations=3, noise=rig.NOISE_FREE, progress=cb)
    assert calls == [("origin search", 1, 3), ("origin search", 2, 3), ("origin search", 3, 3)]
    assert capsys.readouterr() == ("", "")                 # the library draws nothing itself


def test_diagnose_reports_every_candidate(capsys):
    from ambfit.data import read_csv
    from ambfit.diagnosis import diagnose
    from ambfit.physics import effects as E

    data = read_csv(ROOT / "data" / "paper_table2.csv")
    calls, cb = recorder()
    diagnose(data, candidates=[E.Saturation(), E.Leakage()], progress=cb)
    fits = [c for c in calls if c[0] == "candidate effects"]
    assert [c[1] for c in fits] == [1, 2, 3] and {c[0] for c in calls} == {"candidate effects", "discrepancy"}
    assert fits[-1][1] == fits[-1][2]                       # ends full: the ideal law and both candidates
    assert calls[-1] == ("discrepancy", 1, 1)               # then the model-discrepancy term, one phase
    assert capsys.readouterr() == ("", "")


def test_the_bar_is_silent_off_a_terminal_and_draws_on_one():
    with progress_bar(enabled=False) as bar:
        assert not bar.enabled
        bar("anything", 1, 2)                               # a no-op
        bar.step("phase")
        assert list(bar.iterate([1, 2], "items")) == [1, 2]
    from rich.console import Console
    from rich.progress import Progress

    out = io.StringIO()
    with Progress(console=Console(file=out, force_terminal=True, width=80)) as live:
        bar = Bar(live, phases=2)
        bar.step("least squares")
        bar("candidate effects: saturation", 3, 11)
        bar("candidate effects: leakage", 4, 11)            # the same bar, a new detail
        assert len(live.tasks) == 2
        task = live.tasks[1]
        assert (task.completed, task.total, task.description) == (4, 11, "candidate effects: leakage")


def test_cli_prints_no_progress_into_a_pipe(tmp_path):
    r = CliRunner().invoke(app, ["origin-search", "--iterations", "2", "--current-noise-ma", "0",
                                 "--position-noise-um", "0"])
    assert r.exit_code == 0, r.output
    assert "\r" not in r.output and "0:00:0" not in r.output          # no bar redraws, no elapsed-time column


def test_help_imports_nothing_heavy():
    # what keeps `ambfit --help` fast: the command line imports no numerical stack (its time is measured against
    # a peer in benchmarks/ls_speed.py, not asserted here: a loaded CI machine fails any wall-clock bound)
    code = ("import sys; import ambfit.faces.cli; "
            "print([m for m in ('jax', 'pandas', 'matplotlib', 'scipy', 'rich.progress') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stdout + out.stderr
    exe = str(Path(sys.executable).with_name("ambfit"))
    r = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "identify" in r.stdout


def test_diagnose_without_std_columns_reports_the_noise_phase_first():
    from ambfit.data import read_csv
    from ambfit.diagnosis import diagnose
    from ambfit.physics import effects as E

    data = read_csv(ROOT / "data" / "paper_table2.csv")
    bare = data.frame.drop(columns=[c for c in data.frame if "_std_" in c])
    calls, cb = recorder()
    diagnose(bare, candidates=[E.Saturation(), E.Leakage()], progress=cb)
    assert calls[:2] == [("the readings' noise", 0, 2), ("the readings' noise", 2, 2)]
    assert calls[2][0] == "candidate effects"
