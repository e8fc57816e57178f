"""The identified bearing linearised for a rotor model (k_i, k_s), and as a ROSS bearing element (ambfit[ross])."""

import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from ambfit import rig
from ambfit.estimation import bayes
from ambfit.estimation.fit import fit
from ambfit.estimation.measure import FittedModel, predict
from ambfit.faces.cli import app
from ambfit.physics.effects import Saturation
from ambfit.rig import protocol as P
from ambfit.rotordynamics import Linearisation, linearise

SPEC = rig.PAPER_RIG


@pytest.fixture(scope="module")
def sat_data():
    """The rich design on a rig whose iron saturates: a model with saturation, and the ideal law, fitted to it."""
    return rig.simulate(SPEC, P.rich(center=SPEC.centre), [Saturation(b_sat=1.0)], seed=2).data


@pytest.fixture(scope="module")
def sat_fit(sat_data):
    return fit(sat_data, [Saturation()])


def _finite_differences(res, axis, bias, x, y, h_i=1e-5, h_x=1e-9):
    """Central differences of ambfit's own force model (measure.predict) in the control current and position."""
    import pandas as pd

    def force(i_c, xx):
        row = {"axis": axis, "i_top_A": bias + i_c, "i_bottom_A": bias - i_c, "bias_A": bias,
               "v_um": (xx if axis == "v" else y) * 1e6, "w_um": (y if axis == "v" else xx) * 1e6,
               "experiment": "x", "iteration": 1, "time_s": 0.0}
        other = {**row, "axis": "w" if axis == "v" else "v", "i_top_A": bias, "i_bottom_A": bias}
        return float(predict(res, pd.DataFrame([row, other]))[0])

    k_i = (force(h_i, x) - force(-h_i, x)) / (2 * h_i)
    k_s = (force(0.0, x + h_x) - force(0.0, x - h_x)) / (2 * h_x)
    return k_i, k_s


@pytest.mark.parametrize("axis", ["v", "w"])
def test_k_i_and_k_s_are_the_derivatives_of_the_identified_model(sat_fit, axis):
    # autodiff of the model with its effect against central differences of the same model's predicted force,
    # at the bias and the bearing centre
    lin = linearise(sat_fit, axis, 1.3, draws=0)
    other = "w" if axis == "v" else "v"
    k_i, k_s = _finite_differences(sat_fit, axis, 1.3, -sat_fit.value(f"{axis}0"), -sat_fit.value(f"{other}0"))
    assert lin.k_i == pytest.approx(k_i, rel=1e-6) and lin.k_s == pytest.approx(k_s, rel=1e-5)
    assert lin.position == pytest.approx(-sat_fit.value(f"{axis}0"))


def test_the_ideal_law_linearises_to_its_closed_form():
    # Eq. 4 at the centre: k_i = 4 k b / g0², k_s = 4 k b² cos α / g0³ (the position enters the pole gap through
    # cos α), a hand computation independent of the model code
    data = rig.simulate(SPEC, P.paper_table2(center=SPEC.centre), seed=1).data
    res = fit(data)
    lin = linearise(res, "v", 1.5, draws=0)
    k, g = res.value("k_v"), res.value("g_v0")
    cos_alpha = math.cos(math.radians(22.5))
    assert lin.k_i == pytest.approx(4 * k * 1.5 / g**2, rel=1e-9)
    assert lin.k_s == pytest.approx(4 * k * 1.5**2 * cos_alpha / g**3, rel=1e-9)


def test_saturation_lowers_both_and_the_errors_follow_the_parameters(sat_data, sat_fit):
    # the saturating bearing linearised with its effect: both coefficients below the ideal law's at the same bias
    # (the ideal law, fitted to the same readings, absorbs part of the bend into gap and k), with standard errors
    # from the parameters' covariance: the delta method's, to the sampling error of 400 draws
    lin = linearise(sat_fit, "v", 1.6)
    ideal = linearise(fit(sat_data), "v", 1.6)
    assert lin.model == "saturation" and lin.k_i < ideal.k_i and lin.k_s < ideal.k_s
    fm = FittedModel.from_result(sat_fit)
    eps = np.sqrt(np.diag(fm.cov)) * 1e-3
    jac = np.array([[(g1 - g0) / (2 * e) for g1, g0 in zip(
        (lambda hi: (hi.k_i, hi.k_s))(linearise(fm.at(fm.values + e * np.eye(len(eps))[j]), "v", 1.6, draws=0)),
        (lambda lo: (lo.k_i, lo.k_s))(linearise(fm.at(fm.values - e * np.eye(len(eps))[j]), "v", 1.6, draws=0)))]
        for j, e in enumerate(eps)]).T
    delta = np.sqrt(np.diag(jac @ fm.cov @ jac.T))
    assert lin.k_i_std == pytest.approx(delta[0], rel=0.12) and lin.k_s_std == pytest.approx(delta[1], rel=0.12)


def test_a_posterior_linearises_from_its_draws():
    data = rig.simulate(SPEC, P.paper_table2(center=SPEC.centre), seed=1).data
    ls = fit(data)
    post = bayes.sample(data, n_ensembles=2, n_steps=400, max_steps=400, seed=1, ls=ls)
    a, b = linearise(post, "w", 1.5), linearise(ls, "w", 1.5)
    assert a.k_i == pytest.approx(b.k_i, rel=2e-3) and a.k_s == pytest.approx(b.k_s, rel=2e-3)
    assert a.k_i_std == pytest.approx(b.k_i_std, rel=0.25)


def test_without_known_loads_there_is_no_force_to_linearise():
    frame = rig.simulate(SPEC, P.paper_table2(center=SPEC.centre), seed=1).data
    frame = frame.assign(load_N=np.nan)
    with pytest.raises(ValueError, match="k_v is not identified"):
        linearise(fit(frame), "v", 1.5)


def test_the_closed_loop_is_rosss_convention():
    # k_eq = -k_s + k_i k_amp k_sense Re C(jω), c_eq = k_i k_amp k_sense Im C(jω)/ω for a PD with a filtered
    # derivative: at low frequency the stiffness is -k_s + k_i kp (k_amp k_sense = 1), the damping k_i kd
    lin = Linearisation("v", 1.5, 0.0, k_i=30.0, k_s=6e4, cov=np.zeros((2, 2)), model="ideal")
    k, c = lin.coefficients([1.0], kp=5000.0, kd=3.0, n_f=1e6)
    assert k[0] == pytest.approx(-6e4 + 30 * 5000, rel=1e-6) and c[0] == pytest.approx(30 * 3.0, rel=1e-6)


def test_ross_bearing_element_has_the_coefficients_ross_itself_computes():
    # ROSS's MagneticBearingElement from its own geometry: its ki and ks (ks = -k_s) in a Linearisation, through
    # bearing_element, give the same kxx, kxy, cxx, ... at every frequency
    rs = pytest.importorskip("ross")
    from ambfit.rotordynamics import bearing_element

    mb = rs.MagneticBearingElement(n=0, g0=1e-3, i0=1.0, ag=1e-4, nw=200, kp_pid=1.5e4, kd_pid=8.0, k_amp=1.0,
                                   k_sense=1.0)
    lin = {ax: Linearisation(ax, 1.0, 0.0, k_i=float(np.ravel(mb.ki)[0]), k_s=-float(np.ravel(mb.ks)[0]),
                             cov=np.zeros((2, 2)), model="ideal") for ax in "vw"}
    el = bearing_element(lin["v"], lin["w"], 0, kp=1.5e4, kd=8.0, frequency=mb.frequency)
    for attr in ("kxx", "kxy", "kyx", "kyy", "cxx", "cxy", "cyx", "cyy"):
        np.testing.assert_allclose(getattr(el, attr), getattr(mb, attr), rtol=1e-9, atol=1e-9, err_msg=attr)


def test_ross_is_imported_only_for_the_element_and_quietly(capfd):
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", "import ambfit.rotordynamics, sys; print(sys.modules.get('ross') is not None)"],
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
    pytest.importorskip("ross")
    code = "from ambfit.rotordynamics import ross; ross()"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout == "" and out.stderr == "", (out.stdout, out.stderr)


def test_linearise_command_reads_an_identify_model(tmp_path, sat_data):
    csv, model, js = tmp_path / "sat.csv", tmp_path / "sat.json", tmp_path / "lin.json"
    sat_data.to_csv(csv, index=False)
    runner = CliRunner()
    r = runner.invoke(app, ["identify", str(csv), "--effect", "saturation", "--json", str(model), "--no-force-check"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["linearise", str(model), "--bias-a", "1.6", "--json", str(js)])
    assert r.exit_code == 0, r.output
    rec = json.loads(js.read_text())
    by_axis = {e["axis"]: e for e in rec["axes"]}
    res = fit(sat_data, [Saturation()])
    assert by_axis["v"]["k_i_N_per_A"] == pytest.approx(linearise(res, "v", 1.6, draws=0).k_i, rel=1e-6)
    assert by_axis["w"]["model"] == "saturation" and "k_s" in r.output


def test_an_anisotropic_bearing_puts_v_and_w_where_the_docstring_says():
    # k_v != k_w: the x-y stiffness matrix has the v axis (cos θ, sin θ) and the w axis (-sin θ, cos θ) as its
    # eigenvectors, with each axis' own closed-loop stiffness and damping as eigenvalues
    pytest.importorskip("ross")
    from ambfit.rotordynamics import bearing_element

    v = Linearisation("v", 1.5, 0.0, k_i=30.0, k_s=6e4, cov=np.zeros((2, 2)), model="ideal")
    w = Linearisation("w", 1.5, 0.0, k_i=36.0, k_s=7e4, cov=np.zeros((2, 2)), model="ideal")
    theta = math.radians(30.0)
    omega = np.array([50.0, 500.0])
    el = bearing_element(v, w, 0, kp=1e4, kd=5.0, frequency=omega, sensors_axis_rotation=theta)
    ev, ew = np.array([math.cos(theta), math.sin(theta)]), np.array([-math.sin(theta), math.cos(theta)])
    for i, _ in enumerate(omega):
        k = np.array([[el.kxx[i], el.kxy[i]], [el.kyx[i], el.kyy[i]]])
        c = np.array([[el.cxx[i], el.cxy[i]], [el.cyx[i], el.cyy[i]]])
        (kv, cv), (kw, cw) = (lin.coefficients(omega[i:i + 1], kp=1e4, kd=5.0) for lin in (v, w))
        np.testing.assert_allclose(k @ ev, kv[0] * ev, rtol=1e-9)
        np.testing.assert_allclose(k @ ew, kw[0] * ew, rtol=1e-9)
        np.testing.assert_allclose(c @ ev, cv[0] * ev, rtol=1e-9)
        np.testing.assert_allclose(c @ ew, cw[0] * ew, rtol=1e-9)
