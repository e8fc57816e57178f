"""Every command of the README's "Command line" section runs as written and exits 0 (in a scratch folder).

The first command runs as the README shows it, through the installed ``.venv/bin/ambfit`` in a new process (the
entry point, the light import); the others run the same command line through the same entry function in this
process, so they share what JAX has compiled instead of compiling it again in a new process each (a new process
per command took most of this test's 100 s)."""

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    section = text.split("## Command line", 1)[1]
    block = re.search(r"```bash\n(.*?)```", section, flags=re.S).group(1)
    return [line for line in block.splitlines() if line.strip() and not line.lstrip().startswith("#")]


def _in_process(argv: list[str]) -> tuple[int, str]:
    """``ambfit argv`` through :func:`ambfit.faces.cli.main` in this process: its exit code and its output."""
    import contextlib
    import io

    from ambfit.faces import cli

    out = io.StringIO()
    code = 0
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        saved, sys.argv = sys.argv, ["ambfit", *argv]
        try:
            cli.main()
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        finally:
            sys.argv = saved
    return code, out.getvalue()


@pytest.mark.slow          # every README command, one after another
def test_every_command_line_example_runs(tmp_path, monkeypatch):
    commands = readme_commands()
    assert len(commands) >= 10 and all(c.startswith(".venv/bin/ambfit ") for c in commands)
    (tmp_path / "data").symlink_to(ROOT / "data")
    exe = str(Path(sys.executable).with_name("ambfit"))    # the README's .venv/bin/ambfit, wherever it lives
    first = subprocess.run([exe, *shlex.split(commands[0])[1:]], cwd=tmp_path, capture_output=True, text=True,
                           timeout=600)
    assert first.returncode == 0 and "Traceback" not in first.stderr, f"{commands[0]}\n{first.stderr[-2000:]}"
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("AMBFIT_JAX_CACHE", "off")      # this process's JAX settings stay as the other tests have them
    for command in commands[1:]:
        code, text = _in_process(shlex.split(command)[1:])
        assert code == 0, f"{command}\n{text[-3000:]}"
        assert "Traceback" not in text and "unexpected" not in text, f"{command}\n{text[-3000:]}"

    for name in ("sat.csv", "sat.json", "posterior.nc", "bayes.json", "pair.png", "map.png", "diag.json",
                 "search.json", "reports/sat/index.html", "runs.csv", "runs.json"):
        assert (tmp_path / name).exists(), name
    # what the commands write, run in the repository root as the README says, is ignored by git
    written = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*") if p.is_file() and "data" not in p.parts)
    if (ROOT / ".git").exists():
        kept = [w for w in written if subprocess.run(["git", "-C", str(ROOT), "check-ignore", "-q", w]).returncode]
        assert not kept, f"README outputs not in .gitignore: {kept}"
    # what the comments promise: Table 2's protocol cannot see the saturation, the bias sweep names it
    import json

    assert json.loads((tmp_path / "diag.json").read_text())["verdict"] == "none"
    sweep = json.loads((tmp_path / "sweep_diag.json").read_text())
    assert sweep["verdict"] == "saturation" and sweep["shrink"] > 0.9
    # several files: one entry per file, no pooled fit unless asked
    runs = json.loads((tmp_path / "runs.json").read_text())
    assert [g["group"] for g in runs["groups"]] == ["sat.csv", "sweep.csv"] and "pooled" not in runs
    assert all(g["status"] == "ok" for g in runs["groups"])


def test_a_failing_command_fails_the_readme_check(tmp_path, monkeypatch):
    """The in-process runner reports what the command line reports: a missing file is exit 2 with a message."""
    monkeypatch.chdir(tmp_path)
    code, text = _in_process(["identify", "missing.csv"])
    assert code == 2 and "missing.csv" in text
