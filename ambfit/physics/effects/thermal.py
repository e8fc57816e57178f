"""Thermal drift: the effective gap and origin move with the bearing's temperature."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from ambfit.physics.stages import Effect, _ax, _set


class ThermalDrift(Effect):
    """Gap and origin drift with bearing temperature.

    ``g0(T) = g0 + dg_dT (T - ref_C)``, ``x0(T) = x0 + dx0_dT (T - ref_C)``.
    Differential expansion of rotor and stator (Δα ≈ 5e-6 /K over a 17.5 mm radius)
    gives about 0.1 µm/K on the gap; sensor-mount growth moves the origin 0.3-2
    µm/K.  On the rig the coils heat the bearing by ``heating_K`` with time constant
    ``tau_s``: ``T(t) = ambient + heating_K (1 - exp(-t / tau_s))``.  Rows without a
    temperature are taken at ``ref_C``.
    """

    dg_dT: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(0.2e-6))
    dx0_dT: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(1.0e-6))
    heating_K: float = 15.0
    tau_s: float = 900.0
    ref_C: float = 22.0
    name: ClassVar[str] = "thermal_drift"
    RANGES: ClassVar = {"dg_dT": (0.1e-6, 0.5e-6), "dx0_dT": (0.5e-6, 2.0e-6)}
    SIGNED: ClassVar = ("dx0_dT",)
    UNITS: ClassVar = {"dg_dT": "m/K", "dx0_dT": "m/K", "heating_K": "K", "tau_s": "s", "ref_C": "°C"}

    def geometry(self, ctx):
        dt = jnp.where(jnp.isnan(ctx.temperature), 0.0, ctx.temperature - self.ref_C)
        return _set(ctx, g0=ctx.g0 + _ax(self.dg_dT, ctx.axis) * dt,
                    x0=ctx.x0 + _ax(self.dx0_dT, ctx.axis) * dt,
                    y0=ctx.y0 + _ax(self.dx0_dT, 1 - ctx.axis) * dt)

    def temperature(self, time_s, ambient_C):
        return ambient_C + self.heating_K * (1.0 - jnp.exp(-jnp.asarray(time_s) / self.tau_s))
