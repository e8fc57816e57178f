"""ambfit: identify active magnetic bearing parameters from current-position perturbations.

Importing ambfit switches JAX to float64 before any array is made: gaps of
hundreds of micrometres and ratios of nearly equal current squares need it.
"""

import jax

jax.config.update("jax_enable_x64", True)

from ambfit import effects, protocol  # noqa: E402
from ambfit.model import (  # noqa: E402
    ALPHA_DEFAULT, AXES, MU_0, BearingParams, Readings, axis_force, flux_density, force_constant, gaps,
    ideal_force,
)

__version__ = "0.1.0"

__all__ = [
    "ALPHA_DEFAULT", "AXES", "MU_0", "BearingParams", "Readings", "axis_force", "effects", "flux_density",
    "force_constant", "gaps", "ideal_force", "protocol", "__version__",
]
