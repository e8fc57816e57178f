"""The GUM uncertainty budget (:mod:`ambfit.estimation.budget`) against numbers computed independently.

Whether its combined interval covers the truth at 95 % when the calibration really is off within its tolerances
is a statistical study: benchmarks/uncertainty_budget.py (reports/benchmarks/uncertainty_budget.md).
"""

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from ambfit import rig
from ambfit.estimation.budget import budget, fit_instead, standard_uncertainty, terms
from ambfit.estimation.fit import fit
from ambfit.faces.cli import app
from ambfit.physics.bearing import PAPER_BEARING, Bearing, BearingError
from ambfit.rig import protocol

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT / "data" / "paper_table2.csv"


@pytest.fixture(scope="module")
def table2():
    spec = rig.PAPER_RIG
    return rig.simulate(spec, protocol.paper_table2(center=spec.centre), seed=7).data


@pytest.fixture(scope="module")
def fitted(table2):
    res = fit(table2)
    return res, budget(table2, res)


def test_standard_uncertainty_of_a_tolerance():
    # GUM 4.3.7: a uniform ±a has u = a / sqrt(3); a "normal" tolerance is already a standard uncertainty
    assert standard_uncertainty(0.003, "uniform") == pytest.approx(0.003 / 1.7320508075688772, rel=1e-15)
    assert standard_uncertainty(0.003, "normal") == 0.003


def test_the_terms_are_the_declared_channels(table2):
    names = [t.name for t in terms(table2, PAPER_BEARING)]
    assert len(names) == 11 and len(set(names)) == 11           # 4 gains, 4 zeros, 2 position gains, the loads
    assert "current gain, axis v, top" in names and "load scale" in names
    assert [t.name for t in terms(table2, PAPER_BEARING.with_(load_scale_tolerance=0.0))] == names[:-1]


def test_a_gain_error_moves_the_origin_as_its_sensitivity_says(table2, fitted):
    # an independent measurement: the v-axis top current read 0.5 % high (the tester's probe) and refitted from
    # scratch; the budget's shift at one u (0.1 %/sqrt 3), scaled to 0.5 %, predicts it within 3 %
    res, b = fitted
    k = [t.name for t in b.terms].index("current gain, axis v, top")
    high = table2.assign(i_top_A=np.where(table2["axis"] == "v", table2["i_top_A"] * 1.005, table2["i_top_A"]))
    moved = fit(high).value("v0") - res.value("v0")
    predicted = b.contributions[k][res.names.index("v0")] * 0.005 / b.terms[k].u
    assert abs(moved) > 5 * res.error("v0")                      # far outside the statistical error bar
    assert predicted == pytest.approx(moved, rel=0.03)


def test_the_load_scale_moves_k_alone_and_by_its_own_share(fitted):
    # loads read (1 + d) times too heavy make k (1 + d) times too large and leave gaps and origins (the force law
    # is linear in k): the term's contribution to k_v is k_v u exactly, u = 0.001 / sqrt(3) for a uniform ±0.1 %
    res, b = fitted
    k = [t.name for t in b.terms].index("load scale")
    assert b.terms[k].u == pytest.approx(0.001 / math.sqrt(3.0), rel=1e-15)
    c = dict(zip(b.names, b.contributions[k]))
    assert c["k_v"] == pytest.approx(res.value("k_v") * b.terms[k].u, rel=1e-5)
    assert abs(c["g_v0"]) < 1e-3 * res.error("g_v0") and abs(c["v0"]) < 1e-3 * res.error("v0")


def test_terms_whose_refits_fail_are_named_and_add_nothing(fitted, table2):
    from ambfit.estimation.core import FitError

    res, _ = fitted

    def refit(table):
        raise FitError("no fit")

    b = budget(table2, res, refit=refit)
    assert len(b.failed) == 11 and b.to_json()["failed"] == list(b.failed)
    assert b.u_combined("v0") == pytest.approx(res.error("v0"), rel=1e-12)


def test_identify_reports_std_and_the_combined_uncertainty(tmp_path):
    out = tmp_path / "fit.json"
    r = CliRunner().invoke(app, ["identify", str(DEFAULT), "--json", str(out)])
    assert r.exit_code == 0, r.output
    assert "u_combined" in r.output and "largest calibration term" in r.output
    rec = json.loads(out.read_text())
    res = fit(pd.read_csv(DEFAULT))
    for key, name in (("v0_um", "v0"), ("g_w0_um", "g_w0")):
        p = rec["params"][key]
        assert p["std"] == pytest.approx(res.error(name) * 1e6, rel=1e-9)      # std stays the statistical error
        assert p["u_combined"] > p["std"]
        assert p["u_combined"] == pytest.approx(math.sqrt(sum(t["u"] ** 2 for t in p["budget"])), rel=1e-12)
        assert p["budget"][0]["share"] >= p["budget"][-1]["share"]
    assert len(rec["uncertainty_budget"]["terms"]) == 11 and rec["uncertainty_budget"]["failed"] == []


def test_the_bearing_file_declares_the_tolerances(tmp_path):
    toml = tmp_path / "b.toml"
    toml.write_text('current_offset_tolerance_mA = 2.5\nload_scale_tolerance = 0.002\ntolerance_distribution = '
                    '"normal"\n')
    b = Bearing.from_toml(toml)
    assert (b.current_offset_tolerance, b.load_scale_tolerance, b.tolerance_distribution) == (2.5e-3, 0.002, "normal")
    assert Bearing.from_dict(b.to_dict()).tolerance_distribution == "normal"
    toml.write_text('tolerance_distribution = "triangular"\n')
    with pytest.raises(BearingError, match="tolerance_distribution must be one of uniform, normal"):
        Bearing.from_toml(toml)


def test_current_zeros_a_model_fits_are_not_budgeted_again():
    # the rich design (four biases) identifies each coil's current zero: a model with current_offset fits them,
    # their error is in its statistical covariance, and the budget holds only the other terms
    from ambfit.physics.effects import CurrentOffset

    spec = rig.PAPER_RIG
    data = rig.simulate(spec, protocol.rich(center=spec.centre), seed=3).data
    res = fit(data, [CurrentOffset()])
    b = budget(data, res)
    names = [t.name for t in b.terms]
    assert b.fitted_terms == ("current zero",) and not [n for n in names if n.startswith("current zero")]
    assert "current gain, axis v, top" in names and len(names) == 7
    plain = budget(data, fit(data))
    assert plain.fitted_terms == () and len(plain.terms) == 11


def test_identify_fits_the_current_zeros_where_the_data_determine_them(tmp_path):
    # zeros declared to ±10 mA dominate the origins' uncertainty; the rich design's four biases determine them
    # (their prior shares are small), Table 2's two do not: the first is fitted with current_offset (and says so),
    # or only advised with --no-fit-current-zeros; the second keeps the ideal law
    toml = tmp_path / "b.toml"
    toml.write_text("current_offset_tolerance_mA = 10.0\n")
    spec = rig.PAPER_RIG
    rich = tmp_path / "rich.csv"
    rig.simulate(spec, protocol.rich(center=spec.centre), seed=3).data.to_csv(rich, index=False)
    runner = CliRunner()
    out = tmp_path / "rich.json"
    r = runner.invoke(app, ["identify", str(rich), "--bearing", str(toml), "--json", str(out)])
    assert r.exit_code == 0, r.output
    rec = json.loads(out.read_text())
    done = rec["uncertainty_budget"]["current_zeros_fitted"]
    assert done["effect"] == "current_offset" and done["zero_share"] > 0.25
    assert done["u_combined_fitted"] < 0.5 * done["u_combined"] and "the fit below does" in r.output
    assert [e["name"] for e in rec["model_state"]["effects"]] == ["current_offset"]
    assert rec["uncertainty_budget"]["fitted_instead"] == ["current zero"]
    worst = done["parameter"]
    assert rec["params"][f"{worst}_um"]["u_combined"] == pytest.approx(done["u_combined_fitted"], rel=1e-9)

    out = tmp_path / "advised.json"
    r = runner.invoke(app, ["identify", str(rich), "--bearing", str(toml), "--json", str(out),
                            "--no-fit-current-zeros"])
    assert r.exit_code == 0, r.output
    rec = json.loads(out.read_text())
    advice = rec["uncertainty_budget"]["fit_instead"]
    assert advice == {**done, "text": advice["text"]} and "--effect current_offset" in r.output
    assert rec["model_state"]["effects"] == [] and rec["params"][f"{worst}_um"]["u_combined"] == pytest.approx(
        advice["u_combined"], rel=1e-9)

    out = tmp_path / "t2.json"
    r = runner.invoke(app, ["identify", str(DEFAULT), "--bearing", str(toml), "--json", str(out)])
    assert r.exit_code == 0, r.output
    assert not {"fit_instead", "current_zeros_fitted"} & set(json.loads(out.read_text())["uncertainty_budget"])


@pytest.mark.parametrize("distribution", ["uniform", "normal"])
def test_marginalising_the_calibration_adds_its_variance_to_the_draws(fitted, distribution):
    # the shifts' variance is Σ (c_k u_k)² = the type-B variance, whichever distribution the errors have
    res, b = fitted
    n = 200_000
    draws = {name: np.zeros(n) for name in ("g_v0", "v0", "k_w")}
    b = dataclasses.replace(b, distribution=distribution)
    wide = b.propagate(draws, np.random.default_rng(1))
    for name in draws:
        i = b.names.index(name)
        # 200,000 draws: the sample variance is within 1 % of the true one (its relative sd is 0.3 %)
        assert np.var(wide[name]) == pytest.approx(b.cov_b[i, i], rel=0.01), name
    # the shape, not only the variance: one term's shifts are uniform (kurtosis 1.8) or normal (3.0)
    one = dataclasses.replace(b, terms=b.terms[:1], contributions=b.contributions[:1])
    x = one.propagate({"v0": np.zeros(n)}, np.random.default_rng(2))["v0"]
    kurtosis = np.mean((x - x.mean()) ** 4) / np.var(x) ** 2
    assert kurtosis == pytest.approx(1.8 if distribution == "uniform" else 3.0, abs=0.05)


def test_a_law_that_does_not_fit_keeps_its_zeros_unfitted():
    # a saturating rig on the rich design: the ideal law misses by χ²/dof ~1500, and current offsets fitted to it
    # would absorb that misfit rather than measure the channels' zeros: no fit instead, however wide the zeros
    from ambfit.physics.effects import Saturation

    spec = rig.PAPER_RIG
    data = rig.simulate(spec, protocol.rich(center=spec.centre), [Saturation(b_sat=1.0)],
                        seed=2).data
    wide = dataclasses.replace(PAPER_BEARING, current_offset_tolerance=10e-3)
    res = fit(data, bearing=wide)
    assert res.adequate is False
    assert fit_instead(data, res, budget(data, res)) is None
    clean = rig.simulate(spec, protocol.rich(center=spec.centre), seed=3).data
    ok = fit(clean, bearing=wide)
    assert ok.adequate and fit_instead(clean, ok, budget(clean, ok)) is not None
