"""The staged force evaluation that effects plug into: the :class:`Context` each stage passes on and the
:class:`Effect` base class whose methods are the stages.

:func:`ambfit.physics.model.evaluate` threads one :class:`Context` per reading through every
effect's stages, in this order:

``physical``  sensor readings -> physical currents and positions (``unsense``)
``geometry``  effective gap ``g0`` and origin ``x0``
``gap``       magnetic gaps ``g_top``, ``g_bottom``
``coil``      magnetising currents ``m_*`` and coil force constants ``k_*``
``force``     the axis force

An effect (:mod:`ambfit.physics.effects`) overrides the stages it changes and returns a modified
copy of the context; the base class leaves every stage as it is.  The force model and the effects
both build on this module, so neither imports the other.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ambfit.physics.bearing import Bearing


class Context(eqx.Module):
    """Everything one evaluation of the force knows about each reading (SI units).

    Effects receive a context and return a modified copy (``eqx.tree_at``).  The
    stages, in order, are ``physical`` (sensor readings to physical quantities),
    ``geometry`` (``g0``, ``x0``), ``gap`` (``g_top``, ``g_bottom``), ``coil``
    (magnetising currents ``m_*`` and coil force constants ``k_*``) and ``force``.
    """

    axis: jnp.ndarray
    i_top: jnp.ndarray
    i_bottom: jnp.ndarray
    x: jnp.ndarray
    y: jnp.ndarray
    bias: jnp.ndarray
    time: jnp.ndarray
    temperature: jnp.ndarray
    dir_top: jnp.ndarray
    dir_bottom: jnp.ndarray
    g0: jnp.ndarray
    x0: jnp.ndarray
    y0: jnp.ndarray
    k: jnp.ndarray
    g0_other: jnp.ndarray
    bearing: Bearing = eqx.field(static=True)
    g_top: jnp.ndarray
    g_bottom: jnp.ndarray
    m_top: jnp.ndarray
    m_bottom: jnp.ndarray
    k_top: jnp.ndarray
    k_bottom: jnp.ndarray
    m_prev_top: jnp.ndarray
    m_prev_bottom: jnp.ndarray
    i_top_other: jnp.ndarray
    i_bottom_other: jnp.ndarray
    flux_start: jnp.ndarray | None = None
    """A solve's warm start per row, e.g. the magnetic circuit's loop fluxes at a fit's previous point (None: cold)."""
    flux: jnp.ndarray | None = None
    """What that solve converged to, for the next evaluation's start (set by the ``force`` stage; None: no solve)."""

    def b_top(self) -> jnp.ndarray:
        """Ideal-circuit flux density in the top gaps [T] (:meth:`Bearing.flux_density`)."""
        return self.bearing.flux_density(self.m_top, self.g_top)

    def b_bottom(self) -> jnp.ndarray:
        """Ideal-circuit flux density in the bottom gaps [T]."""
        return self.bearing.flux_density(self.m_bottom, self.g_bottom)


def _set(ctx: Context, **fields) -> Context:
    names = tuple(fields)
    return eqx.tree_at(lambda c: tuple(getattr(c, n) for n in names), ctx, tuple(fields.values()))


def _ax(p, axis):
    """Per-row value of a parameter given as a scalar or a ``(v, w)`` pair."""
    return jnp.broadcast_to(jnp.asarray(p, dtype=float), (2,))[axis]


class Effect(eqx.Module):
    """Base class: every stage is the identity.  Subclasses override what they change."""

    name: ClassVar[str] = ""
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {}
    SIGNED: ClassVar[tuple[str, ...]] = ()
    UNITS: ClassVar[dict[str, str]] = {}
    FROM_BEARING: ClassVar[dict[str, str]] = {}
    """Fields whose default is a fact of the bearing description: ``{field: Bearing attribute}``
    (:func:`ambfit.physics.effects.effect_by_name` fills them from the bearing it is given)."""
    stateful: ClassVar[bool] = False
    FLUX_WIDTH: ClassVar[int] = 0
    """The width of the solve per row whose solution :meth:`force_and_flux` returns (0: none)."""

    def ranges(self) -> dict[str, tuple[float, float]]:
        """The free parameters of this instance and their ranges (``RANGES``; an instance may fix some)."""
        return type(self).RANGES

    def sense(self, axis, i_top, i_bottom, x, y):
        """Physical currents [A] and positions [m] -> what the sensors report."""
        return i_top, i_bottom, x, y

    def unsense(self, axis, i_top, i_bottom, x, y):
        """Inverse of :meth:`sense`: sensor readings -> physical quantities."""
        return i_top, i_bottom, x, y

    def physical(self, ctx: Context) -> Context:
        it, ib, x, y = self.unsense(ctx.axis, ctx.i_top, ctx.i_bottom, ctx.x, ctx.y)
        return _set(ctx, i_top=it, i_bottom=ib, x=x, y=y)

    def geometry(self, ctx: Context) -> Context:
        return ctx

    def gap(self, ctx: Context) -> Context:
        return ctx

    def coil(self, ctx: Context) -> Context:
        return ctx

    def force(self, ctx: Context, force):
        return force

    def force_and_flux(self, ctx: Context, force):
        """:meth:`force` and the solution of a solve per row it made from ``ctx.flux_start`` (None: none), for a
        caller that evaluates again nearby (Levenberg-Marquardt's next point) to start from."""
        return self.force(ctx, force), None

    def temperature(self, time_s, ambient_C):
        """Bearing temperature [°C] this effect implies at ``time_s`` (rig side only)."""
        return ambient_C + 0.0 * time_s

    @classmethod
    def random(cls, rng: np.random.Generator) -> Effect:
        """An instance with every parameter drawn uniformly from ``RANGES`` (per axis).

        Parameters in ``SIGNED`` get a random sign.
        """
        kw = {}
        for name, (lo, hi) in cls.RANGES.items():
            val = rng.uniform(lo, hi, size=2)
            if name in cls.SIGNED:
                val = val * rng.choice([-1.0, 1.0], size=2)
            kw[name] = jnp.asarray(val)
        return cls(**kw)

    def describe(self) -> dict[str, list[float] | float]:
        """Parameter values as plain lists, for JSON and reports (SI units)."""
        return {f.name: np.asarray(getattr(self, f.name)).tolist() for f in dataclasses.fields(self)}
