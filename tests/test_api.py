"""The public API: the README's notebook recipe runs as written; importing ambfit is cheap and complete."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

import ambfit

ROOT = Path(__file__).resolve().parents[1]


def readme_recipe() -> str:
    text = (ROOT / "README.md").read_text()
    m = re.search(r"<!-- recipe -->\s*```python\n(.*?)```", text, flags=re.S)
    assert m, "README.md has no recipe block (<!-- recipe --> before a python code block)"
    return m.group(1)


def test_readme_recipe_runs_and_prints_the_gap():
    code = readme_recipe()
    assert len([line for line in code.splitlines() if line.strip()]) <= 5
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    # the default data: g_v0 = 774.50 ± 1.41 µm (least squares, see reports/demo)
    assert re.search(r"g_v0 = 774\.\d+ ± 1\.\d+ µm", out.stdout), out.stdout


def test_import_is_lazy_and_switches_float64():
    code = ("import sys, ambfit; assert 'jax' not in sys.modules, 'import ambfit loaded jax'; "
            "import jax.numpy as jnp; assert jnp.zeros(1).dtype == 'float64'")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr


@pytest.mark.parametrize("name", ambfit.__all__)
def test_every_public_name_resolves(name):
    assert getattr(ambfit, name) is not None


def test_fit_is_the_function_and_modules_stay_reachable():
    from ambfit.estimation import fit as fit_module

    assert callable(ambfit.fit) and ambfit.fit is fit_module.fit
    # the closed form checked against least squares (the closed form itself sits below the fit and fits nothing)
    from ambfit.estimation import checked

    assert ambfit.closed_form is checked.closed_form
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        ambfit.nope  # noqa: B018


def test_the_data_format_document_ships_with_the_package_and_names_every_column():
    from importlib.resources import files

    from ambfit import data

    text = (files("ambfit") / "docs" / "data-format.md").read_text()
    for column in (*data.REQUIRED, *data.NUMERIC_OPTIONAL, *data.LABELS, "iteration"):
        assert f"`{column}`" in text, column
    for key in ("pole_angle_deg", "turns_per_pole", "pole_area_mm2", "nominal_gap_um", "backup_clearance_um",
                "max_current_A", "polarity", "iron_path_mm"):
        assert key in text, key
