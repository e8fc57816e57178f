"""Every command of the README's "Command line" section runs as written and exits 0 (in a scratch folder)."""

import re
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    section = text.split("## Command line", 1)[1]
    block = re.search(r"```bash\n(.*?)```", section, flags=re.S).group(1)
    return [line for line in block.splitlines() if line.strip() and not line.lstrip().startswith("#")]


def test_every_command_line_example_runs(tmp_path):
    commands = readme_commands()
    assert len(commands) >= 10 and all(c.startswith(".venv/bin/ambfit ") for c in commands)
    (tmp_path / "data").symlink_to(ROOT / "data")
    exe = str(Path(sys.executable).with_name("ambfit"))    # the README's .venv/bin/ambfit, wherever it lives
    for command in commands:
        args = [exe, *shlex.split(command)[1:]]
        out = subprocess.run(args, cwd=tmp_path, capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, f"{command}\n{out.stdout[-2000:]}\n{out.stderr[-2000:]}"
        assert "Traceback" not in out.stderr, command
    for name in ("sat.csv", "sat.json", "posterior.nc", "bayes.json", "pair.png", "map.png", "diag.json",
                 "search.json", "reports/sat/index.html", "runs.csv", "runs.json"):
        assert (tmp_path / name).exists(), name
    # what the comments promise: Table 2's protocol cannot see the saturation, the bias sweep names it
    import json

    assert json.loads((tmp_path / "diag.json").read_text())["verdict"] == "none"
    sweep = json.loads((tmp_path / "sweep_diag.json").read_text())
    assert sweep["verdict"] == "saturation" and sweep["shrink"] > 0.9
    # several files: one entry per file, no pooled fit unless asked
    runs = json.loads((tmp_path / "runs.json").read_text())
    assert [g["group"] for g in runs["groups"]] == ["sat.csv", "sweep.csv"] and "pooled" not in runs
    assert all(g["status"] == "ok" for g in runs["groups"])
