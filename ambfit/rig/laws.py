"""Unmodelled physics whose laws differ from the library's candidates, for judging the diagnosis.

A real bearing's hysteresis or cross-coupling need not follow the law ambfit's candidate effects write.
These effects are families the library knows, with other physically reasonable laws; the diagnosis is
never offered them as candidates (they are not in :data:`ambfit.physics.effects.EFFECTS`), so data made with
them test whether it names the family when the law differs (``benchmarks/gap_attribution.py``, tests).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from ambfit.physics.stages import Effect, _ax, _set


class RayleighHysteresis(Effect):
    """Hysteresis whose loop width grows with the magnetising current (the Rayleigh region of soft iron).

    At low fields the coercive width of a minor loop is proportional to its amplitude (Rayleigh's law,
    Bozorth, *Ferromagnetism*, 1951, ch. 13), so the play operator's half-width is ``ratio * |i|`` instead of
    the library's constant ``width``: ``m = clip(m_prev, i - ratio |i|, i + ratio |i|)``.
    """

    ratio: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(0.008))
    name: ClassVar[str] = "hysteresis_rayleigh"
    RANGES: ClassVar = {"ratio": (0.006, 0.012)}
    UNITS: ClassVar = {"ratio": "-"}
    stateful: ClassVar[bool] = True

    def coil(self, ctx):
        r = _ax(self.ratio, ctx.axis)

        def one(i, m_prev, direction):
            h = r * jnp.abs(i)
            return jnp.where(jnp.isnan(m_prev), i - h * direction, jnp.clip(m_prev, i - h, i + h))

        return _set(ctx, m_top=one(ctx.m_top, ctx.m_prev_top, ctx.dir_top),
                    m_bottom=one(ctx.m_bottom, ctx.m_prev_bottom, ctx.dir_bottom))


class BiasCoupling(Effect):
    """Cross stiffness that grows with this axis' bias squared, as a bearing's own stiffnesses do.

    The library's cross-coupling is a constant cross stiffness ``kappa`` on the other axis' displacement.
    Through shared back iron the coupling flux is this axis' bias flux, so the cross stiffness scales with
    the bias current squared (Schweitzer and Maslen 2009, sec. 4.4): ``F += kappa (b / b_ref)^2 (y0 + y)``
    with ``b`` the mean of the two coil currents and ``b_ref`` = 1.3 A.
    """

    kappa: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(2000.0))
    b_ref: float = 1.3
    name: ClassVar[str] = "cross_coupling_bias"
    RANGES: ClassVar = {"kappa": (1500.0, 3000.0)}
    SIGNED: ClassVar = ("kappa",)
    UNITS: ClassVar = {"kappa": "N/m", "b_ref": "A"}

    def force(self, ctx, force):
        b = 0.5 * (ctx.i_top + ctx.i_bottom)
        return force + _ax(self.kappa, ctx.axis) * (b / self.b_ref) ** 2 * (ctx.y0 + ctx.y)


OTHER_LAWS: dict[str, tuple[str, type[Effect]]] = {
    "hysteresis_rayleigh": ("hysteresis", RayleighHysteresis),
    "cross_coupling_bias": ("cross_coupling", BiasCoupling),
}
"""Each other-law effect and the library family it belongs to."""
