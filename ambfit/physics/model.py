"""The paper's magnetic force model (Eq. 3-4) for both bearing axes, in SI units.

Conventions follow ``DATA-CONTRACT.md`` section 1.  For one axis (``v`` or ``w``)
with effective gap ``g0`` [m], effective origin ``x0`` [m] and force constant
``k`` [N m^2 / A^2]::

    g_top    = g0 - (x0 + x) * cos(alpha)
    g_bottom = g0 + (x0 + x) * cos(alpha)
    F        = k * (i_top**2 / g_top**2 - i_bottom**2 / g_bottom**2)

The law is written once, in :func:`pole_gaps` and :func:`horseshoe_force`; every
estimator calls these (or :func:`evaluate`, which threads unmodelled effects through
them).  The bearing's facts (pole angle, turns, pole face) come from
:class:`ambfit.physics.bearing.Bearing`.

Unmodelled physics enters through :mod:`ambfit.physics.effects`: :func:`evaluate`
threads a :class:`~ambfit.physics.stages.Context` through every effect's stages
(:mod:`ambfit.physics.stages`), so the same effect objects serve the virtual rig
(as truth) and the fit (as model extensions).

Reference: the seed paper, "Active Magnetic Bearing System Identification using
Current-Position Perturbation", Eq. 3-4; Schweitzer & Maslen (eds.), *Magnetic
Bearings*, Springer 2009, ch. 4 (eq. 4.13 for the horseshoe force).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import equinox as eqx
import jax.numpy as jnp
import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from collections.abc import Sequence

    from ambfit.physics.stages import Effect

from ambfit._arrays import Array, frozen, numpy_unless_traced, traced
from ambfit.physics.bearing import PAPER_BEARING, Bearing
from ambfit.physics.stages import Context, _set


class BearingParams(eqx.Module):
    """Effective parameters of a two-axis radial bearing (the paper's unknowns).

    Parameters
    ----------
    g0 : array[2]
        Effective radial gaps ``(g_v0, g_w0)`` [m] with the rotor at the effective origin.
    x0 : array[2]
        Effective origins ``(v0, w0)`` [m] in sensor coordinates: the pole gaps of an
        axis are equal where the sensor reads ``x = -x0``.
    k : array[2]
        Force constants ``(k_v, k_w)`` [N m^2 / A^2] of Eq. 3 (includes the lamination
        coefficient).

    Examples
    --------
    >>> p = BearingParams.from_values(g0=762e-6, x0=(33e-6, -11e-6), k=3.45e-6)
    >>> float(p.g0[1]) * 1e6
    762.0
    """

    g0: jnp.ndarray
    x0: jnp.ndarray
    k: jnp.ndarray

    @classmethod
    def from_values(cls, g0, x0, k) -> BearingParams:
        """Build from scalars (same for both axes) or pairs ``(v, w)``, SI units (NumPy arrays from concrete values,
        which every JAX function takes without an eager dispatch per field; JAX arrays from traced ones)."""
        values = (g0, x0, k)
        if traced(*values):
            return cls(*(jnp.broadcast_to(jnp.asarray(a, dtype=float), (2,)) for a in values))
        return cls(*(frozen(np.broadcast_to(np.asarray(a, dtype=float), (2,))) for a in values))

    def as_dict_um(self) -> dict[str, float]:
        """Parameters with the contract's names and units (µm, N m^2/A^2)."""
        return {
            "g_v0_um": float(self.g0[0]) * 1e6,
            "v0_um": float(self.x0[0]) * 1e6,
            "g_w0_um": float(self.g0[1]) * 1e6,
            "w0_um": float(self.x0[1]) * 1e6,
            "k_v_Nm2_per_A2": float(self.k[0]),
            "k_w_Nm2_per_A2": float(self.k[1]),
        }


class Readings(eqx.Module):
    """Static equilibrium readings of one or both axes, SI units, one entry per row.

    Parameters
    ----------
    axis : int array[n]
        0 for the v axis, 1 for the w axis.
    i_top, i_bottom : array[n]
        Coil currents [A]; ``i_top`` pulls the rotor towards +axis.
    x : array[n]
        Rotor position on the row's own axis [m], sensor coordinates.
    y : array[n]
        Rotor position on the other axis [m], sensor coordinates.
    bias : array[n]
        Commanded bias current [A].
    time : array[n]
        Time of the reading [s] (zeros when unknown); from a contract table, counted from the start of its
        clock (:func:`ambfit.rows.clock`), on the virtual rig its clock.
    temperature : array[n]
        Bearing temperature [°C] (NaN when unknown).
    dir_top, dir_bottom : array[n]
        Direction from which each coil current was approached: +1 rising, -1 falling,
        0 unknown (derived from the order of readings, see
        :func:`ambfit.rows.approach_direction`).
    i_top_other, i_bottom_other : array[n] or None
        The other axis' coil currents at the same moment [A] (the row of the other axis with the
        same ``experiment`` and ``time_s``, :func:`ambfit.rows.other_axis_currents`); NaN where
        there is none.  Only effects coupling the axes through the stator need them.
    """

    axis: Array
    i_top: Array
    i_bottom: Array
    x: Array
    y: Array
    bias: Array
    time: Array
    temperature: Array
    dir_top: Array
    dir_bottom: Array
    i_top_other: Array | None = None
    i_bottom_other: Array | None = None

    @classmethod
    def build(
        cls, axis, i_top, i_bottom, x, y=None, bias=None, time=None, temperature=None,
        dir_top=None, dir_bottom=None, i_top_other=None, i_bottom_other=None,
    ) -> Readings:
        """Readings from array-likes; optional fields default to 'unknown'.  Read-only NumPy arrays of their own
        (copies, not views of the caller's table) unless a value is traced: in JAX, an eager conversion of each new
        shape compiles a program, and a compiled fit converts its inputs."""
        given = (axis, i_top, i_bottom, x, y, bias, time, temperature, dir_top, dir_bottom, i_top_other,
                 i_bottom_other)
        xp = numpy_unless_traced(*given)
        own = frozen if xp is np else jnp.asarray
        axis = own(axis, dtype=int)
        n = axis.shape
        def arr(a, fill):
            return own(xp.full(n, fill) if a is None else a, dtype=float)
        i_top = arr(i_top, 0.0)
        return cls(
            axis=axis, i_top=i_top, i_bottom=arr(i_bottom, 0.0), x=arr(x, 0.0), y=arr(y, 0.0),
            bias=arr(bias, np.nan), time=arr(time, 0.0), temperature=arr(temperature, np.nan),
            dir_top=arr(dir_top, 0.0), dir_bottom=arr(dir_bottom, 0.0),
            i_top_other=arr(i_top_other, np.nan), i_bottom_other=arr(i_bottom_other, np.nan),
        )

    def __len__(self) -> int:
        return int(self.axis.shape[0])


def _per_row(value, axis):
    """``value[axis]``, each row's entry of a per-axis pair: in JAX when either is traced (a pair of NumPy
    parameters closed over by a jitted function), else as the arrays are (NumPy needs no dispatch)."""
    if traced(value, axis):
        return jnp.asarray(value)[axis]
    return value[axis]


def make_context(
    params: BearingParams, readings: Readings, *, bearing: Bearing = PAPER_BEARING, m_prev_top=None,
    m_prev_bottom=None, flux_start=None,
) -> Context:
    """Context for ``readings`` under ``params`` before any effect has acted."""
    ax = readings.axis
    nan = jnp.full(ax.shape, jnp.nan)
    return Context(
        axis=ax, i_top=readings.i_top, i_bottom=readings.i_bottom, x=readings.x, y=readings.y,
        bias=readings.bias, time=readings.time, temperature=readings.temperature,
        dir_top=readings.dir_top, dir_bottom=readings.dir_bottom,
        g0=_per_row(params.g0, ax), x0=_per_row(params.x0, ax), y0=_per_row(params.x0, 1 - ax),
        k=_per_row(params.k, ax), g0_other=_per_row(params.g0, 1 - ax), bearing=bearing,
        g_top=nan, g_bottom=nan, m_top=nan, m_bottom=nan, k_top=nan, k_bottom=nan,
        m_prev_top=nan if m_prev_top is None else jnp.asarray(m_prev_top, dtype=float),
        m_prev_bottom=nan if m_prev_bottom is None else jnp.asarray(m_prev_bottom, dtype=float),
        i_top_other=nan if readings.i_top_other is None else readings.i_top_other,
        i_bottom_other=nan if readings.i_bottom_other is None else readings.i_bottom_other,
        flux_start=flux_start,
    )


def evaluate(
    params: BearingParams, readings: Readings, effects: Sequence[Effect] = (), *,
    bearing: Bearing = PAPER_BEARING, physical: bool = False, m_prev_top=None, m_prev_bottom=None, flux_start=None,
) -> tuple[jnp.ndarray, Context]:
    """Force on each reading's axis [N] and the final :class:`~ambfit.physics.stages.Context`.

    Parameters
    ----------
    params : BearingParams
    readings : Readings
        Measured readings (or physical ones with ``physical=True``, as the rig uses).
    effects : sequence of :class:`ambfit.physics.effects.Effect`
        Unmodelled physics added to the ideal law, applied stage by stage in order.
    bearing : Bearing
        The bearing's facts: pole angle, turns (for flux densities), pole face.
    physical : bool
        When True the readings are already physical quantities and the sensor
        stage is skipped.
    flux_start : array, optional
        A warm start of an effect's solve per row (:meth:`~ambfit.physics.stages.Effect.force_and_flux`), e.g. the
        returned context's ``flux`` at nearby parameters; the force does not depend on it.
    """
    ctx = make_context(params, readings, bearing=bearing, m_prev_top=m_prev_top, m_prev_bottom=m_prev_bottom,
                       flux_start=flux_start)
    if not physical:
        for e in effects:
            ctx = e.physical(ctx)
    for e in effects:
        ctx = e.geometry(ctx)
    g_top, g_bottom = pole_gaps(ctx.g0, ctx.x0, ctx.x, bearing.cos_alpha)
    ctx = _set(ctx, g_top=g_top, g_bottom=g_bottom)
    for e in effects:
        ctx = e.gap(ctx)
    ctx = _set(ctx, m_top=ctx.i_top, m_bottom=ctx.i_bottom, k_top=ctx.k, k_bottom=ctx.k)
    for e in effects:
        ctx = e.coil(ctx)
    force = horseshoe_force(ctx.k_top, ctx.m_top, ctx.g_top, ctx.k_bottom, ctx.m_bottom, ctx.g_bottom)
    flux = None
    for e in effects:
        force, solved = e.force_and_flux(ctx, force)
        flux = flux if solved is None else solved
    if flux is not None:
        ctx = eqx.tree_at(lambda c: c.flux, ctx, flux, is_leaf=lambda v: v is None)
    return force, ctx


def axis_force(params: BearingParams, readings: Readings, effects: Sequence[Effect] = (), **kw) -> jnp.ndarray:
    """Force [N] each reading's axis applies to the rotor along +axis (Eq. 4 plus effects).

    Examples
    --------
    >>> p = BearingParams.from_values(g0=762e-6, x0=0.0, k=3.4452e-6)
    >>> r = Readings.build(axis=[0], i_top=[3.0], i_bottom=[0.0], x=[0.0])
    >>> round(float(axis_force(p, r)[0]), 2)   # the paper's 53.4 N load capacity at 3.0 A
    53.4
    """
    return evaluate(params, readings, effects, **kw)[0]


def pole_gaps(g0, x0, x, cos_alpha: float = PAPER_BEARING.cos_alpha):
    """Pole gaps ``(g_top, g_bottom)`` [m] along the pole direction (contract section 1).

    Plain arithmetic: works on floats, numpy and JAX arrays.
    """
    u = (x0 + x) * cos_alpha
    return g0 - u, g0 + u


def horseshoe_force(k_top, m_top, g_top, k_bottom, m_bottom, g_bottom):
    """Eq. 3: ``k_t m_t^2 / g_t^2 - k_b m_b^2 / g_b^2`` [N], the one place the square law is written."""
    return k_top * m_top**2 / g_top**2 - k_bottom * m_bottom**2 / g_bottom**2


def ideal_force(g0, x0, k, i_top, i_bottom, x, cos_alpha: float = PAPER_BEARING.cos_alpha):
    """Eq. 4 for one axis on plain arrays: ``k (i_t^2/g_t^2 - i_b^2/g_b^2)`` [N] (numpy or JAX)."""
    g_top, g_bottom = pole_gaps(g0, x0, x, cos_alpha)
    return horseshoe_force(k, i_top, g_top, k, i_bottom, g_bottom)
