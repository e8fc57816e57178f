"""Effects of the iron and the gaps on the magnetic force: saturation, finite iron permeability, fringing,
leakage, cross-coupling between the axes and hysteresis.

Each patches one stage of the ideal law (:mod:`ambfit.physics.stages`); the magnetic circuit of
the whole bearing (:class:`~ambfit.physics.effects.magnetic_circuit.MagneticCircuit`) holds the
first five as one physics.  General reference: Schweitzer & Maslen (eds.), *Magnetic Bearings:
Theory, Design, and Application to Rotating Machinery*, Springer 2009, ch. 3-4 (pp. 69-109).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from ambfit.physics.bearing import PAPER_BEARING
from ambfit.physics.stages import Effect, _ax, _set


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
    FROM_BEARING: ClassVar = {"l_fe": "iron_path"}

    def ranges(self) -> dict[str, tuple[float, float]]:
        """``mu_r`` and ``b_knee``; ``l_fe`` is held at this instance's value (the paper bearing's iron path by
        default).  The extra gap is ``l_fe (1 + (B / b_knee)^4) / (2 mu_r)``: the two enter only as their ratio,
        so fitting both leaves Levenberg-Marquardt crawling along that ratio's valley, held by the priors alone
        (on 840 rig readings five such fits take 404 steps, and one does not converge).  The fitted ``mu_r`` is the
        permeability at the held path length; a rig draws both (``RANGES``)."""
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
        return play_coils(ctx, self.width)


def play_coils(ctx, width):
    """Both coils' states after a play operator of half-width ``width`` [A] (scalar or per axis): the previous state
    ``m_prev`` clipped to ``[i - width, i + width]``, or without one (a fit) ``i - width * direction``."""
    h = _ax(width, ctx.axis)

    def one(i, m_prev, direction):
        return jnp.where(jnp.isnan(m_prev), i - h * direction, jnp.clip(m_prev, i - h, i + h))

    return _set(ctx, m_top=one(ctx.m_top, ctx.m_prev_top, ctx.dir_top),
                m_bottom=one(ctx.m_bottom, ctx.m_prev_bottom, ctx.dir_bottom))
