"""The virtual test rig: equilibria under a controller, perturbation protocols.

``ambfit.rig`` re-exports the simulator (:mod:`ambfit.rig.virtual`); protocols live in
:mod:`ambfit.rig.protocol`, the bearing's limits on them (back-up clearance, coil current) in
:mod:`ambfit.rig.limits`.  The paper's effective-origin search, which identifies the origin
with the closed form at every iteration, runs on the rig from :mod:`ambfit.studies.origin`.
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
