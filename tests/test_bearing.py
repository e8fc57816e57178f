"""The bearing description: contract section 4 files, derived quantities, errors that name the key."""

import math

import numpy as np
import pytest

from ambfit import PAPER_BEARING, Bearing
from ambfit.physics.bearing import BearingError

FEM_TOML = """
name = "8-pole test bearing"
pole_angle_deg = 22.5
turns_per_pole = 160
pole_area_mm2 = 116.0
nominal_gap_um = 762.0
backup_clearance_um = 60.0
max_current_A = 3.0
polarity = "NSNS"
iron_path_mm = 80.0
position_gain_tolerance = 0.0025
current_gain_tolerance = 0.001
extra_key = "kept by the contract, ignored here"

[material]
B_T = [0.0, 0.4, 0.8, 1.2, 1.4, 1.6]
H_A_per_m = [0.0, 64.0, 129.0, 225.0, 442.0, 2033.0]
"""


def test_paper_bearing_reproduces_the_published_load_capacity():
    # The paper: 53.4 N at 3.0 A on one coil, rotor centred at 762 µm.
    assert PAPER_BEARING.load_capacity() == pytest.approx(53.4, rel=1e-12)
    assert PAPER_BEARING.nominal_gap == 762e-6
    assert math.degrees(PAPER_BEARING.pole_angle) == pytest.approx(22.5)


def test_contract_file_in_si_units(tmp_path):
    path = tmp_path / "b.toml"
    path.write_text(FEM_TOML)
    b = Bearing.from_toml(path)
    assert b.turns_per_pole == 160 and b.horseshoe_turns == 320
    assert b.pole_area == pytest.approx(116e-6)
    assert b.backup_clearance == pytest.approx(60e-6)
    assert b.polarity == "NSNS"
    assert b.b_curve[-1] == 1.6 and b.h_curve[-1] == 2033.0
    assert b.extra_keys == ("extra_key",)        # allowed by the contract, recorded, not used
    # k = 0.25 mu0 A (2N)^2 cos(alpha) = 0.25 * 4e-7 pi * 116e-6 * 320^2 * cos(22.5°) = 3.44765e-6
    k = 0.25 * 4e-7 * math.pi * 116e-6 * 320**2 * math.cos(math.radians(22.5))
    assert b.with_(lamination=1.0).force_constant() == pytest.approx(k, rel=1e-14)
    assert b.force_constant(1.0) == pytest.approx(3.44765e-6, rel=1e-5)
    # B = mu0 N i / g for N = 160 turns per pole: 4e-7 pi * 160 * 3 / 762e-6 = 0.79157 T
    assert b.flux_density(3.0, 762e-6) == pytest.approx(4e-7 * math.pi * 160 * 3.0 / 762e-6, rel=1e-14)


@pytest.mark.parametrize("text, words", [
    ('turns_per_pole = "many"', "turns_per_pole must be a number"),
    ("nominal_gap_um = -5.0", "nominal_gap must be a positive number"),
    ('polarity = "NNNN"', "polarity must be one of NNSS, NSNS"),
    ("[material]\nB_T = [0.0, 1.0]\nH_A_per_m = [0.0]", "must have the same length, at least 2, got 2 and 1"),
    ("[material]\nB_T = [0.0, 1.0, 1.0]\nH_A_per_m = [0.0, 1.0, 2.0]", "B_T must ascend, got 1.0 then 1.0"),
    ("[material]\nB_T = [0.0, 1.0]\nH_A_per_m = [-5.0, 300.0]", "given for B >= 0"),
    ("[material]\nB_T = [0.0, 1.0]\nH_A_per_m = [0.0, \"x\"]", "must be lists of numbers"),
    ("[material]\nB_T = [0.0, 1.0, 1.5]\nH_A_per_m = [0.0, 300.0, 200.0]",
     "H_A_per_m must not fall as B_T rises.*300.0 then 200.0"),
    ("[material]\nB_T = [-1.0, 1.0]\nH_A_per_m = [-300.0, 300.0]", "given for B >= 0"),
    ("[material]\nB_T = [0.5, 1.0]\nH_A_per_m = [0.0, 300.0]", "give H > 0 there"),
    ("nominal_gap_um = ", "not valid TOML"),
    ("nominal_gap = 762.0", "unknown key 'nominal_gap'; did you mean 'nominal_gap_um'"),
    ("turns_per_poles = 160", "did you mean 'turns_per_pole'"),
])
def test_bad_files_name_the_file_and_key(tmp_path, text, words):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(BearingError, match=words) as info:
        Bearing.from_toml(path)
    assert str(path) in str(info.value)


def test_directory_and_missing_file(tmp_path):
    with pytest.raises(BearingError, match="is a directory"):
        Bearing.from_toml(tmp_path)
    with pytest.raises(BearingError, match="cannot read"):
        Bearing.from_toml(tmp_path / "nope.toml")


def test_bearing_is_immutable_and_hashable():
    with pytest.raises(AttributeError):
        PAPER_BEARING.nominal_gap = 1.0
    assert hash(PAPER_BEARING.with_(turns_per_pole=100.0)) != hash(PAPER_BEARING)


def test_shipped_paper_file_is_the_default_bearing():
    from pathlib import Path

    b = Bearing.from_toml(Path(__file__).resolve().parents[1] / "data" / "paper" / "bearing.toml")
    assert b.force_constant() == pytest.approx(PAPER_BEARING.force_constant(), rel=1e-6)   # pole area rounded
    for name in ("pole_angle", "turns_per_pole", "nominal_gap", "backup_clearance", "max_current", "polarity",
                 "iron_path", "lamination", "pole_width", "position_gain_tolerance", "current_gain_tolerance"):
        assert getattr(b, name) == pytest.approx(getattr(PAPER_BEARING, name)) if name != "polarity" else \
            getattr(b, name) == getattr(PAPER_BEARING, name), name


def test_a_description_survives_its_own_dict():
    """to_dict and from_dict are inverses for every field a bearing description has (a model file records it)."""
    import dataclasses

    other = dataclasses.replace(PAPER_BEARING, rotor_mass=2.5, nominal_gap=500e-6, max_current=5.0)
    back = Bearing.from_dict(other.to_dict())
    for f in dataclasses.fields(Bearing):
        a, b = getattr(other, f.name), getattr(back, f.name)
        assert (a == pytest.approx(b, rel=1e-12)) if isinstance(a, float) else a == b, f.name


def test_a_bh_table_from_above_zero_is_completed_with_the_origin(tmp_path):
    # data sheets often start at 0.1 T or more: soft iron has H = 0 at B = 0, which the circuit's odd curve needs
    path = tmp_path / "b.toml"
    path.write_text("[material]\nB_T = [0.5, 1.0, 1.5]\nH_A_per_m = [80.0, 200.0, 2000.0]\n")
    b = Bearing.from_toml(path)
    assert b.b_curve == (0.0, 0.5, 1.0, 1.5) and b.h_curve == (0.0, 80.0, 200.0, 2000.0)
    direct = PAPER_BEARING.with_(b_curve=np.array([0.5, 1.0]), h_curve=[80, 200])
    assert direct.b_curve == (0.0, 0.5, 1.0) and direct.h_curve == (0.0, 80.0, 200.0)
    assert direct.with_(lamination=0.9).b_curve == direct.b_curve      # completed once, then kept as it is
    hash(direct)                                                        # (a static argument of compiled fits)
    # kept as given: H > 0 at B = 0 (a coercive field, not modelled) and H level between two points
    kept = PAPER_BEARING.with_(b_curve=(0.0, 0.5, 1.0), h_curve=(5.0, 80.0, 80.0))
    assert kept.b_curve == (0.0, 0.5, 1.0) and kept.h_curve == (5.0, 80.0, 80.0)
    # a bearing built in code is checked as a file's table is, its messages naming the fields
    for b_curve, h_curve, words in [((0.0, 1.0, 1.5), (0.0, 300.0, 200.0), "h_curve must not fall as b_curve rises"),
                                    ((0.0, float("nan")), (0.0, 1.0), "must be finite numbers"),
                                    ((0.0, 1.0), (0.0,), "must have the same length")]:
        with pytest.raises(BearingError, match=words):
            PAPER_BEARING.with_(b_curve=b_curve, h_curve=h_curve)
