"""Thermal drift: the effective gap and origin move with the bearing's temperature, or with time when no
temperature is measured."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from ambfit.physics.stages import Effect, _ax, _set

_HEATING_K, _TAU_S = 15.0, 900.0
"""The rig's coil heating [K] and its time constant [s] (:class:`ThermalDrift`'s defaults)."""
_RANGE_dg_dT, _RANGE_dx0_dT = (0.1e-6, 0.5e-6), (0.5e-6, 2.0e-6)
_HEAT_RATE = _HEATING_K / _TAU_S
"""Initial slope [K/s] of the rig's heating curve: it turns the temperature coefficients' ranges into rates."""


class ThermalDrift(Effect):
    """Gap and origin drift with bearing temperature or, where none is measured, with time.

    A row with a temperature ``T`` [°C] (``temperature_C``)::

        g0 = g0 + dg_dT (T - ref_C),    x0 = x0 + dx0_dT (T - ref_C)        (dg_dT, dx0_dT in m/K)

    A row without one but with a time ``t`` [s] (``time_s``)::

        g0 = g0 + dg_dt t,              x0 = x0 + dx0_dt t                  (dg_dt, dx0_dt in m/s)

    where ``t`` counts from the start of the rows' clock (:func:`ambfit.rows.clock`: the file's first reading
    when its experiments were read one after another, each experiment's first when each restarted its clock),
    so the fitted gap and origin are those at that start, and nothing depends on where the clock's zero is.  A
    row with neither is taken at ``ref_C``, i.e. without drift; a temperature column that does not change is no
    thermometer (:func:`ambfit.rows.thermometer`).

    Differential expansion of rotor and stator (Δα ≈ 5e-6 /K over a 17.5 mm radius) gives about 0.1 µm/K on
    the gap; sensor-mount growth moves the origin 0.3-2 µm/K.  On the rig the coils heat the bearing by
    ``heating_K`` with time constant ``tau_s``: ``T(t) = ambient + heating_K (1 - exp(-t / tau_s))``.
    When the cause of a drift is not measured, a drift linear in time is its first-order model over a
    measurement short against its time constant; the heating curve is the case whose ``tau_s`` is known, and is
    not assumed.  The rates' ranges are the temperature coefficients' times the heating curve's initial slope
    ``heating_K / tau_s``; both rates are signed (a bearing may be cooling).

    Each law's parameters are seen only by rows that use it: fitted on data without a temperature column, the
    temperature coefficients stay at their prior (and the rates on data with one); their Jacobian columns are
    zero, so the other estimates are those of the law the data do see.  Schweitzer & Maslen (eds.), *Magnetic
    Bearings*, Springer 2009, ch. 4: the gap and origin of a radial bearing follow its thermal state.
    """

    dg_dT: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(0.2e-6))
    dx0_dT: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(1.0e-6))
    dg_dt: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(0.2e-6 * _HEAT_RATE))
    dx0_dt: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(1.0e-6 * _HEAT_RATE))
    heating_K: float = _HEATING_K
    tau_s: float = _TAU_S
    ref_C: float = 22.0
    name: ClassVar[str] = "thermal_drift"
    RANGES: ClassVar = {"dg_dT": _RANGE_dg_dT, "dx0_dT": _RANGE_dx0_dT,
                        "dg_dt": tuple(r * _HEAT_RATE for r in _RANGE_dg_dT),
                        "dx0_dt": tuple(r * _HEAT_RATE for r in _RANGE_dx0_dT)}
    SIGNED: ClassVar = ("dx0_dT", "dg_dt", "dx0_dt")
    UNITS: ClassVar = {"dg_dT": "m/K", "dx0_dT": "m/K", "dg_dt": "m/s", "dx0_dt": "m/s", "heating_K": "K",
                       "tau_s": "s", "ref_C": "°C"}

    def drift(self, ctx):
        """The change of the row's own gap, its own origin and the other axis' origin [m]."""
        measured = ~jnp.isnan(ctx.temperature)
        d_temp = jnp.where(measured, ctx.temperature - self.ref_C, 0.0)
        d_time = jnp.where(measured | jnp.isnan(ctx.time), 0.0, ctx.time)

        def shift(per_kelvin, per_second, axis):
            return _ax(per_kelvin, axis) * d_temp + _ax(per_second, axis) * d_time

        return (shift(self.dg_dT, self.dg_dt, ctx.axis), shift(self.dx0_dT, self.dx0_dt, ctx.axis),
                shift(self.dx0_dT, self.dx0_dt, 1 - ctx.axis))

    def geometry(self, ctx):
        dg, dx0, dy0 = self.drift(ctx)
        return _set(ctx, g0=ctx.g0 + dg, x0=ctx.x0 + dx0, y0=ctx.y0 + dy0)

    def temperature(self, time_s, ambient_C):
        return ambient_C + self.heating_K * (1.0 - jnp.exp(-jnp.asarray(time_s) / self.tau_s))
