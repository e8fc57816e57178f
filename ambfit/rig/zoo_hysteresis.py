"""Zoo laws of hysteresis (:mod:`ambfit.rig.zoo`): memories of the coil current's past that the rig carries from
reading to reading.

The rig keeps one number per coil between readings (the context's ``m_*``, :func:`ambfit.rig.simulate`), so each
law here is a first-order memory: a generalised play operator, or an exponentially fading memory of the
current's recent course.  A Preisach or Prandtl-Ishlinskii operator of several plays would need one state per
play.  References: Mayergoyz, *Mathematical Models of Hysteresis*, 1991, ch. 1; Visintin, *Differential Models
of Hysteresis*, 1994, ch. 3.
"""

from __future__ import annotations

from typing import ClassVar

import jax.numpy as jnp
import numpy as np

from ambfit.physics.stages import _set
from ambfit.rig.laws import magnetising, with_magnetising
from ambfit.rig.zoo_magnetic import I_REF
from ambfit.rig.zoo_shapes import Shape, ZooLaw, log_uniform, random_shape


class PlayHysteresis(ZooLaw):
    """Hysteresis as a generalised play: asymmetric, current-dependent widths, partly felt.

    The play's output ``p = clip(p_prev, i - h_rise(i), i + h_fall(i))`` with ``h(i) = h0 (1 + growth f(|i| / I_REF))``
    (a random increasing :class:`Shape` ``f``: the Rayleigh region's loops widen with the amplitude), and the
    magnetising current is ``m = i + fraction (p - i)``: the largest lag is 5-20 mA, the library's range, however the
    width and fraction share it (Visintin, *Differential Models of Hysteresis*, 1994, ch. 3; Mayergoyz 1991, ch. 1).

    The rig carries ``p`` as each coil's state (``m_*``); the force stage puts ``m`` in its place.  Without a state
    (a fit) ``p = i - h direction``.  It must be the last effect of a rig's list, after every other coil stage.
    """

    rise: jnp.ndarray
    fall: jnp.ndarray
    growth: jnp.ndarray
    shape: Shape
    fraction: jnp.ndarray
    name: ClassVar[str] = "zoo_hysteresis_play"
    family: ClassVar[str] = "hysteresis"
    stateful: ClassVar[bool] = True

    def coil(self, ctx):
        def one(i, p_prev, direction):
            grow = 1.0 + self.growth * self.shape(i / I_REF)
            up, down = self.rise * grow, self.fall * grow
            fit = i - jnp.where(direction >= 0, up, down) * direction
            return jnp.where(jnp.isnan(p_prev), fit, jnp.clip(p_prev, i - up, i + down))

        return _set(ctx, m_top=one(ctx.i_top, ctx.m_prev_top, ctx.dir_top),
                    m_bottom=one(ctx.i_bottom, ctx.m_prev_bottom, ctx.dir_bottom))

    def force(self, ctx, force):
        f = self.fraction
        return with_magnetising(ctx, force, magnetising(ctx.i_top, ctx.m_top, f),
                                magnetising(ctx.i_bottom, ctx.m_bottom, f))

    @classmethod
    def _draw(cls, rng, duration_s):
        fraction = rng.uniform(0.25, 1.0)
        rise, fall = rng.uniform(0.005, 0.02, 2) / fraction
        growth = 0.0 if rng.random() < 0.5 else rng.uniform(0.2, 1.5)
        return cls(np.asarray(rise), np.asarray(fall), np.asarray(growth),
                   random_shape(rng, kinds=("power", "knee", "settle"), power=(1.0, 2.0), centre=(0.2, 1.0)),
                   np.asarray(fraction))


class MemoryHysteresis(ZooLaw):
    """Hysteresis as an exponentially fading memory of the current's direction history.

    Each coil keeps ``q``, its current smoothed over the last few readings, ``q = memory q_prev + (1 - memory) i``,
    and lags by ``m = i - lag tanh((i - q) / scale)``: after a run of rising steps the iron lags below, after a
    run of falling ones above, and a single step back half undoes it.  ``lag`` 5-20 mA (the library's range),
    ``scale`` 20-200 mA, a memory of 0.5-6 readings (Mayergoyz 1991, ch. 1: hysteresis as a memory of the
    input's past extrema, here with a fading kernel).  The rig carries ``q`` as the coil's state; a fit (no
    state) takes ``q = i - 3 scale direction``.  It must be the last effect of a rig's list.
    """

    lag: jnp.ndarray
    scale: jnp.ndarray
    memory: jnp.ndarray
    name: ClassVar[str] = "zoo_hysteresis_memory"
    family: ClassVar[str] = "hysteresis"
    stateful: ClassVar[bool] = True

    def coil(self, ctx):
        def one(i, q_prev, direction):
            return jnp.where(jnp.isnan(q_prev), i - 3.0 * self.scale * direction,
                             self.memory * q_prev + (1.0 - self.memory) * i)

        return _set(ctx, m_top=one(ctx.i_top, ctx.m_prev_top, ctx.dir_top),
                    m_bottom=one(ctx.i_bottom, ctx.m_prev_bottom, ctx.dir_bottom))

    def force(self, ctx, force):
        def m(i, q):
            return i - self.lag * jnp.tanh((i - q) / self.scale)

        return with_magnetising(ctx, force, m(ctx.i_top, ctx.m_top), m(ctx.i_bottom, ctx.m_bottom))

    @classmethod
    def _draw(cls, rng, duration_s):
        return cls(np.asarray(rng.uniform(0.005, 0.02)), np.asarray(log_uniform(rng, 0.02, 0.2)),
                   np.asarray(np.exp(-1.0 / rng.uniform(0.5, 6.0))))


HYSTERESIS: dict[str, tuple[type[ZooLaw], ...]] = {"hysteresis": (PlayHysteresis, MemoryHysteresis)}
"""The zoo's hysteresis law classes."""
