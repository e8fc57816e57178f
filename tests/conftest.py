import json
import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

import ambfit  # noqa: F401  (switches JAX to float64 before any test makes an array)

# The same examples on every run (derandomize): a test suite that passes on one run passes on the next, so CI
# cannot flake on a newly drawn case.  AMBFIT_HYPOTHESIS_PROFILE=explore draws new cases each run, to hunt bugs.
settings.register_profile(
    "ambfit", deadline=None, max_examples=int(os.environ.get("AMBFIT_HYPOTHESIS_EXAMPLES", "25")),
    suppress_health_check=[HealthCheck.too_slow], derandomize=True, database=None,
)
settings.register_profile("explore", parent=settings.get_profile("ambfit"), derandomize=False)
settings.load_profile(os.environ.get("AMBFIT_HYPOTHESIS_PROFILE", "ambfit"))


@pytest.fixture(scope="module")
def clean_fit(tmp_path_factory):
    """The contract JSON ``ambfit identify --json`` writes for the bundled default data."""
    from typer.testing import CliRunner

    from ambfit.faces.cli import app

    out = tmp_path_factory.mktemp("clean") / "clean.json"
    data = Path(__file__).resolve().parents[1] / "data" / "paper_table2.csv"
    r = CliRunner().invoke(app, ["identify", str(data), "--json", str(out)])
    assert r.exit_code == 0, r.output
    return json.loads(out.read_text())



def pytest_collection_modifyitems(config, items):
    # The long tests (marked slow) first: with two workers they then run beside the many short ones instead of
    # alone at the end (the README's commands take as long as a hundred short tests).
    items.sort(key=lambda item: (item.get_closest_marker("slow") is None, "test_readme" not in item.nodeid))
