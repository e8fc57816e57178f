"""The magnetic equivalent circuit of the whole bearing as one effect, in place of Eq. 4."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ambfit._arrays import traced
from ambfit.physics.stages import Effect, _ax


class MagneticCircuit(Effect):
    """The whole stator and rotor as a nonlinear magnetic equivalent circuit, in place of Eq. 4.

    One physics for what :class:`Saturation`, :class:`IronReluctance`, :class:`Fringing`,
    :class:`Leakage` and :class:`CrossCoupling` patch one by one: iron with the bearing's B-H curve
    in every pole, yoke and rotor branch; Roters fringing permeances at every pole side; slot
    leakage permeances between neighbouring poles; and the four horseshoes sharing back iron, so
    that this axis' displacement changes the gaps of the other axis' poles 22.5° away and flux
    crosses between horseshoes as the polarity (NNSS/NSNS) dictates
    (:mod:`ambfit.physics.circuit`, with its references).  The circuit is solved per reading
    with both axes' currents (rows paired by ``time_s``); the gap of each row is its axis'
    effective gap ``g0`` (the air gap as drawn when this physics is right), the displacement
    ``x0 + x``, and the force is scaled by ``k`` over the geometric force constant (1 when the
    turns and pole face are as drawn).

    Parameters a designer recognises (their ranges are the priors' scale):

    ``fringe_depth`` [m]
        Depth of the fringing field beside each pole side (Roters' "half annulus"): about half
        the slot opening at the bore, 1-5 mm for radial bearings of 20-100 mm bore.
    ``leakage`` [-]
        Slot-leakage shape factor λ: permeance ``MU_0 l λ`` between neighbouring pole bodies,
        0.2-1 for open slots (Meeker, Maslen & Noh 1996).
    ``iron_scale`` [-]
        The B-H curve's field strength times this: 1 for datasheet iron over the drawn iron
        path; stress from punching, joints and a longer mean path raise it (0.5-2).
    ``pole_area_ratio`` [-]
        Pole-body cross-section over the pole face (< 1 under pole shoes; 0.5-1).

    ``held`` names parameters that are not fitted but held at this instance's values (for example the
    fringe depth the drawing implies: ``MagneticCircuit(fringe_depth=1.5e-3, held=("fringe_depth",))``), to
    see what the data say when a designer's value is imposed.
    """

    fringe_depth: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(3.0e-3))
    leakage: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(0.5))
    iron_scale: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(1.0))
    pole_area_ratio: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(0.8))
    on: jnp.ndarray = eqx.field(default_factory=lambda: jnp.ones(5))
    """1 for each piece of the physics (``PIECES`` order) that is on, 0 when switched off to measure what it
    contributes.  An array, not a static setting, so every variant runs the same compiled fit; the
    parameters of a piece that is off stay in the fit, held at their prior centre by the prior."""
    held: tuple = eqx.field(static=True, default=(), converter=tuple)
    name: ClassVar[str] = "magnetic_circuit"
    PIECES: ClassVar = ("saturation", "iron", "fringing", "leakage", "coupling")
    """``saturation`` off: the iron keeps a constant permeability (the B-H curve's initial slope, scaled by
    ``iron_scale``); ``iron`` off: ideal iron; ``fringing``, ``leakage`` off: no such permeances;
    ``coupling`` off: isolated horseshoes (the ideal law's assumption)."""
    IDLE: ClassVar = {"iron": ("leakage", "iron_scale", "pole_area_ratio"), "fringing": ("fringe_depth",),
                      "leakage": ("leakage",)}
    """The parameters the force no longer depends on when a piece is off (ideal iron has no drop along the pole that
    slot leakage could divert flux from; a billionth of its effect remains, from iron's ``MU_R_MAX`` ceiling)."""
    RANGES: ClassVar = {"fringe_depth": (1.0e-3, 5.0e-3), "leakage": (0.2, 1.0), "iron_scale": (0.5, 2.0),
                        "pole_area_ratio": (0.5, 1.0)}
    UNITS: ClassVar = {"fringe_depth": "m", "leakage": "-", "iron_scale": "-", "pole_area_ratio": "-"}
    needs_other_axis: ClassVar[bool] = True
    FLUX_WIDTH: ClassVar[int] = 17         # the circuit's loop fluxes (ambfit.physics.circuit.FLUX_WIDTH)
    SHARED: ClassVar[bool] = True          # one stator: the same parameters for both axes
    FAMILIES: ClassVar = ("saturation", "iron_reluctance", "fringing", "leakage", "cross_coupling")

    def __check_init__(self):
        unknown = set(self.held) - set(type(self).RANGES)
        if unknown:
            raise ValueError(f"held: {', '.join(sorted(unknown))} not among {', '.join(type(self).RANGES)}")

    def ranges(self) -> dict[str, tuple[float, float]]:
        """``RANGES`` without the ``held`` parameters."""
        return {k: v for k, v in type(self).RANGES.items() if k not in self.held}

    @property
    def off(self) -> tuple:
        """The pieces switched off (concrete values only, not inside a traced function)."""
        return tuple(p for p, flag in zip(self.PIECES, np.asarray(self.on)) if flag == 0)

    @property
    def idle(self) -> tuple:
        """The parameters of no effect with the pieces that are off (``IDLE``; concrete values only)."""
        return tuple(dict.fromkeys(n for piece in self.off for n in self.IDLE.get(piece, ())))

    def without(self, piece: str) -> MagneticCircuit:
        """The same circuit with one more piece (``PIECES``) switched off."""
        if piece not in self.PIECES:
            raise ValueError(f"unknown piece {piece!r}; pieces: {', '.join(self.PIECES)}")
        j = self.PIECES.index(piece)
        if traced(self.on):
            return eqx.tree_at(lambda e: e.on, self, jnp.asarray(self.on).at[j].set(0.0))
        on = np.array(self.on, dtype=float)              # (see ambfit._arrays)
        on[j] = 0.0
        return eqx.tree_at(lambda e: e.on, self, on)

    def force(self, ctx, force):
        return self.force_and_flux(ctx, force)[0]

    def force_and_flux(self, ctx, force):
        """The circuit's force and each row's loop fluxes, solved from ``ctx.flux_start``
        (:func:`ambfit.physics.circuit.row_axis_force_and_flux`)."""
        from ambfit.physics import circuit

        a = ctx.axis
        sat, iron, fringing, leak, coupling = (self.on[j] for j in range(5))
        params = circuit.MECParams.drawing(ctx.bearing).replace(
            gap=ctx.g0, fringe_depth=fringing * _ax(self.fringe_depth, a), leakage=leak * _ax(self.leakage, a),
            iron_h_scale=iron * _ax(self.iron_scale, a),
            pole_area_ratio=iron * _ax(self.pole_area_ratio, a) + (1.0 - iron), link=coupling, saturation=sat)
        bearing = ctx.bearing
        f, flux = circuit.row_axis_force_and_flux(params, bearing, a, ctx.m_top, ctx.m_bottom, ctx.i_top_other,
                                                  ctx.i_bottom_other, ctx.x, ctx.y, ctx.x0, ctx.y0, ctx.flux_start)
        return f * ctx.k / ctx.bearing.force_constant(1.0), flux
