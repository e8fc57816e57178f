"""Every command on a user's own bearing (a 500 µm gap, 5 A coils, 40 µm back-up clearance), not the paper's.

The bearing description is read from TOML as a user gives it; the virtual rig is built around it
(:meth:`ambfit.rig.RigSpec.for_bearing`), and what the commands propose or map must follow its gap, clearance
and current limit.
"""

import json
import re

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from ambfit import rig
from ambfit.faces.cli import app
from ambfit.physics.bearing import Bearing
from ambfit.rig import limits
from ambfit.rig import protocol as P

runner = CliRunner()

USER_TOML = """name = "user 500"
pole_angle_deg = 22.5
turns_per_pole = 200
pole_area_mm2 = 80.0
nominal_gap_um = 500.0
backup_clearance_um = 40.0
max_current_A = 5.0
polarity = "NNSS"
iron_path_mm = 60.0
rotor_mass_kg = 2.5
"""

PAPER_BIASES_A = {0.8, 1.0, 1.2, 1.4, 1.5, 1.6, 1.8}
"""Every bias the paper ran (Tables 1-4) or the old fixed design grid offered [A]."""


@pytest.fixture(scope="module")
def toml(tmp_path_factory):
    path = tmp_path_factory.mktemp("bearing") / "user.toml"
    path.write_text(USER_TOML)
    return path


@pytest.fixture(scope="module")
def bearing(toml):
    return Bearing.from_toml(toml)


@pytest.fixture(scope="module")
def spec(bearing):
    return rig.RigSpec.for_bearing(bearing)


@pytest.fixture(scope="module")
def data(spec):
    """The paper's Table 2 protocol about the rig's bearing centre, on the user's bearing."""
    proto = P.paper_table2(iterations=5, center=spec.centre, loads=spec.loads)
    return rig.simulate(spec, proto, seed=4).data


def test_rig_for_a_bearing_takes_its_gap_lamination_and_load(bearing, spec):
    assert rig.RigSpec.for_bearing(rig.PAPER_RIG.bearing) == rig.PAPER_RIG
    # the paper rig's true gaps are 775/762 and 763/762 of its drawing; the same excess on a 500 µm drawing
    assert spec.g0 == pytest.approx((500e-6 * 775 / 762, 500e-6 * 763 / 762), rel=1e-12)
    assert spec.bearing.iron_path == 0.06 and spec.lamination == bearing.lamination
    load = spec.loads["rotor"]
    assert load.force_v == pytest.approx(2.5 * P.G_STANDARD * np.cos(np.pi / 4), rel=1e-12) and load.known


def test_simulate_with_a_bearing_fits_to_its_gap(toml, tmp_path):
    csv, truth, fitted = tmp_path / "d.csv", tmp_path / "t.json", tmp_path / "f.json"
    r = runner.invoke(app, ["simulate", "-o", str(csv), "--bearing", str(toml), "--truth", str(truth),
                            "--effect", "iron_reluctance:mu_r=3000"])
    assert r.exit_code == 0, r.output
    t = json.loads(truth.read_text())
    assert t["params"]["0"]["g_v0_um"] == pytest.approx(500 * 775 / 762, rel=1e-9)
    assert t["effects"][0]["l_fe"] == pytest.approx(0.06)        # the bearing's iron path, not the paper's 80 mm
    df = pd.read_csv(csv)
    assert df["load_N"].to_numpy() == pytest.approx(2.5 * P.G_STANDARD * np.cos(np.pi / 4), rel=1e-9)
    r = runner.invoke(app, ["identify", str(csv), "--bearing", str(toml), "--json", str(fitted)])
    assert r.exit_code == 0, r.output
    g = json.loads(fitted.read_text())["params"]["g_v0_um"]
    # the iron's l_fe / (2 mu_r) = 10 µm adds to the effective gap; nothing of the paper's 775 µm is left
    assert 500 < g["value"] < 530, g


def test_simulate_presets_fit_the_users_bearing(toml, tmp_path):
    # the rich sweep spans two thirds of the back-up clearance (±40 µm on the paper's 60 µm): inside this 40 µm one
    for preset in ("table2", "rich"):
        r = runner.invoke(app, ["simulate", "-o", str(tmp_path / f"{preset}.csv"), "--preset", preset,
                                "--bearing", str(toml)], env={"COLUMNS": "300"})
        assert r.exit_code == 0 and "beyond" not in r.output, (preset, r.output)
    df = pd.read_csv(tmp_path / "rich.csv")
    r = np.hypot(df["v_set_um"] + 33.3, df["w_set_um"] - 11.3)
    assert 30.0 < r.max() <= 40.0


def _run_recommended(spec, steps: pd.DataFrame) -> P.Protocol:
    return P.concat(*(P.grid([(s.v_set_um * 1e-6, s.w_set_um * 1e-6)], [s.bias_A], loads=spec.loads,
                             iteration=i + 1) for i, s in enumerate(steps.itertuples())))


def test_every_step_design_recommends_is_accepted_by_simulates_limit_check(spec, bearing):
    # on a bias sweep (four biases: the force law's bend with flux density shows) the design reaches out to the
    # clearance about the estimated centre
    from ambfit.estimation import design

    scale = bearing.max_current / rig.PAPER_RIG.bearing.max_current       # the rich preset on this bearing
    proto = P.rich(biases=tuple(b * scale for b in (1.0, 1.2, 1.4, 1.6)), center=spec.centre,
                   rotor_kg=bearing.rotor_mass, span=bearing.backup_clearance * 2 / 3)
    data = rig.simulate(spec, proto, seed=4).data
    rec = design.recommend(data, n_steps=8, bearing=bearing)
    assert rec.margin_reason is None
    proto = _run_recommended(spec, rec.steps)
    assert limits.limit_violations(spec, proto) == []
    sim = rig.simulate(spec, proto, seed=1)
    assert limits.limit_violations(spec, proto, currents=sim.physical_currents) == []
    # the grid it chose from reaches the clearance (less the origin's uncertainty), measured from the centre
    grid = rec.candidates
    lim = limits.step_limits(grid[["v_set_um", "w_set_um"]].to_numpy() * 1e-6, grid["bias_A"].to_numpy(),
                             spec.x0, bearing)
    assert lim.ok.all() and lim.distance.max() > 0.8 * bearing.backup_clearance


def test_design_candidates_scale_with_the_bearing(data, bearing):
    from ambfit.estimation import design

    grid = design.candidate_steps(bearing=bearing)
    assert grid["bias_A"].max() == pytest.approx(0.6 * 5.0) and grid["bias_A"].max() > 1.8
    assert not set(grid["bias_A"].round(6)) & PAPER_BIASES_A
    assert grid["v_set_um"].max() == pytest.approx(40 * 5 / 6, abs=0.05)
    rec = design.recommend(data, n_steps=6, bearing=bearing)
    assert (rec.steps["bias_A"] <= bearing.max_current).all()
    assert not set(rec.steps["bias_A"].round(6)) & PAPER_BIASES_A, rec.steps
    centre = np.array(rec.centre_um)
    r = np.hypot(rec.steps["v_set_um"] - centre[0], rec.steps["w_set_um"] - centre[1])
    assert (r <= 40.0).all() and rec.radius_um < 40.0


def test_design_command_on_the_users_bearing_passes_simulate(toml, data, spec, tmp_path):
    csv, js, out = tmp_path / "d.csv", tmp_path / "rec.json", tmp_path / "next.csv"
    data.to_csv(csv, index=False)
    r = runner.invoke(app, ["design", str(csv), "--bearing", str(toml), "--steps", "4", "--json", str(js)])
    assert r.exit_code == 0, r.output
    record = json.loads(js.read_text())
    steps = pd.DataFrame(record["steps"])
    assert record["bearing_centre_um"] == pytest.approx([-33.3, 11.3], abs=1.0) and record["max_distance_um"] < 40
    plan = tmp_path / "next.toml"
    plan.write_text("".join(f'[[block]]\nkind = "grid"\npoints_um = [[{s.v_set_um}, {s.w_set_um}]]\n'
                            f"biases_A = [{s.bias_A}]\n" for s in steps.itertuples()))
    r = runner.invoke(app, ["simulate", "-o", str(out), "--protocol", str(plan), "--bearing", str(toml)])
    assert r.exit_code == 0 and "beyond" not in r.output, r.output


def test_solution_space_is_centred_on_the_users_gap(data, bearing):
    from ambfit.estimation import conditioning, fit

    res = fit.fit(data[data["axis"] == "v"], bearing=bearing)
    space = conditioning.solution_space(data, "v", weights_at=res, bearing=bearing)
    g, x = space.minimum
    step = space.gap[1] - space.gap[0]
    assert not space.on_edge and space.widened == 0
    assert abs(g - res.value("g_v0")) <= step and abs(x - res.value("v0")) <= step
    # wide enough to show the valley: a quarter of the gap to each side, far beyond 10 standard errors here
    assert space.gap[0] <= 0.76 * g and space.gap[-1] >= 1.24 * g
    # the paper's Fig. 2 axes (600-1000 µm) do not hold a 508 µm gap: the minimum sits on their edge, said so
    paper = conditioning.solution_space(data, "v", weights_at=res, bearing=bearing, **conditioning.PAPER_FIG2)
    assert paper.on_edge and paper.minimum[0] == pytest.approx(600e-6)
    assert "edge of the grid" in paper.edge_text() and "EDGE" in paper.summary()


def test_solution_space_widens_until_the_minimum_is_inside(data, bearing, monkeypatch):
    from ambfit.estimation import conditioning

    # a first grid beside the minimum (508, 33) µm: doubled about its edge minimum, the next one holds it
    monkeypatch.setattr(conditioning, "_default_ranges", lambda *a: ((420e-6, 470e-6), (0.0, 20e-6)))
    space = conditioning.solution_space(data, "v", bearing=bearing)
    assert space.widened == 1 and not space.on_edge
    assert space.minimum[0] == pytest.approx(508e-6, abs=3e-6)


def test_solution_space_command_on_the_users_bearing(toml, data, tmp_path):
    csv, png = tmp_path / "d.csv", tmp_path / "map.png"
    data.to_csv(csv, index=False)
    r = runner.invoke(app, ["solution-space", str(csv), "--png", str(png), "--bearing", str(toml)],
                      env={"COLUMNS": "300"})
    assert r.exit_code == 0 and png.exists(), r.output
    minimum = re.search(r"minimum at gap ([\d.]+) µm", r.output)
    assert minimum and float(minimum.group(1)) == pytest.approx(500 * 775 / 762, abs=3.0), r.output
    assert "EDGE" not in r.output
    r = runner.invoke(app, ["solution-space", str(csv), "--png", str(png), "--bearing", str(toml),
                            "--gap-um", "600,1000", "--origin-um", "-100,100"], env={"COLUMNS": "300"})
    assert r.exit_code == 3 and "minimum lies on the edge of the grid" in r.output, r.output


def test_report_section_says_when_the_minimum_is_on_the_edge(data, bearing):
    from ambfit.estimation import conditioning, fit
    from ambfit.faces.report import dataset

    res = fit.fit(data, bearing=bearing)
    spaces = {"v": conditioning.solution_space(data, "v", weights_at=res, bearing=bearing, **conditioning.PAPER_FIG2),
              "w": conditioning.solution_space(data, "w", weights_at=res, bearing=bearing)}
    out = dataset.solution_space(spaces, res)
    assert len(out["edges"]) == 1 and out["edges"][0].startswith("axis v: the minimum lies on the edge")


FITTING_COMMANDS = ("identify", "diagnose", "sample", "solution-space", "design", "report")
"""Every command that fits data: each takes the readings' noise the same way."""


@pytest.mark.parametrize("command", FITTING_COMMANDS)
def test_every_fitting_command_takes_the_declared_noise(command):
    import inspect

    from ambfit.faces.cli.fitting import CurrentNoiseOption, PositionNoiseOption

    callback = next(c.callback for c in app.registered_commands
                    if (c.name or c.callback.__name__.replace("_", "-")) == command)
    params = inspect.signature(callback, eval_str=True).parameters
    # the one definition identify uses, not a copy
    assert params["current_noise_ma"].annotation is CurrentNoiseOption, command
    assert params["position_noise_um"].annotation is PositionNoiseOption, command
    r = runner.invoke(app, [command, "--help"], env={"COLUMNS": "200"})
    assert "--current-noise-ma" in r.output and "--position-noise-um" in r.output


def test_diagnose_without_std_columns_reports_the_declared_noise(tmp_path):
    from ambfit.physics.effects import Saturation

    # saturated iron that the ideal law does not fit: estimated from the residuals, the current noise would be
    # the model error (about 10 mA), not the rig's 0.6 mA
    sim = rig.simulate(rig.PAPER_RIG, P.rich(center=(-33.3e-6, 11.3e-6)), [Saturation(b_sat=1.2)], seed=1)
    csv, js = tmp_path / "sweep.csv", tmp_path / "diag.json"
    sim.data.drop(columns=[c for c in sim.data if "_std_" in c]).to_csv(csv, index=False)
    r = runner.invoke(app, ["diagnose", str(csv), "--json", str(js), "--current-noise-ma", "0.6",
                            "--position-noise-um", "0.1"], env={"COLUMNS": "300"})
    assert r.exit_code == 0, r.output
    floor = json.loads(js.read_text())["noise_floor"]
    assert floor["source"] == "current 0.6 mA declared; position 0.1 µm declared", floor
    assert "current 0.6 mA declared" in r.output and "estimated" not in r.output.split("\n")[0]


@pytest.mark.parametrize("user", [False, True], ids=["paper rig, the README's sat.csv", "user's bearing"])
def test_design_on_a_protocol_blind_to_saturation_stays_within_the_rigs_clearance(user, bearing):
    # Table 2's two biases cannot show iron saturating at 1.2 T: the ideal law fits (χ²/dof < 1.2) with its
    # bearing centre 17 µm (paper rig) or 37 µm (the user's, 40 µm clearance) off the rig's.  Steps kept within the
    # estimated centre's clearance would hit the back-up bearing; the design keeps them among the positions
    # already run (their hull lies inside the clearance, wherever the centre is), and simulate accepts them all.
    from ambfit.estimation import design
    from ambfit.estimation.fit import fit
    from ambfit.physics.effects import Saturation

    spec = rig.RigSpec.for_bearing(bearing) if user else rig.PAPER_RIG
    proto = P.paper_table2(center=spec.centre, loads=spec.loads)
    data = rig.simulate(spec, proto, [Saturation(b_sat=1.2)], seed=1).data
    res = fit(data, bearing=spec.bearing)
    assert res.adequate
    rec = design.recommend(data, n_steps=8, result=res)
    assert rec.margin_reason and "2 biases" in rec.margin_reason and "positions already run" in rec.limits
    assert limits.limit_violations(spec, _run_recommended(spec, rec.steps)) == []
    shift = np.hypot(*(np.array(rec.centre_um) * 1e-6 + np.asarray(spec.x0)))
    assert shift > 0.25 * spec.bearing.backup_clearance             # the blind spot's bias is real here
    # what the estimated centre's clearance alone would have allowed: the rig refuses some of it
    grid = design.candidate_steps(tuple(round(c) for c in rec.centre_um), bearing=spec.bearing)
    pts = grid[["v_set_um", "w_set_um"]].to_numpy() * 1e-6
    by_estimate = limits.step_limits(pts, grid["bias_A"].to_numpy(), -np.array(rec.centre_um) * 1e-6, spec.bearing)
    by_rig = limits.step_limits(pts, grid["bias_A"].to_numpy(), spec.x0, spec.bearing)
    assert (by_estimate.ok & ~by_rig.ok).any()
    assert design.inside_visited(rec.steps[["v_set_um", "w_set_um"]].to_numpy() * 1e-6,
                                 data[["v_um", "w_um"]].to_numpy() * 1e-6).all()


def test_inside_visited_is_the_hull_of_the_positions_run():
    from ambfit.estimation import design

    square = np.array([[0, 0], [10, 0], [10, 10], [0, 10]]) * 1e-6
    pts = np.array([[5, 5], [10, 5], [10.3, 5], [11, 5], [-1, -1]]) * 1e-6
    assert design.inside_visited(pts, square).tolist() == [True, True, True, False, False]
    diagonal = np.array([[-20, -20], [20, 20], [-20.05, -19.98]]) * 1e-6     # Table 2's pairs, with noise
    pts = np.array([[0, 0], [10, 10.2], [10, 11], [25, 25]]) * 1e-6
    assert design.inside_visited(pts, diagonal).tolist() == [True, True, False, False]
