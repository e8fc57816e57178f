"""Zoo laws of the measurement chain and of time (:mod:`ambfit.rig.zoo`): one-coil current channel errors,
position sensor characteristics, drifts in time or temperature, the rig's heating, and three effects that no
contract family describes.

Sensor laws are pairs of maps, ``sense`` (physical -> reading) and its inverse ``unsense``; drifts move the
effective gap and origin in the ``geometry`` stage.  Each class's :meth:`ZooLaw.draw` draws its structure and a
realistic magnitude (compare :mod:`ambfit.physics.effects.sensors` and :mod:`ambfit.physics.effects.thermal`).
"""

from __future__ import annotations

from typing import ClassVar

import jax.numpy as jnp
import numpy as np

from ambfit.physics.stages import _ax, _set
from ambfit.rig.zoo_magnetic import I_REF, Y_REF, _known
from ambfit.rig.zoo_shapes import Shape, ZooLaw, numerics, random_shape, signed

X_REF = 100e-6
"""Reference position [m] of the sensor polynomials."""
_NEWTON_STEPS = 8
"""Newton steps that invert a sensor characteristic: each squares an error that starts below 1e-3 relative."""


def _per_axis(p, axis, xp):
    """:func:`ambfit.physics.stages._ax` in ``xp``: the per-row value of a scalar or ``(v, w)`` parameter."""
    return xp.broadcast_to(xp.asarray(p, dtype=float), (2,))[axis]


def _one_coil(rng, lo, hi):
    """Errors array[2] for the top and the bottom channel of each axis: one coil of one axis or of both, the other
    channels exact."""
    axes = [0, 1] if rng.random() < 0.5 else [int(rng.integers(2))]
    top, bottom = np.zeros(2), np.zeros(2)
    for a in axes:
        (top if rng.random() < 0.5 else bottom)[a] = signed(rng, lo, hi)
    return top, bottom


class ChannelGain(ZooLaw):
    """A gain error on one coil's current channel: ``reading = i (1 + gain + compression (i / I_REF - 1))``.

    One coil of one axis, or one coil of each axis, reads 1-8 % high or low (an uncalibrated shunt or amplifier gain;
    the library's ``current_gain`` spreads a mismatch over both coils of an axis); with chance 0.6 the gain also
    changes with the current by 0.3-2 % over ``I_REF`` (amplifier compression).  A gain error is mostly absorbed
    by the origin: smaller ones hardly show above the noise.  ``top``, ``bottom``,
    ``top_compression``, ``bottom_compression`` are ``(v, w)`` values.
    """

    top: jnp.ndarray
    bottom: jnp.ndarray
    top_compression: jnp.ndarray
    bottom_compression: jnp.ndarray
    name: ClassVar[str] = "zoo_channel_gain"
    family: ClassVar[str] = "current_gain"

    @staticmethod
    def _read(i, e0, e1):
        return i * (1.0 + e0 + e1 * (i / I_REF - 1.0))

    @staticmethod
    def _invert(r, e0, e1):
        a, b = 1.0 + e0 - e1, e1 / I_REF        # the root of b i^2 + a i - r near r / a
        return 2.0 * r / (a + numerics(r, a).sqrt(a**2 + 4.0 * b * r))

    def _channels(self, axis, i_top, i_bottom, f):
        xp = numerics(i_top, self.top)
        return (f(i_top, _per_axis(self.top, axis, xp), _per_axis(self.top_compression, axis, xp)),
                f(i_bottom, _per_axis(self.bottom, axis, xp), _per_axis(self.bottom_compression, axis, xp)))

    def sense(self, axis, i_top, i_bottom, x, y):
        return *self._channels(axis, i_top, i_bottom, self._read), x, y

    def unsense(self, axis, i_top, i_bottom, x, y):
        return *self._channels(axis, i_top, i_bottom, self._invert), x, y

    @classmethod
    def _draw(cls, rng, duration_s):
        top, bottom = _one_coil(rng, 0.01, 0.08)
        bend = signed(rng, 0.003, 0.02) if rng.random() < 0.6 else 0.0
        return cls(*(np.asarray(a) for a in (top, bottom, bend * (top != 0), bend * (bottom != 0))))


class ChannelOffset(ZooLaw):
    """An offset on one coil's current channel: ``reading = i + offset``, 5-25 mA on one coil of one axis or of
    each axis (an uncalibrated Hall sensor or shunt amplifier zero; the library's ``current_offset`` is 4-15 mA)."""

    top: jnp.ndarray
    bottom: jnp.ndarray
    name: ClassVar[str] = "zoo_channel_offset"
    family: ClassVar[str] = "current_offset"

    def sense(self, axis, i_top, i_bottom, x, y):
        xp = numerics(i_top, self.top)
        return i_top + _per_axis(self.top, axis, xp), i_bottom + _per_axis(self.bottom, axis, xp), x, y

    def unsense(self, axis, i_top, i_bottom, x, y):
        xp = numerics(i_top, self.top)
        return i_top - _per_axis(self.top, axis, xp), i_bottom - _per_axis(self.bottom, axis, xp), x, y

    @classmethod
    def _draw(cls, rng, duration_s):
        return cls(*(np.asarray(a) for a in _one_coil(rng, 0.005, 0.025)))


class SensorCharacteristic(ZooLaw):
    """A position sensor's characteristic as a polynomial plus periodic terms in the position.

    ``s = x + X_REF (c1 u + c2 u^2 + c3 u^3) + sum_k a_k (sin(2 pi x / lambda_k + phi_k) - sin(phi_k))``, ``u = x / X_REF``:
    a gain error ``c1`` of 1-4 % (eddy-current probes on another target material), the bending of the probe's
    characteristic (``c2``, ``c3`` 1-5 %) and ripples of 0.3-1.5 µm over 15-80 µm (a target's electrical runout,
    a probe's linearisation table).  Each axis draws which terms it has; at least one is not linear, since a pure
    gain error is absorbed by the gap and origin.  ``coef`` array[2, 3], ``amp``, ``wavelength``, ``phase``
    array[2, 2] per axis.
    """

    coef: jnp.ndarray
    amp: jnp.ndarray
    wavelength: jnp.ndarray
    phase: jnp.ndarray
    name: ClassVar[str] = "zoo_sensor_characteristic"
    family: ClassVar[str] = "position_gain"

    def _read(self, x, axis, slope=False):
        xp = numerics(x, self.coef)
        c, a, lam, ph = (xp.asarray(p)[axis] for p in (self.coef, self.amp, self.wavelength, self.phase))
        u, arg = x / X_REF, 2.0 * xp.pi * x[..., None] / lam + ph
        if slope:
            return (1.0 + c[..., 0] + 2.0 * c[..., 1] * u + 3.0 * c[..., 2] * u**2
                    + xp.sum(a * 2.0 * xp.pi / lam * xp.cos(arg), axis=-1))
        return (x + X_REF * (c[..., 0] * u + c[..., 1] * u**2 + c[..., 2] * u**3)
                + xp.sum(a * (xp.sin(arg) - xp.sin(ph)), axis=-1))

    def _invert(self, s, axis):
        x = s / (1.0 + numerics(s, self.coef).asarray(self.coef)[axis][..., 0])
        for _ in range(_NEWTON_STEPS):
            x = x - (self._read(x, axis) - s) / self._read(x, axis, slope=True)
        return x

    def sense(self, axis, i_top, i_bottom, x, y):
        return i_top, i_bottom, self._read(x, axis), self._read(y, 1 - axis)

    def unsense(self, axis, i_top, i_bottom, x, y):
        return i_top, i_bottom, self._invert(x, axis), self._invert(y, 1 - axis)

    @classmethod
    def _draw(cls, rng, duration_s):
        coef, amp = np.zeros((2, 3)), np.zeros((2, 2))
        for a in range(2):
            while not (coef[a, 1:].any() or amp[a].any()):
                coef[a] = (rng.random(3) < (0.8, 0.5, 0.4)) * signed(rng, (0.01, 0.01, 0.01), (0.04, 0.05, 0.05))
                amp[a] = (rng.random(2) < (0.5, 0.2)) * rng.uniform(0.3e-6, 1.5e-6, 2)
        return cls(np.asarray(coef), np.asarray(amp), np.asarray(rng.uniform(15e-6, 80e-6, (2, 2))),
                   np.asarray(rng.uniform(0.0, 2.0 * np.pi, (2, 2))))


class Heating(ZooLaw):
    """The rig's bearing warming up, ``T = ambient + heating_K (1 - exp(-t / tau_s))``, and nothing else.

    Every zoo case has a temperature history (a thermometer, where one is written, reads it), so that a rising
    temperature does not by itself tell a drift.  ``heating_K`` 0-20 K, ``tau_s`` 0.2-3 times the run's length.
    """

    heating_K: jnp.ndarray
    tau_s: jnp.ndarray
    name: ClassVar[str] = "heating"

    def temperature(self, time_s, ambient_C):
        return ambient_C + self.heating_K * (1.0 - np.exp(-np.asarray(time_s) / self.tau_s))

    @classmethod
    def _draw(cls, rng, duration_s):
        return cls(np.asarray(rng.uniform(0.0, 20.0)), np.asarray(rng.uniform(0.2, 3.0) * duration_s))


def _drift_sizes(rng):
    """Per-axis origin and gap excursions over a run [m]: origin 2-12 µm, gap 0.5-4 µm or (chance 0.3) none."""
    origin = signed(rng, 2e-6, 12e-6, 2)
    gap = np.zeros(2) if rng.random() < 0.3 else signed(rng, 0.5e-6, 4e-6, 2)
    return np.asarray(origin), np.asarray(gap)


class TimeDrift(ZooLaw):
    """Gap and origin drifting as smooth random functions of time: ``x0 += origin_drift f_a(t / duration)``.

    ``f`` are random signed :class:`Shape` s (polynomials, sigmoid steps, lagged ramps, exponential settling, and
    sums of them, so a drift may turn back), one per axis for the origin and one for the gap, each at most 1 in
    size over the run; ``origin_drift`` 2-12 µm, ``gap_drift`` 0.5-4 µm or none (a sensor mount settling, creep, a warm-up
    read on the clock).  Rows without a time are taken at ``t = 0``.
    """

    origin_drift: jnp.ndarray
    gap_drift: jnp.ndarray
    duration: jnp.ndarray
    shape_v: Shape
    shape_w: Shape
    shape_gap: Shape
    name: ClassVar[str] = "zoo_drift_time"
    family: ClassVar[str] = "thermal_drift"

    def geometry(self, ctx):
        u = _known(ctx.time) / self.duration

        def origin(axis):
            return _ax(self.origin_drift, axis) * jnp.where(axis == 0, self.shape_v(u), self.shape_w(u))

        return _set(ctx, g0=ctx.g0 + _ax(self.gap_drift, ctx.axis) * self.shape_gap(u), x0=ctx.x0 + origin(ctx.axis),
                    y0=ctx.y0 + origin(1 - ctx.axis))

    @classmethod
    def _draw(cls, rng, duration_s):
        def shape():
            return random_shape(rng, signed=True, power=(1.0, 3.0), centre=(0.1, 0.9), width=(0.03, 0.3),
                                tau=(0.05, 1.0))

        return cls(*_drift_sizes(rng), np.asarray(duration_s), shape(), shape(), shape())


class TemperatureDrift(ZooLaw):
    """Gap and origin following the bearing's temperature, non-linearly and with a lag.

    The bearing warms as ``T = ambient + heating_K (1 - exp(-t / tau_s))`` (5-20 K, ``tau_s`` 0.2-1.5 run lengths);
    the parts that set the gap and origin follow it through a first-order lag ``lag_s`` (none, or 0.05-0.5 run
    lengths: the rotor and the sensor mount are not where the thermometer is): with ``r`` the lagged rise over
    ``heating_K``, ``x0 += origin_drift (r + curve r^2) / (1 + curve)`` (``curve`` -0.6-0.6), likewise the gap,
    moving the origin 2-12 µm and the gap 0.5-4 µm (or not) by the run's end (Schweitzer & Maslen 2009, ch. 4).
    """

    origin_drift: jnp.ndarray
    gap_drift: jnp.ndarray
    curve: jnp.ndarray
    heating_K: jnp.ndarray
    tau_s: jnp.ndarray
    lag_s: jnp.ndarray
    name: ClassVar[str] = "zoo_drift_temperature"
    family: ClassVar[str] = "thermal_drift"

    def rise(self, t):
        """The lagged temperature rise [K] at time ``t`` [s] (the first-order lag of the heating curve)."""
        tau, lag = self.tau_s, self.lag_s
        lagged = (tau * jnp.exp(-t / tau) - lag * jnp.exp(-t / jnp.maximum(lag, 1e-9))) / (tau - lag)
        return self.heating_K * (1.0 - jnp.where(lag > 0, lagged, jnp.exp(-t / tau)))

    def shift(self, t):
        """The drift's course [-]: 0 at the start, 1 once the lagged rise is the whole heating."""
        r = self.rise(t) / self.heating_K
        return (r + self.curve * r**2) / (1.0 + self.curve)

    def geometry(self, ctx):
        s = self.shift(_known(ctx.time))
        return _set(ctx, g0=ctx.g0 + _ax(self.gap_drift, ctx.axis) * s, x0=ctx.x0 + _ax(self.origin_drift, ctx.axis) * s,
                    y0=ctx.y0 + _ax(self.origin_drift, 1 - ctx.axis) * s)

    def temperature(self, time_s, ambient_C):
        return ambient_C + self.heating_K * (1.0 - np.exp(-np.asarray(time_s) / self.tau_s))

    @classmethod
    def _draw(cls, rng, duration_s):
        heating, tau = rng.uniform(5.0, 20.0), rng.uniform(0.2, 1.5) * duration_s
        lag = 0.0 if rng.random() < 0.3 else rng.uniform(0.05, 0.5) * duration_s
        while abs(lag - tau) < 0.02 * duration_s:
            lag = rng.uniform(0.05, 0.5) * duration_s
        origin, gap = _drift_sizes(rng)
        law = cls(origin, gap, *(np.asarray(a) for a in (rng.uniform(-0.6, 0.6), heating, tau, lag)))
        end = float(law.shift(duration_s))     # the excursions drawn are those at the run's end
        return cls(origin / end, gap / end, law.curve, law.heating_K, law.tau_s, law.lag_s)


class ProbePickup(ZooLaw):
    """No family: the position probe picks up the coils' field, ``s = x + p1 (i_t - i_b) + p2 (i_t^2 - i_b^2) / 1 A``.

    An eddy-current probe beside a pole sees the coil's stray field (its reading moves with the control current
    at a fixed rotor position): ``p1`` 1.5-6 µm/A, ``p2`` none or 0.5-2 µm/A^2, per axis.  Only a row's own
    axis' currents are known where a reading is sensed, so the other axis' position ``y`` is left as it is.
    """

    p1: jnp.ndarray
    p2: jnp.ndarray
    name: ClassVar[str] = "zoo_probe_pickup"

    def _pickup(self, axis, i_top, i_bottom):
        xp = numerics(i_top, self.p1)
        return (_per_axis(self.p1, axis, xp) * (i_top - i_bottom)
                + _per_axis(self.p2, axis, xp) * (i_top**2 - i_bottom**2))

    def sense(self, axis, i_top, i_bottom, x, y):
        return i_top, i_bottom, x + self._pickup(axis, i_top, i_bottom), y

    def unsense(self, axis, i_top, i_bottom, x, y):
        return i_top, i_bottom, x - self._pickup(axis, i_top, i_bottom), y

    @classmethod
    def _draw(cls, rng, duration_s):
        p2 = np.zeros(2) if rng.random() < 0.5 else signed(rng, 0.5e-6, 2e-6, 2)
        return cls(np.asarray(signed(rng, 1.5e-6, 6e-6, 2)), np.asarray(p2))


class ZeroOscillation(ZooLaw):
    """No family: the probes' zero oscillates slowly, ``s = x + amp sin(2 pi t / period + phase)``.

    A ground loop or a thermostat cycling near the sensor electronics: 0.7-3 µm, 3-8 periods over the run, so no
    drift (monotone or turning once) describes it.  A shift of the sensor's zero moves the effective origin, in
    sensor coordinates, the other way.
    """

    amp: jnp.ndarray
    period: jnp.ndarray
    phase: jnp.ndarray
    name: ClassVar[str] = "zoo_zero_oscillation"

    def geometry(self, ctx):
        t = _known(ctx.time)

        def zero(axis):
            return _ax(self.amp, axis) * jnp.sin(2.0 * jnp.pi * t / self.period + _ax(self.phase, axis))

        return _set(ctx, x0=ctx.x0 - zero(ctx.axis), y0=ctx.y0 - zero(1 - ctx.axis))

    @classmethod
    def _draw(cls, rng, duration_s):
        return cls(np.asarray(rng.uniform(0.7e-6, 3e-6, 2)), np.asarray(duration_s / rng.uniform(3.0, 8.0)),
                   np.asarray(rng.uniform(0.0, 2.0 * np.pi, 2)))


class MechanicalSpring(ZooLaw):
    """No family: a mechanical stiffness on the rotor, ``F -= k1 u + k3 u^3 / Y_REF^2`` with ``u = x0 + x``.

    A flexible coupling to the drive, a cable or a seal pulls the rotor towards its own rest position whatever
    the currents: ``k1`` 3000-10000 N/m, ``k3`` none or 0.02-0.1 N at ``Y_REF`` per axis.  No family of the contract
    writes a force that does not pass through the coils.
    """

    k1: jnp.ndarray
    k3: jnp.ndarray
    name: ClassVar[str] = "zoo_mechanical_spring"

    def force(self, ctx, force):
        u = ctx.x0 + ctx.x
        return force - _ax(self.k1, ctx.axis) * u - _ax(self.k3, ctx.axis) * (u / Y_REF) ** 3

    @classmethod
    def _draw(cls, rng, duration_s):
        k3 = np.zeros(2) if rng.random() < 0.5 else signed(rng, 0.02, 0.1, 2)
        return cls(np.asarray(rng.uniform(3000.0, 10000.0, 2)), np.asarray(k3))


MEASUREMENT: dict[str, tuple[type[ZooLaw], ...]] = {
    "current_offset": (ChannelOffset,),
    "current_gain": (ChannelGain,),
    "position_gain": (SensorCharacteristic,),
    "thermal_drift": (TimeDrift, TemperatureDrift),
}
"""The zoo's law classes of the measurement chain and of time by contract family."""

NO_FAMILY: tuple[type[ZooLaw], ...] = (ProbePickup, ZeroOscillation, MechanicalSpring)
"""Effects that no contract family describes: a diagnosis should call them ``unexplained`` or ``undecided``."""
