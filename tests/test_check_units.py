"""``ambfit check`` judges every column against the bearing description, as identify does (issue 24).

Each probe damages the bundled default data the way a unit mistake does; ``check`` must exit 2 naming the row,
the column, the value and the likely unit, and ``identify`` must stop on the same finding.  The bundled data
and the FEM bearing's slice (with its own description) must stay clean.
"""

from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from ambfit.estimation import plausibility
from ambfit.faces.cli import app
from ambfit.physics.bearing import PAPER_BEARING

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT / "data" / "paper_table2.csv"
FEM_SLICE, FEM_BEARING = ROOT / "tests" / "data" / "fem_slice.csv", ROOT / "tests" / "data" / "fem_dev.toml"
runner = CliRunner()


@pytest.fixture(scope="module")
def clean():
    return pd.read_csv(DEFAULT)


def _one_current_in_ma(d):
    d.loc[5, "i_top_A"] = 1400.0


def _loads(d):
    d.loc[6, ["load_N", "load_id"]] = (-1e6, "hung")


def _loads_in_mn(d):
    d["load_N"] = d["load_N"] * 1e3


def _positions_in_metres(d):
    for c in ("v_um", "w_um"):          # the set-points stay in µm: the readings alone are in metres
        d[c] = d[c] * 1e-6


def _positions_in_tenths(d):
    for c in ("v_um", "w_um", "v_set_um", "w_set_um"):
        d[c] = d[c] * 10


PROBES = [
    # (name, damage, row, column, words of the cause)
    ("one current in mA", _one_current_in_ma, 6, "i_top_A", ["1400.0", "mA"]),
    ("one load of -1e6 N", _loads, 7, "load_N", ["-1000000.0", "typing"]),
    ("loads in mN", _loads_in_mn, None, "load_N", ["mN", "grams", "orders"]),
    ("positions in metres", _positions_in_metres, None, "v_um", ["metres"]),
    ("positions in 0.1 µm", _positions_in_tenths, None, "v_um", ["clearance"]),
]


@pytest.mark.parametrize("name,damage,row,column,words", PROBES, ids=[p[0] for p in PROBES])
def test_check_names_row_column_value_and_unit(tmp_path, clean, name, damage, row, column, words):
    d = clean.copy()
    damage(d)
    path = tmp_path / "probe.csv"
    d.to_csv(path, index=False)
    r = runner.invoke(app, ["check", str(path)])
    assert r.exit_code == 2, r.output
    assert column in r.output and all(w in r.output for w in words), r.output
    if row is not None:
        assert f"│ {row:>3} │ {column}" in r.output, r.output
    # identify judges the data with the same checks (exit 3 unless --accept-implausible), naming file and row
    r = runner.invoke(app, ["identify", str(path)])
    assert r.exit_code == 3 and "probe.csv" in r.output and column in r.output, r.output


@pytest.mark.parametrize("data,bearing", [(DEFAULT, None), (FEM_SLICE, FEM_BEARING)], ids=["default", "fem"])
def test_the_bundled_data_pass_the_check(data, bearing):
    r = runner.invoke(app, ["check", str(data), *(["--bearing", str(bearing)] if bearing else [])])
    assert r.exit_code == 0 and ": ok," in r.output, r.output


def test_a_flag_names_file_row_column_and_value(clean):
    d = clean.copy()
    _one_current_in_ma(d)
    (flag,) = plausibility.check_data(d, PAPER_BEARING, "probe.csv")
    assert (flag.file, flag.row, flag.column, flag.value) == ("probe.csv", 6, "i_top_A", 1400.0)
    assert str(flag).startswith("probe.csv, row 6 (line 7), column 'i_top_A': ") and "mA instead of A" in str(flag)
