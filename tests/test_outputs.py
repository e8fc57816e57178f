"""Outputs never damage files: atomic writes, links followed, devices written into, a full disk reported, every
output checked before the work (issue 24)."""

import errno
import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from ambfit import _output
from ambfit.faces.cli import app

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT / "data" / "paper_table2.csv"
runner = CliRunner()

SEARCH = ["origin-search", "--iterations", "4"]      # the quickest command with a --json output


def leftovers(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir() if p.name.startswith(".")]


# --- the writers -----------------------------------------------------------------------------------------------

def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    old = tmp_path / "out.json"
    old.write_text("old")

    def full(f):
        f.write(b"half")
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(_output.OutputError, match=r"out.json: could not be written \(No space left on device\)"):
        _output.write_with(old, full)
    assert old.read_text() == "old" and leftovers(tmp_path) == []


def test_writing_keeps_the_mode_of_the_file_it_replaces(tmp_path):
    old = tmp_path / "out.csv"
    old.write_text("old")
    old.chmod(0o640)
    _output.write_text(old, "new")
    assert old.read_text() == "new" and stat.S_IMODE(old.stat().st_mode) == 0o640


def test_a_symbolic_link_is_written_through_and_stays_a_link(tmp_path):
    (tmp_path / "real").mkdir()
    target = tmp_path / "real" / "out.json"
    target.write_text("old")
    link = tmp_path / "link.json"
    link.symlink_to(target)
    dangling = tmp_path / "dangling.json"
    dangling.symlink_to(tmp_path / "real" / "new.json")
    _output.write_json(link, {"a": 1})
    _output.write_json(dangling, {"b": 2})
    assert link.is_symlink() and json.loads(target.read_text()) == {"a": 1}
    assert dangling.is_symlink() and json.loads((tmp_path / "real" / "new.json").read_text()) == {"b": 2}


def test_a_fifo_is_written_into_not_replaced(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    reader = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)     # a reader waiting, as `cat pipe` would
    try:
        _output.write_text(fifo, "through the pipe")
        assert os.read(reader, 1024) == b"through the pipe"
    finally:
        os.close(reader)
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
def test_a_full_device_is_reported_and_stays_a_device():
    with pytest.raises(_output.OutputError, match="No space left on device"):
        _output.write_text("/dev/full", "x" * 10_000)
    assert stat.S_ISCHR(os.stat("/dev/full").st_mode)


@pytest.mark.parametrize("name, folder, parents, why", [
    ("data.csv/out.json", False, False, "is a file, not a folder"),
    ("data.csv/a/b/out.json", False, True, "is a file, not a folder"),
    ("data.csv/report", True, False, "is a file, not a folder"),
    ("data.csv", True, False, "exists and is not a folder"),
    ("sub", False, False, "is a directory; give a file name"),
    ("missing/out.json", False, False, "does not exist"),
])
def test_unwritable_says_why(tmp_path, name, folder, parents, why):
    (tmp_path / "data.csv").write_text("x")
    (tmp_path / "sub").mkdir()
    assert why in _output.unwritable(tmp_path / name, folder=folder, parents=parents)
    assert _output.unwritable(tmp_path / "missing" / "x.json", parents=True) is None


# --- the command line ------------------------------------------------------------------------------------------

def test_a_fifo_output_of_a_command_stays_a_fifo(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    reader = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)
    try:
        r = runner.invoke(app, [*SEARCH, "--json", str(fifo)])
        assert r.exit_code == 0, r.output
        assert json.loads(os.read(reader, 1 << 16))["iterations"]
    finally:
        os.close(reader)
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)


def test_a_linked_output_of_a_command_is_written_through(tmp_path):
    target = tmp_path / "kept" / "search.json"
    target.parent.mkdir()
    target.write_text("old")
    link = tmp_path / "search.json"
    link.symlink_to(target)
    r = runner.invoke(app, [*SEARCH, "--json", str(link), "-o", str(tmp_path / "d.csv")])
    assert r.exit_code == 0, r.output
    assert link.is_symlink() and json.loads(target.read_text())["iterations"]


def test_a_full_disk_is_a_message_and_the_old_file_stays(tmp_path, monkeypatch):
    old = tmp_path / "search.json"
    old.write_text("old")

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(_output.os, "fsync", full)          # where a full disk shows at the latest
    r = runner.invoke(app, [*SEARCH, "--json", str(old)])
    assert r.exit_code == 2 and "No space left on device" in r.output and "search.json" in r.output, r.output
    assert r.exception is None or isinstance(r.exception, SystemExit)
    assert old.read_text() == "old" and leftovers(tmp_path) == []


def _small_disk(tmp_path) -> Path:
    mnt = tmp_path / "small"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=192k", "tmpfs", str(mnt)],
                      capture_output=True).returncode != 0:
        pytest.skip("cannot mount a small tmpfs here (needs root)")
    return mnt


def test_a_full_disk_during_sample_keeps_the_old_posterior(tmp_path):
    """HDF5 crashed the process (SIGSEGV) on a full disk and left a truncated file; now the NetCDF is made in
    memory and written by Python: a message, exit 2, the old file as it was, no temporary file."""
    mnt = _small_disk(tmp_path)
    try:
        old = mnt / "posterior.nc"
        old.write_bytes(b"old posterior")
        r = subprocess.run([sys.executable, "-m", "ambfit", "sample", str(DEFAULT), "--out", str(old),
                            "--steps", "500", "--max-steps", "1000", "--no-progress"],
                           capture_output=True, text=True, timeout=600)
        assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
        assert "posterior.nc: could not be written (No space left on device)" in r.stderr
        assert "Traceback" not in r.stderr
        assert old.read_bytes() == b"old posterior" and leftovers(mnt) == []
    finally:
        subprocess.run(["umount", str(mnt)], check=False)


# every output option of every command, under a regular file: refused before the work
UNDER_A_FILE = [
    ["simulate", "-o", "{f}/x.csv"], ["simulate", "-o", "{t}/x.csv", "--truth", "{f}/t.json"],
    ["origin-search", "--json", "{f}/x.json"], ["origin-search", "-o", "{f}/x.csv"],
    ["origin-search", "--truth", "{f}/x.json"],
    ["identify", "{d}", "--json", "{f}/x.json"], ["identify", "{d}", "--table", "{f}/x.csv"],
    ["sample", "{d}", "--out", "{f}/x.nc"], ["sample", "{d}", "--json", "{f}/x.json"],
    ["sample", "{d}", "--pair-png", "{f}/x.png"],
    ["solution-space", "{d}", "--png", "{f}/x.png"], ["design", "{d}", "--json", "{f}/x.json"],
    ["diagnose", "{d}", "--json", "{f}/x.json"], ["diagnose", "{d}", "--report", "{f}/r"],
    ["report", "{d}", "-o", "{f}/r"], ["paper", "-o", "{f}/r"],
    ["campaign", "{d}", "--json", "{f}/x.json"], ["campaign", "{d}", "--table", "{f}/x.csv"],
    ["campaign", "--example", "{f}/x.csv"],
    ["force", "{t}/m.json", "--axis", "v", "--i-top", "1.5", "--i-bottom", "1.3", "--json", "{f}/x.json"],
]


@pytest.mark.parametrize("args", UNDER_A_FILE, ids=lambda a: " ".join(a[:1] + a[-2:-1]))
def test_every_output_under_a_file_is_refused_before_the_work(tmp_path, args):
    f = tmp_path / "somefile.csv"
    f.write_text("x")
    argv = [a.format(f=f, t=tmp_path, d=DEFAULT) for a in args]
    r = runner.invoke(app, argv)
    assert r.exit_code == 2 and "somefile.csv is a file, not a folder" in r.output, r.output


def test_an_output_onto_the_input_is_refused(tmp_path):
    data = tmp_path / "d.csv"
    data.write_bytes(DEFAULT.read_bytes())
    r = runner.invoke(app, ["identify", str(data), "--table", str(data)])
    assert r.exit_code == 2 and "is the input" in r.output, r.output
    r = runner.invoke(app, ["identify", str(data), "--json", str(tmp_path / "o"), "--table", str(tmp_path / "o")])
    assert r.exit_code == 2 and "given for two outputs" in r.output, r.output
    assert data.read_bytes() == DEFAULT.read_bytes()


def test_force_refuses_to_write_over_its_model_or_readings(tmp_path):
    """``ambfit force`` checks its outputs against its inputs too: the model file and the readings stay."""
    data = tmp_path / "d.csv"
    data.write_bytes(DEFAULT.read_bytes())
    model = tmp_path / "m.json"
    assert runner.invoke(app, ["identify", str(data), "--json", str(model)]).exit_code == 0
    before = model.read_bytes()
    for option, target in (("--json", model), ("--out", data)):
        r = runner.invoke(app, ["force", str(model), "--data", str(data), option, str(target)])
        assert r.exit_code == 2 and "is the input" in r.output, r.output
    assert model.read_bytes() == before and data.read_bytes() == DEFAULT.read_bytes()
