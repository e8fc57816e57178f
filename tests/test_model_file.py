"""The model file ``ambfit force`` reads: marked by its writer, checked value by value by its reader (issue 24).

Every damaged or foreign file must end in exit 2 with one line naming the file, the JSON key and the value;
the file as written gives the fit's own forces and the force output says which file and version it used.
"""

import copy
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

import ambfit
from ambfit.data import read_csv
from ambfit.estimation import model_file
from ambfit.estimation.measure import FittedModel, ModelFileError
from ambfit.faces.cli import app
from ambfit.rows import readings

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT / "data" / "paper_table2.csv"
runner = CliRunner()
ONE = ["--axis", "v", "--i-top", "1.6", "--i-bottom", "1.2"]


@pytest.fixture(scope="module")
def fit():
    return ambfit.fit(read_csv(DEFAULT))


@pytest.fixture(scope="module")
def record(fit):
    return json.loads(json.dumps(fit.to_json()))          # through JSON, as a file holds it


def _force(tmp_path, rec, *args, raw: bytes | None = None):
    path = tmp_path / "model.json"
    path.write_bytes(raw) if raw is not None else path.write_text(json.dumps(rec))
    return runner.invoke(app, ["force", str(path), *(args or ONE)])


def test_identify_records_its_version_schema_and_kind_and_keeps_the_contract(record):
    from ambfit import __version__

    assert record["ambfit_version"] == __version__ and record["kind"] == "identify"
    assert record["schema"] == model_file.SCHEMA
    # the contract's keys, as they were
    assert {"method", "params", "converged", "n_rows", "goodness_of_fit", "model_state"} <= set(record)
    assert set(record["params"]) == {"g_v0_um", "v0_um", "g_w0_um", "w0_um", "k_v_Nm2_per_A2", "k_w_Nm2_per_A2"}
    # the bearing it was fitted with, in the contract's keys (section 4), reads back as the same bearing
    described = ambfit.Bearing.from_dict(record["model_state"]["bearing_description"])
    assert model_file.differing_key(described, ambfit.PAPER_BEARING) is None


def _drop(state, name):
    j = state["names"].index(name)
    del state["names"][j], state["values"][j]
    state["covariance"] = [[c for k, c in enumerate(r) if k != j] for i, r in enumerate(state["covariance"]) if i != j]


def _set(name, value):
    def edit(rec):
        s = rec["model_state"]
        s["values"][s["names"].index(name)] = value
    return edit


def _state(fn):
    return lambda rec: fn(rec["model_state"])


DAMAGED = [
    # (name, edit of the identify record, key and value the message must name)
    ("gap deleted", _state(lambda s: _drop(s, "g_v0")), ["model_state.names", "no 'g_v0'"]),
    ("gap renamed", _state(lambda s: s["names"].__setitem__(0, "gap_v")), ["model_state.names[0]", "'gap_v'"]),
    ("negative k", _set("k_v", -3.4e-6), ["(k_v)", "-3.4e-06", "positive"]),
    ("k of 0", _set("k_w", 0.0), ["(k_w)", "0.0", "positive"]),
    ("gap in µm where model_state holds m", _set("g_v0", 774.5), ["(g_v0)", "774.5", "micrometres"]),
    ("gap ten times the drawn one", _set("g_w0", 0.0095), ["(g_w0)", "0.0095"]),
    ("origin as large as the gap", _set("v0", 0.0008), ["(v0)", "0.0008", "as large as the gap"]),
    ("negative variance", _state(lambda s: s["covariance"][0].__setitem__(0, -1e-12)),
     ["model_state.covariance[0][0]", "-1e-12", "negative variance"]),
    ("params gap in metres", lambda r: r["params"]["g_v0_um"].__setitem__("value", 0.00077),
     ["params.g_v0_um.value", "0.00077", "metres"]),
    ("params key renamed", lambda r: r["params"].__setitem__("gap_w_um", r["params"].pop("g_w0_um")),
     ["params.gap_w_um", "did you mean 'g_w0_um'"]),
    ("params std not finite", lambda r: r["params"]["v0_um"].__setitem__("std", float("nan")),
     ["params.v0_um.std", "nan"]),
    ("params std negative", lambda r: r["params"]["v0_um"].__setitem__("std", -0.3), ["params.v0_um.std", "-0.3"]),
    ("params edited, model_state not", lambda r: r["params"]["g_w0_um"].__setitem__("value", 700.0),
     ["params.g_w0_um", "700.0", "the file was edited"]),
    ("newer major version", lambda r: r.__setitem__("ambfit_version", "99.0.0"), ["ambfit_version", "'99.0.0'"]),
    ("newer schema", lambda r: r.__setitem__("schema", "ambfit.model.v2"), ["schema", "'ambfit.model.v2'"]),
    ("another kind", lambda r: r.__setitem__("kind", "sample"), ["kind", "'sample'"]),
]


@pytest.mark.parametrize("name,edit,words", DAMAGED, ids=[d[0] for d in DAMAGED])
def test_force_refuses_a_damaged_model_file_naming_key_and_value(tmp_path, record, name, edit, words):
    rec = copy.deepcopy(record)
    edit(rec)
    r = _force(tmp_path, rec)
    assert r.exit_code == 2, r.output
    assert "model.json" in r.output and all(w in r.output for w in words), r.output
    assert "Traceback" not in r.output and "force [N]" not in r.output


def _sample_like(record):
    return {"method": "bayes", "params": {k: v | {"hdi_low": 0.0, "hdi_high": 1.0} for k, v in record["params"].items()}}


FOREIGN = [
    ("a posterior (sample) JSON", _sample_like, "ambfit sample"),
    ("the rig's truth JSON", lambda r: json.loads((ROOT / "data" / "paper_table2.truth.json").read_text()), "truth"),
    ("a random JSON object", lambda r: {"a": 1, "b": [2]}, "not an ambfit identify/diagnose output"),
    ("a JSON list", lambda r: [r], "not an ambfit identify/diagnose output"),
    ("several groups", lambda r: {"groups": [r, r]}, "groups"),
    ("a closed-form result", lambda r: {"method": "closed_form", "params": r["params"]}, "closed-form"),
]


@pytest.mark.parametrize("name,make,words", FOREIGN, ids=[f[0] for f in FOREIGN])
def test_force_refuses_a_file_that_is_not_a_model(tmp_path, record, name, make, words):
    r = _force(tmp_path, make(record))
    assert r.exit_code == 2 and words in r.output, r.output


def test_force_refuses_a_binary_file(tmp_path):
    r = _force(tmp_path, None, raw=bytes(range(256)) * 4)
    assert r.exit_code == 2 and "not a model JSON" in r.output and "Traceback" not in r.output


def test_a_file_without_version_is_used_with_a_warning_only_when_all_else_holds(tmp_path, record, fit):
    old = {k: v for k, v in copy.deepcopy(record).items() if k not in ("schema", "kind", "ambfit_version")}
    del old["model_state"]["bearing_description"]
    r = _force(tmp_path, old, *ONE, "--json", str(tmp_path / "f.json"))
    assert r.exit_code == 0, r.output
    assert "warning" in r.output and "no ambfit_version" in r.output
    f, _ = ambfit.force(fit, "v", 1.6, 1.2, 0.0)
    assert json.loads((tmp_path / "f.json").read_text())["force_N"][0] == pytest.approx(float(f), rel=1e-12)
    old["model_state"]["values"][old["model_state"]["names"].index("k_v")] = -3.4e-6
    assert _force(tmp_path, old).exit_code == 2


def test_an_effect_parameter_neither_estimated_nor_held_is_refused(record):
    rec = copy.deepcopy(record)
    rec["model_state"]["effects"] = [{"name": "saturation", "off": [], "held": {}}]
    rec["model_state"]["names"] += ["saturation.b_sat[v]", "saturation.b_sat[w]", "saturation.sharpness[v]"]
    rec["model_state"]["values"] += [1.2, 1.2, 4.0]
    rec["model_state"]["covariance"] = np.eye(len(rec["model_state"]["names"])).tolist()
    rec.pop("params")
    with pytest.raises(ModelFileError, match=r"saturation\.sharpness"):
        FittedModel.from_json(rec, ambfit.PAPER_BEARING, "m.json")


def test_the_force_output_names_the_model_file_and_its_version(tmp_path, record):
    from ambfit import __version__

    out, js = tmp_path / "forces.csv", tmp_path / "f.json"
    r = _force(tmp_path, record, "--data", str(DEFAULT), "--out", str(out), "--json", str(js))
    assert r.exit_code == 0, r.output
    got = json.loads(js.read_text())
    assert got["model_file"].endswith("model.json") and got["model_ambfit_version"] == __version__
    assert got["model_kind"] == "identify" and got["ambfit_version"] == __version__
    table = pd.read_csv(out)
    assert table["model_file"].str.endswith("model.json").all() and (table["model_ambfit_version"] == __version__).all()


def test_the_bearing_the_model_records_is_used_and_another_description_refused(tmp_path):
    # a model fitted with a bearing description of its own: force uses the description the file records (250
    # turns: the data's k is 0.88 of this drawing's, plausible; force judges the model as identify does)
    bearing = ambfit.PAPER_BEARING.with_(name="rig B", turns_per_pole=250.0)
    ds = read_csv(DEFAULT)
    res = ambfit.fit(ds, bearing=bearing)
    rec = json.loads(json.dumps(res.to_json()))
    r = _force(tmp_path, rec, "--data", str(DEFAULT), "--json", str(tmp_path / "f.json"))
    assert r.exit_code == 0, r.output
    want, _ = FittedModel.from_result(res).force(readings(ds))
    np.testing.assert_allclose(json.loads((tmp_path / "f.json").read_text())["force_N"], want, rtol=1e-9)
    # the same name with another number of turns: not the bearing the model was fitted with
    toml = tmp_path / "b.toml"
    toml.write_text('name = "rig B"\nturns_per_pole = 160\n')
    r = _force(tmp_path, rec, *ONE, "--bearing", str(toml))
    assert r.exit_code == 2 and "bearing_description.turns_per_pole" in r.output, r.output


def test_diagnose_records_its_version_and_force_reads_it(tmp_path):
    from ambfit import __version__

    out = tmp_path / "dg.json"
    assert runner.invoke(app, ["diagnose", str(DEFAULT), "--json", str(out)]).exit_code == 0
    rec = json.loads(out.read_text())
    assert (rec["kind"], rec["ambfit_version"], rec["schema"]) == ("diagnose", __version__, model_file.SCHEMA)
    assert {"baseline", "noise_floor", "where", "ranking", "verdict", "confounded_with", "shrink"} <= set(rec)
    r = runner.invoke(app, ["force", str(out), *ONE, "--use", "ideal", "--json", str(tmp_path / "f.json")])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "f.json").read_text())["model_key"] == "baseline_fit.model_state"
    rec["baseline_fit"]["model_state"]["names"][1] = "g_w"
    out.write_text(json.dumps(rec))
    r = runner.invoke(app, ["force", str(out), *ONE, "--use", "ideal"])
    assert r.exit_code == 2 and "baseline_fit.model_state.names[1] = 'g_w'" in r.output, r.output


@pytest.mark.parametrize("edit", ["off", "method"])
def test_json_values_of_the_wrong_kind_are_named_not_a_traceback(tmp_path, record, edit):
    """An effect's "off" that is not a list, a "method" that is not a string: one line or a clean run, never a
    traceback (review found a TypeError escaping)."""
    rec = copy.deepcopy(record)
    if edit == "off":
        rec["model_state"]["effects"] = [{"name": "saturation", "off": 3, "held": {}}]
        rec.pop("params")
    else:
        rec.pop("kind", None)
        rec.pop("ambfit_version", None)
        rec["method"] = ["least_squares"]
    r = _force(tmp_path, rec)
    assert r.exit_code in (0, 2) and r.exception is None or isinstance(r.exception, SystemExit), r.output
    if edit == "off":
        assert r.exit_code == 2 and "model_state.effects[0]" in r.output, r.output
