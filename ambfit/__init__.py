"""ambfit: identify active magnetic bearing parameters from current-position perturbations.

The public API (everything a notebook needs)::

    import ambfit
    data = ambfit.read_csv("data/paper_table2.csv")
    result = ambfit.fit(data)                       # least squares; ambfit.fit(data, effects=(...)) extends it
    print(result)                                   # gap ± error, χ², health
    g, s = result.value("g_v0"), result.error("g_v0")   # SI units (m)

``read_csv``, ``fit`` (and ``fit_by``, ``fit_many``), ``closed_form``, ``sample``,
``diagnose``, ``simulate``, ``force`` (force measurement from a fit), ``recommend`` (what to
measure next), ``solution_space`` (the paper's Fig. 2), the effects (``Saturation``,
``Fringing``, ...) and the bearing description (``Bearing``, ``PAPER_BEARING``) are loaded on first use, so ``import ambfit`` (and ``ambfit --help``)
stays fast.  JAX is switched to float64 before any of it makes an array: gaps of
hundreds of micrometres and ratios of nearly equal current squares need it.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import os
import sys
from typing import TYPE_CHECKING

try:
    __version__ = importlib.metadata.version("ambfit")
except importlib.metadata.PackageNotFoundError:  # a source tree that was not installed
    __version__ = "unknown"

# float64 before JAX makes any array: set it in the environment when JAX is not loaded yet (cheap), else in
# its config.  Every module that imports JAX comes through this package, so this runs first.
if "jax" in sys.modules:
    sys.modules["jax"].config.update("jax_enable_x64", True)
else:
    os.environ["JAX_ENABLE_X64"] = "True"

_API = {
    "read_csv": ("ambfit.data", "read_csv"),
    "write_csv": ("ambfit.data", "write_csv"),
    "DataError": ("ambfit.data", "DataError"),
    "Dataset": ("ambfit.data", "Dataset"),
    "fit": ("ambfit.estimation.fit", "fit"),
    "fit_by": ("ambfit.estimation.fit", "fit_by"),
    "fit_many": ("ambfit.estimation.fit", "fit_many"),
    "force": ("ambfit.estimation.measure", "force"),
    "recommend": ("ambfit.estimation.design", "recommend"),
    "solution_space": ("ambfit.estimation.conditioning", "solution_space"),
    "FitResult": ("ambfit.estimation.results", "FitResult"),
    "FitError": ("ambfit.estimation.core", "FitError"),
    "closed_form": ("ambfit.estimation.checked", "closed_form"),
    "sample": ("ambfit.estimation.bayes", "sample"),
    "Posterior": ("ambfit.estimation.bayes", "Posterior"),
    "Prior": ("ambfit.estimation.bayes", "Prior"),
    "sample_nuts": ("ambfit.estimation.nuts", "sample_nuts"),
    "linearise": ("ambfit.rotordynamics", "linearise"),
    "Linearisation": ("ambfit.rotordynamics", "Linearisation"),
    "bearing_element": ("ambfit.rotordynamics", "bearing_element"),
    "diagnose": ("ambfit.diagnosis.attribution", "diagnose"),
    "Diagnosis": ("ambfit.diagnosis.results", "Diagnosis"),
    "simulate": ("ambfit.rig.virtual", "simulate"),
    "RigSpec": ("ambfit.rig.virtual", "RigSpec"),
    "PAPER_RIG": ("ambfit.rig.virtual", "PAPER_RIG"),
    "Noise": ("ambfit.rig.virtual", "Noise"),
    "Bearing": ("ambfit.physics.bearing", "Bearing"),
    "PAPER_BEARING": ("ambfit.physics.bearing", "PAPER_BEARING"),
    "MU_0": ("ambfit.physics.bearing", "MU_0"),
    "AXES": ("ambfit.physics.bearing", "AXES"),
    "BearingParams": ("ambfit.physics.model", "BearingParams"),
    "Readings": ("ambfit.physics.model", "Readings"),
    "axis_force": ("ambfit.physics.model", "axis_force"),
    "ideal_force": ("ambfit.physics.model", "ideal_force"),
    "pole_gaps": ("ambfit.physics.model", "pole_gaps"),
    "effects": ("ambfit.physics.effects", None),
    "protocol": ("ambfit.rig.protocol", None),
    **{name: ("ambfit.physics.effects", name) for name in (
        "Effect", "Saturation", "IronReluctance", "Fringing", "Leakage", "CurrentOffset", "CurrentGain",
        "PositionGain", "CrossCoupling", "Hysteresis", "ThermalDrift", "EFFECTS", "effect_by_name")},
}

__all__ = sorted(_API) + ["__version__"]


def __getattr__(name: str):
    try:
        module, attr = _API[name]
    except KeyError:
        raise AttributeError(f"module 'ambfit' has no attribute {name!r}") from None
    value = importlib.import_module(module)
    if attr is not None:
        value = getattr(value, attr)
    globals()[name] = value
    return value


def __dir__():
    return __all__


if TYPE_CHECKING:  # pragma: no cover - static analysers see the eager imports
    from ambfit.data import DataError, Dataset, read_csv, write_csv  # noqa: F401
    from ambfit.diagnosis.attribution import diagnose  # noqa: F401
    from ambfit.diagnosis.results import Diagnosis  # noqa: F401
    from ambfit.estimation.bayes import Posterior, Prior, sample  # noqa: F401
    from ambfit.estimation.checked import closed_form  # noqa: F401
    from ambfit.estimation.conditioning import solution_space  # noqa: F401
    from ambfit.estimation.core import FitError  # noqa: F401
    from ambfit.estimation.design import recommend  # noqa: F401
    from ambfit.estimation.fit import fit, fit_by, fit_many  # noqa: F401
    from ambfit.estimation.measure import force  # noqa: F401
    from ambfit.estimation.results import FitResult  # noqa: F401
    from ambfit.physics.bearing import AXES, MU_0, PAPER_BEARING, Bearing  # noqa: F401
    from ambfit.physics.effects import *  # noqa: F401,F403
    from ambfit.physics.model import BearingParams, Readings, axis_force, ideal_force, pole_gaps  # noqa: F401
    from ambfit.rig.virtual import PAPER_RIG, Noise, RigSpec, simulate  # noqa: F401
