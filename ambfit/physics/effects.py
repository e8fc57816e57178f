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

General reference for the magnetics: Schweitzer & Maslen (eds.), *Magnetic
Bearings: Theory, Design, and Application to Rotating Machinery*, Springer 2009,
ch. 3-4 (pp. 69-109).
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ambfit.physics.bearing import PAPER_BEARING
from ambfit.physics.stages import Effect, _ax, _set

__all__ = [
    "Effect", "Saturation", "IronReluctance", "Fringing", "Leakage", "CurrentOffset",
    "CurrentGain", "PositionGain", "CrossCoupling", "Hysteresis", "ThermalDrift", "MagneticCircuit",
    "EFFECTS", "CIRCUITS", "effect_by_name",
]


class Saturation(Effect):
    """Iron saturation: the gap flux density lags the linear law ``B = MU_0 (2 N) i / (2 g)``.

    (:meth:`ambfit.Bearing.flux_density`, ``N`` the turns of one pole.)

    ``B_eff = B / (1 + (B / b_sat)**sharpness)**(1 / sharpness)``, so the pole force
    (proportional to ``B_eff**2``) falls below the square law at high flux density.
    A Froehlich-type knee; silicon-iron laminations saturate at 1.2-1.6 T
    (Schweitzer & Maslen 2009, sec. 3.2, pp. 73-76).  The paper's rig reaches
    about 1.2 T at its 3.0 A saturation current.
    """

    b_sat: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(1.3))
    sharpness: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(5.0))
    name: ClassVar[str] = "saturation"
    RANGES: ClassVar = {"b_sat": (1.0, 1.3), "sharpness": (3.0, 6.0)}
    UNITS: ClassVar = {"b_sat": "T", "sharpness": "-"}

    def factor(self, b, axis):
        bs, p = _ax(self.b_sat, axis), _ax(self.sharpness, axis)
        return (1.0 + (jnp.abs(b) / bs) ** p) ** (-2.0 / p)

    def coil(self, ctx):
        return _set(ctx, k_top=ctx.k_top * self.factor(ctx.b_top(), ctx.axis),
                    k_bottom=ctx.k_bottom * self.factor(ctx.b_bottom(), ctx.axis))


class IronReluctance(Effect):
    """Finite iron permeability: the magnetic gap is ``g + l_fe / (2 mu_r(B))``.

    ``l_fe`` is the equivalent iron path length of stator and rotor (the paper's
    ``b_th``), ``mu_r(B) = mu_r / (1 + (B / b_knee)**4)`` falls near saturation, so
    the extra gap grows with current.  With ``l_fe`` = 60-120 mm and ``mu_r`` =
    1500-5000 (unsaturated silicon iron) the constant part is 6-40 µm (Schweitzer & Maslen 2009, sec. 4.2,
    eq. 4.8, p. 83: ``B = MU_0 (2 N) i / (2 g + l_fe / mu_r)``).
    """

    l_fe: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(PAPER_BEARING.iron_path))
    mu_r: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(3000.0))
    b_knee: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(1.4))
    name: ClassVar[str] = "iron_reluctance"
    RANGES: ClassVar = {"l_fe": (0.06, 0.12), "mu_r": (1500.0, 5000.0), "b_knee": (1.0, 1.3)}
    UNITS: ClassVar = {"l_fe": "m", "mu_r": "-", "b_knee": "T"}

    def ranges(self) -> dict[str, tuple[float, float]]:
        """``mu_r`` and ``b_knee``; ``l_fe`` is held at this instance's value (the paper bearing's iron path by
        default).  The extra gap is ``l_fe (1 + (B / b_knee)^4) / (2 mu_r)``: the two enter only as their ratio,
        so fitting both left Levenberg-Marquardt crawling along that ratio's valley, held by the priors alone
        (840 rig readings: 404 steps for five fits, one not converged).  The fitted ``mu_r`` is the permeability
        at the held path length; a rig draws both (``RANGES``)."""
        return {k: v for k, v in type(self).RANGES.items() if k != "l_fe"}

    def extra_gap(self, i, g, ctx):
        b = ctx.bearing.flux_density(i, g)
        mu = _ax(self.mu_r, ctx.axis) / (1.0 + (b / _ax(self.b_knee, ctx.axis)) ** 4)
        return _ax(self.l_fe, ctx.axis) / (2.0 * mu)

    def gap(self, ctx):
        return _set(ctx, g_top=ctx.g_top + self.extra_gap(ctx.i_top, ctx.g_top, ctx),
                    g_bottom=ctx.g_bottom + self.extra_gap(ctx.i_bottom, ctx.g_bottom, ctx))


class Fringing(Effect):
    """Fringing: the effective pole area grows with the gap.

    ``A_eff = (w + 2 c g) (l + 2 c g)``, so each coil's force constant is scaled by
    ``(1 + 2 c g / w) (1 + 2 c g / l)`` with ``w`` and ``l`` the pole width and axial
    length (from the bearing description).  ``c`` = 0.3-1.0 covers the usual fringe-width
    estimates (Roters, *Electromagnetic Devices*, Wiley 1941, ch. 5; Schweitzer & Maslen 2009, p. 84).
    """

    coefficient: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(0.5))
    name: ClassVar[str] = "fringing"
    RANGES: ClassVar = {"coefficient": (0.3, 1.0)}
    UNITS: ClassVar = {"coefficient": "-"}

    def area_factor(self, g, axis, bearing):
        c = _ax(self.coefficient, axis)
        return (1.0 + 2.0 * c * g / bearing.pole_width) * (1.0 + 2.0 * c * g / bearing.pole_length)

    def coil(self, ctx):
        return _set(ctx, k_top=ctx.k_top * self.area_factor(ctx.g_top, ctx.axis, ctx.bearing),
                    k_bottom=ctx.k_bottom * self.area_factor(ctx.g_bottom, ctx.axis, ctx.bearing))


class Leakage(Effect):
    """Flux leakage between poles: part of the coil flux never crosses the gap.

    The gap flux is ``(1 - sigma)`` times the ideal, with
    ``sigma = sigma0 + sigma1 tanh((B / 1 T)^2)`` rising as the iron nears saturation
    (bounded, so the force stays monotone in the current); the force scales with
    ``(1 - sigma)^2``.
    Leakage of 5-20 % is typical of radial heteropolar bearings (Schweitzer & Maslen
    2009, sec. 4.2.3, p. 87; Meeker, Maslen & Noh, IEEE Trans. Magn. 32(4), 1996).
    """

    sigma0: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(0.1))
    sigma1: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(0.03))
    name: ClassVar[str] = "leakage"
    RANGES: ClassVar = {"sigma0": (0.05, 0.2), "sigma1": (0.02, 0.08)}
    UNITS: ClassVar = {"sigma0": "-", "sigma1": "-"}

    def factor(self, b, axis):
        return (1.0 - _ax(self.sigma0, axis) - _ax(self.sigma1, axis) * jnp.tanh(b**2)) ** 2

    def coil(self, ctx):
        return _set(ctx, k_top=ctx.k_top * self.factor(ctx.b_top(), ctx.axis),
                    k_bottom=ctx.k_bottom * self.factor(ctx.b_bottom(), ctx.axis))


class CurrentOffset(Effect):
    """Additive offset of the current channels: reading = physical + offset [A].

    ``top`` and ``bottom`` are ``(v, w)`` offsets.  The paper calibrates its DAQ to
    0.1 % of 3 A, i.e. offsets of a few mA; 2-15 mA covers an uncalibrated Hall
    sensor or shunt amplifier.
    """

    top: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(0.005))
    bottom: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(-0.005))
    name: ClassVar[str] = "current_offset"
    RANGES: ClassVar = {"top": (0.004, 0.015), "bottom": (0.004, 0.015)}
    SIGNED: ClassVar = ("top", "bottom")
    UNITS: ClassVar = {"top": "A", "bottom": "A"}

    def sense(self, axis, i_top, i_bottom, x, y):
        return i_top + _ax(self.top, axis), i_bottom + _ax(self.bottom, axis), x, y

    def unsense(self, axis, i_top, i_bottom, x, y):
        return i_top - _ax(self.top, axis), i_bottom - _ax(self.bottom, axis), x, y


class CurrentGain(Effect):
    """Gain mismatch between the top and bottom current channels.

    reading_top = (1 + mismatch/2) i_top, reading_bottom = (1 - mismatch/2) i_bottom.
    0.2-2 % is the spread of shunt resistors and amplifier gains (paper: DAQ
    calibrated to 0.1 %).
    """

    mismatch: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(0.01))
    name: ClassVar[str] = "current_gain"
    RANGES: ClassVar = {"mismatch": (0.003, 0.02)}
    SIGNED: ClassVar = ("mismatch",)
    UNITS: ClassVar = {"mismatch": "-"}

    def sense(self, axis, i_top, i_bottom, x, y):
        e = _ax(self.mismatch, axis) / 2.0
        return i_top * (1.0 + e), i_bottom * (1.0 - e), x, y

    def unsense(self, axis, i_top, i_bottom, x, y):
        e = _ax(self.mismatch, axis) / 2.0
        return i_top / (1.0 + e), i_bottom / (1.0 - e), x, y


class PositionGain(Effect):
    """Gain error of the position sensors: reading = (1 + gain_error) * physical.

    ``gain_error`` is ``(v, w)``.  Eddy-current probes drift 0.5-3 % with target
    material and temperature; the paper's micrometer calibration is good to 0.25 %.
    A gain error rescales the identified gap and origin (it is absorbed).
    """

    gain_error: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(0.02))
    name: ClassVar[str] = "position_gain"
    RANGES: ClassVar = {"gain_error": (0.01, 0.04)}
    SIGNED: ClassVar = ("gain_error",)
    UNITS: ClassVar = {"gain_error": "-"}

    def sense(self, axis, i_top, i_bottom, x, y):
        return i_top, i_bottom, x * (1.0 + _ax(self.gain_error, axis)), y * (1.0 + _ax(self.gain_error, 1 - axis))

    def unsense(self, axis, i_top, i_bottom, x, y):
        return i_top, i_bottom, x / (1.0 + _ax(self.gain_error, axis)), y / (1.0 + _ax(self.gain_error, 1 - axis))


class CrossCoupling(Effect):
    """The other axis' displacement changes this axis' force.

    Two parts: (1) geometry: the two poles of a horseshoe sit at ``±alpha``, so an
    other-axis displacement ``y' = y0 + y`` opens one pole's gap by ``y' sin(alpha)``
    and closes the other's, raising the horseshoe force by the factor
    ``((1 - a)^-2 + (1 + a)^-2) / 2`` with ``a = geometric * y' sin(alpha) / g``;
    (2) magnetic coupling through shared back-iron and rotor misalignment, a cross
    stiffness ``kappa`` [N/m] acting on ``y'``: 1-5 % of the bearing's negative
    stiffness (about 6e4 N/m for the paper's rig), cf. Schweitzer & Maslen 2009,
    sec. 4.4, p. 95, and Meeker et al. 1996.
    """

    kappa: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(1500.0))
    geometric: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(1.0))
    name: ClassVar[str] = "cross_coupling"
    RANGES: ClassVar = {"kappa": (1000.0, 3000.0), "geometric": (1.0, 1.0)}
    SIGNED: ClassVar = ("kappa",)
    UNITS: ClassVar = {"kappa": "N/m", "geometric": "-"}

    def _pair(self, g, yp, ctx):
        a = _ax(self.geometric, ctx.axis) * yp * ctx.bearing.sin_alpha / g
        return 0.5 * ((1.0 - a) ** -2 + (1.0 + a) ** -2)

    def coil(self, ctx):
        yp = ctx.y0 + ctx.y
        return _set(ctx, k_top=ctx.k_top * self._pair(ctx.g_top, yp, ctx),
                    k_bottom=ctx.k_bottom * self._pair(ctx.g_bottom, yp, ctx))

    def force(self, ctx, force):
        return force + _ax(self.kappa, ctx.axis) * (ctx.y0 + ctx.y)


class Hysteresis(Effect):
    """Magnetic hysteresis as a play operator on each coil's magnetising current.

    The magnetising current ``m`` follows the coil current with a dead band of
    half-width ``width`` [A]: ``m = clip(m_prev, i - width, i + width)``, so the
    force at a given current depends on the direction it was approached from and
    the order of readings matters.  ``width = H_c l_fe / N``: coercive field 20-80
    A/m of silicon iron over the paper rig's 80 mm path and 2 x 240 turns gives 3-13 mA
    (Bozorth, *Ferromagnetism*, 1951, ch. 2; Mayergoyz, *Mathematical Models of
    Hysteresis*, 1991, ch. 1 for the play operator).  In a fit, where no history
    state is given, ``m = i - width * direction`` with the approach direction
    derived from the order of readings.
    """

    width: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(0.008))
    name: ClassVar[str] = "hysteresis"
    RANGES: ClassVar = {"width": (0.008, 0.02)}
    UNITS: ClassVar = {"width": "A"}
    stateful: ClassVar[bool] = True

    def play(self, i, m_prev, axis):
        h = _ax(self.width, axis)
        return jnp.clip(m_prev, i - h, i + h)

    def coil(self, ctx):
        h = _ax(self.width, ctx.axis)
        def one(i, m_prev, direction):
            return jnp.where(jnp.isnan(m_prev), i - h * direction, jnp.clip(m_prev, i - h, i + h))
        return _set(ctx, m_top=one(ctx.m_top, ctx.m_prev_top, ctx.dir_top),
                    m_bottom=one(ctx.m_bottom, ctx.m_prev_bottom, ctx.dir_bottom))


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
    RANGES: ClassVar = {"fringe_depth": (1.0e-3, 5.0e-3), "leakage": (0.2, 1.0), "iron_scale": (0.5, 2.0),
                        "pole_area_ratio": (0.5, 1.0)}
    UNITS: ClassVar = {"fringe_depth": "m", "leakage": "-", "iron_scale": "-", "pole_area_ratio": "-"}
    needs_other_axis: ClassVar[bool] = True
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

    def without(self, piece: str) -> MagneticCircuit:
        """The same circuit with one more piece (``PIECES``) switched off."""
        if piece not in self.PIECES:
            raise ValueError(f"unknown piece {piece!r}; pieces: {', '.join(self.PIECES)}")
        return eqx.tree_at(lambda e: e.on, self, jnp.asarray(self.on).at[self.PIECES.index(piece)].set(0.0))

    def force(self, ctx, force):
        from ambfit.physics import circuit

        a = ctx.axis
        sat, iron, fringing, leak, coupling = (self.on[j] for j in range(5))
        params = circuit.MECParams.drawing(ctx.bearing).replace(
            gap=ctx.g0, fringe_depth=fringing * _ax(self.fringe_depth, a), leakage=leak * _ax(self.leakage, a),
            iron_h_scale=iron * _ax(self.iron_scale, a),
            pole_area_ratio=iron * _ax(self.pole_area_ratio, a) + (1.0 - iron), link=coupling, saturation=sat)
        bearing = ctx.bearing
        f = circuit.row_axis_force(params, bearing, a, ctx.m_top, ctx.m_bottom, ctx.i_top_other,
                                   ctx.i_bottom_other, ctx.x, ctx.y, ctx.x0, ctx.y0)
        return f * ctx.k / ctx.bearing.force_constant(1.0)


EFFECTS: dict[str, type[Effect]] = {
    cls.name: cls
    for cls in (Saturation, IronReluctance, Fringing, Leakage, CurrentOffset, CurrentGain,
                PositionGain, CrossCoupling, Hysteresis, ThermalDrift)
}
"""Every effect class of the contract (section 3) by its name."""

CIRCUITS: dict[str, type[Effect]] = {MagneticCircuit.name: MagneticCircuit}
"""Models that replace Eq. 4 by a magnetic circuit of the whole bearing (they need both axes' currents)."""


def effect_by_name(name: str, **params) -> Effect:
    """An effect from its contract name and parameters (SI units; defaults otherwise)."""
    known = {**EFFECTS, **CIRCUITS}
    try:
        cls = known[name]
    except KeyError:
        raise ValueError(f"unknown effect {name!r}; valid names: {', '.join(known)}") from None
    fields = {f.name for f in dataclasses.fields(cls)}
    bad = set(params) - fields
    if bad:
        raise ValueError(f"effect {name!r} has no parameter(s) {sorted(bad)}; valid: {sorted(fields)}")
    conv = {k: (jnp.asarray(v, dtype=float) if k in cls.RANGES else v) for k, v in params.items()}
    return cls(**conv)
