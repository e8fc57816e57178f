"""Bad option values end in one line naming the option and the value, exit 2, no traceback (issue 24); tables
piped to a file keep every cell whole."""

from pathlib import Path

import pytest
from typer.testing import CliRunner

from ambfit.faces.cli import app

ROOT = Path(__file__).resolve().parents[1]
DATA = str(ROOT / "data" / "paper_table2.csv")
runner = CliRunner()

# (arguments, what the message must name); the value itself is checked to appear too
BAD = [
    (["sample", DATA, "--gap-prior-log-sd", "0"], "--gap-prior-log-sd"),
    (["sample", DATA, "--gap-prior-log-sd", "nan"], "--gap-prior-log-sd"),
    (["sample", DATA, "--walkers", "1"], "--walkers"),
    (["sample", DATA, "--walkers", "3"], "--walkers"),
    (["sample", DATA, "--mcmc-steps", "0"], "--mcmc-steps"),
    (["sample", DATA, "--mcmc-steps", "2000", "--max-mcmc-steps", "1000"], "--max-mcmc-steps"),
    (["sample", DATA, "--ensembles", "1"], "--ensembles"),
    (["sample", DATA, "--nominal-gap-um", "-1"], "--nominal-gap-um"),
    (["sample", DATA, "--seed", "-1"], "--seed"),
    (["solution-space", DATA, "--png", "x.png", "--step-um", "0.001"], "--step-um"),
    (["solution-space", DATA, "--png", "x.png", "--step-um", "0"], "--step-um"),
    (["solution-space", DATA, "--png", "x.png", "--gap-um", "1000,600"], "--gap-um"),
    (["solution-space", DATA, "--png", "x.png", "--origin-um", "100,-100"], "--origin-um"),
    (["solution-space", DATA, "--png", "x.png", "--gap-um", "600"], "--gap-um"),
    (["design", DATA, "--next-steps", "0"], "--next-steps"),
    (["design", DATA, "--max-radius-um", "nan"], "--max-radius-um"),
    (["identify", DATA, "--bearing", "/bin/sh"], "--bearing"),
    (["identify", DATA, "--current-noise-ma", "-1"], "--current-noise-ma"),
    (["identify", DATA, "--position-noise-um", "nan"], "--position-noise-um"),
    (["identify", DATA, "--debias", "-1"], "--debias"),
    (["identify", DATA, "--max-position-um", "0"], "--max-position-um"),
    (["identify", DATA, "--workers", "0"], "--workers"),
    (["check", DATA, "--bearing", "/bin/sh"], "--bearing"),
    (["check", DATA, "--max-position-um", "nan"], "--max-position-um"),
    (["simulate", "-o", "x.csv", "--iterations", "0"], "--iterations"),
    (["simulate", "-o", "x.csv", "--biases-a", "1.4,abc"], "--biases-a"),
    (["simulate", "-o", "x.csv", "--offsets-um", "-20"], "--offsets-um"),
    (["simulate", "-o", "x.csv", "--gap-um", "nan"], "--gap-um"),
    (["simulate", "-o", "x.csv", "--center-um", "1,2,3"], "--center-um"),
    (["simulate", "-o", "x.csv", "--current-noise-ma", "inf"], "--current-noise-ma"),
    (["simulate", "-o", "x.csv", "--protocol", "/bin/sh"], "--protocol"),
    (["simulate", "-o", "x.csv", "--effect", "saturation:b_sat=abc"], "--effect"),
    (["simulate", "-o", "x.csv", "--effect", "saturation:b_sat=-1"], "b_sat=-1"),
    (["origin-search", "--biases-a", "1.4"], "--biases-a"),
    (["origin-search", "--biases-a", "1.4,1.4"], "--biases-a"),
    (["origin-search", "--tolerance-um", "0"], "--tolerance-um"),
    (["origin-search", "--offset-um", "-5"], "--offset-um"),
    (["origin-search", "--iterations", "0"], "--iterations"),
    (["origin-search", "--experiment", " "], "--experiment"),
    (["report", DATA, "-o", "rep", "--ensembles", "0"], "--ensembles"),
    (["report", DATA, "-o", "rep", "--max-radius-um", "-1"], "--max-radius-um"),
    (["paper", "-o", "pap", "--replicates", "0"], "--replicates"),
    (["campaign", DATA, "--seed", "-1"], "--seed"),
    (["campaign", DATA, "--alpha", "nan"], "--alpha"),
]


@pytest.mark.parametrize("args, names", BAD, ids=lambda a: " ".join(a[-2:]) if isinstance(a, list) else None)
def test_a_bad_option_is_one_line_naming_it(tmp_path, monkeypatch, args, names):
    monkeypatch.chdir(tmp_path)
    r = runner.invoke(app, args)
    assert r.exit_code == 2, r.output
    assert r.exception is None or isinstance(r.exception, SystemExit), repr(r.exception)
    assert "Traceback" not in r.output
    errors = [line for line in r.output.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and names in errors[0], r.output
    if names.startswith("--"):
        assert args[args.index(names) + 1].strip() in errors[0] or args[-1] in errors[0], r.output
    assert not (tmp_path / "x.csv").exists() and not (tmp_path / "rep").exists()


@pytest.mark.parametrize("command, old, new", [("sample", "--steps", "--mcmc-steps"),
                                               ("design", "--steps", "--next-steps")])
def test_the_old_step_options_are_aliases_of_the_new(command, old, new):
    # --steps meant sampler steps in sample and report, recommended perturbations in design: each has its own
    # name now, and the old one still works (and is named in the message as the new one)
    r = runner.invoke(app, [command, DATA, old, "0"])
    assert r.exit_code == 2 and f"error: {new} 0" in r.output, r.output
    assert f"{new}, {old}" in runner.invoke(app, [command, "--help"]).output.replace("\n", " ")


def test_piped_tables_keep_long_file_names_whole(tmp_path):
    long = "a_rather_long_campaign_file_name_from_the_rig_logger_" * 3
    paths = [tmp_path / f"{long}{i}.csv" for i in (1, 2)]
    for p in paths:
        p.write_bytes(Path(DATA).read_bytes())
    r = runner.invoke(app, ["identify", *map(str, paths), "--method", "closed-form"])
    assert r.exit_code == 0, r.output
    for p in paths:
        assert str(p) in r.output, r.output


@pytest.mark.parametrize("text, named", [
    ('loads = [1, 2]\n[[block]]\nkind = "perturbation"\nbiases_A = [1.4, 1.6]\noffsets_um = [-20, 20]\n', "wrong kind"),
    ('[[block]]\nkind = "perturbation"\noffsets_um = [-20, 20]\n', "lacks the key"),
])
def test_a_bad_protocol_file_is_one_line_naming_it(tmp_path, text, named):
    """A --protocol table of the wrong shape or missing a key: one line naming the file, exit 2, no traceback."""
    path = tmp_path / "p.toml"
    path.write_text(text)
    r = runner.invoke(app, ["simulate", "-o", str(tmp_path / "o.csv"), "--protocol", str(path)])
    assert r.exit_code == 2 and str(path.name) in r.output and named in r.output, r.output
    assert "Traceback" not in r.output


def test_the_design_targets_are_the_head_parameters():
    """``ambfit design --target`` offers the six head parameters.  The command line spells them itself (it imports
    no estimation module until a command runs, so ``ambfit --help`` stays fast): held to the one table here."""
    from ambfit.estimation.units import HEAD
    from ambfit.faces.cli.explore import Target

    assert sorted(t.value for t in Target) == sorted(HEAD)


def test_the_diagnose_occam_choices_are_the_rules():
    """``ambfit diagnose --occam`` offers :data:`ambfit.diagnosis.verdict.OCCAM`, its default the rules' default."""
    from ambfit.diagnosis.verdict import OCCAM, Rules
    from ambfit.faces.cli.fitting import Occam

    assert [o.value for o in Occam] == list(OCCAM) and Occam.all.value == Rules().occam
