"""The virtual test rig: equilibria under a controller, perturbation protocols, the effective-origin search.

``ambfit.rig`` re-exports the simulator (:mod:`ambfit.rig.virtual`); protocols live in
:mod:`ambfit.rig.protocol` and the paper's origin search in :mod:`ambfit.rig.origin`.
"""

from ambfit.rig.virtual import (
    FORCE_TOLERANCE_N,
    NOISE_FREE,
    PAPER_RIG,
    Noise,
    RigError,
    RigSpec,
    RigState,
    Simulation,
    simulate,
    write_truth,
)

__all__ = ["FORCE_TOLERANCE_N", "NOISE_FREE", "PAPER_RIG", "Noise", "RigError", "RigSpec", "RigState", "Simulation",
           "simulate", "write_truth"]
