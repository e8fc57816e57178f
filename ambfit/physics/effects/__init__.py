"""Unmodelled physics as small composable objects (STYLE.md section 3).

Each effect is an immutable :class:`equinox.Module` whose fields are its physical
parameters (SI units; a field of shape ``(2,)`` holds the ``(v, w)`` values, a
scalar is shared by both axes).  It modifies one or more stages of the force
evaluation in :func:`ambfit.physics.model.evaluate` (``physical``, ``geometry``,
``gap``, ``coil``, ``force``; :mod:`ambfit.physics.stages` describes them and holds
the :class:`~ambfit.physics.stages.Effect` base class).

The virtual rig applies the same objects as truth (it also calls ``sense`` to turn
physical quantities into sensor readings), and the fit can use them as model
extensions.  ``RANGES`` gives each parameter's realistic magnitude range with the
source it comes from; :meth:`Effect.random` draws from it.

Layout: :mod:`~ambfit.physics.effects.magnetic` (iron and gaps: saturation, iron
reluctance, fringing, leakage, cross-coupling, hysteresis),
:mod:`~ambfit.physics.effects.sensors` (current offset and gain, position gain),
:mod:`~ambfit.physics.effects.thermal` (thermal drift),
:mod:`~ambfit.physics.effects.magnetic_circuit` (the whole bearing's circuit in place of
Eq. 4); this package names them all (:data:`EFFECTS`, :data:`CIRCUITS`,
:func:`effect_by_name`).

General reference for the magnetics: Schweitzer & Maslen (eds.), *Magnetic
Bearings: Theory, Design, and Application to Rotating Machinery*, Springer 2009,
ch. 3-4 (pp. 69-109).
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from ambfit.physics.effects.magnetic import (
    CrossCoupling,
    Fringing,
    Hysteresis,
    IronReluctance,
    Leakage,
    Saturation,
)
from ambfit.physics.effects.magnetic_circuit import MagneticCircuit
from ambfit.physics.effects.sensors import CurrentGain, CurrentOffset, PositionGain
from ambfit.physics.effects.thermal import ThermalDrift
from ambfit.physics.stages import Effect

__all__ = [
    "Effect", "Saturation", "IronReluctance", "Fringing", "Leakage", "CurrentOffset",
    "CurrentGain", "PositionGain", "CrossCoupling", "Hysteresis", "ThermalDrift", "MagneticCircuit",
    "EFFECTS", "CIRCUITS", "effect_by_name",
]


EFFECTS: dict[str, type[Effect]] = {
    cls.name: cls
    for cls in (Saturation, IronReluctance, Fringing, Leakage, CurrentOffset, CurrentGain,
                PositionGain, CrossCoupling, Hysteresis, ThermalDrift)
}
"""Every effect class of the contract (section 3) by its name."""

CIRCUITS: dict[str, type[Effect]] = {MagneticCircuit.name: MagneticCircuit}
"""Models that replace Eq. 4 by a magnetic circuit of the whole bearing (they need both axes' currents)."""


def effect_by_name(name: str, *, bearing=None, **params) -> Effect:
    """An effect from its contract name and parameters (SI units; defaults otherwise).

    With a :class:`~ambfit.physics.bearing.Bearing`, parameters that are facts of the bearing
    (``FROM_BEARING``, e.g. the iron reluctance's ``l_fe``, the bearing's ``iron_path``) default to its values
    instead of the paper rig's.
    """
    known = {**EFFECTS, **CIRCUITS}
    try:
        cls = known[name]
    except KeyError:
        raise ValueError(f"unknown effect {name!r}; valid names: {', '.join(known)}") from None
    fields = {f.name for f in dataclasses.fields(cls)}
    bad = set(params) - fields
    if bad:
        raise ValueError(f"effect {name!r} has no parameter(s) {sorted(bad)}; valid: {sorted(fields)}")
    if bearing is not None:
        params = {field: getattr(bearing, fact) for field, fact in cls.FROM_BEARING.items()} | params
    conv = {k: (jnp.asarray(v, dtype=float) if k in cls.RANGES else v) for k, v in params.items()}
    return cls(**conv)
