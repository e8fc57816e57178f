"""Zoo laws of the iron and the gaps (:mod:`ambfit.rig.zoo`): saturation, iron reluctance, fringing, leakage and
cross-coupling, each with a drawn structure (:mod:`ambfit.rig.zoo_shapes`); hysteresis is
:mod:`ambfit.rig.zoo_hysteresis`.

Each class is one broad form of its family's physics; :meth:`ZooLaw.draw` draws its structure (which terms,
where the knee sits, how sharp) and scales it to a realistic magnitude, comparable to the library's ``RANGES``
(:mod:`ambfit.physics.effects.magnetic`).  Draws whose force would not rise with the coil current (the rig
solves for equilibria on a monotone force-current curve) are drawn again.  General reference: Schweitzer &
Maslen (eds.), *Magnetic Bearings*, Springer 2009, ch. 3-4 (pp. 69-109).
"""

from __future__ import annotations

from typing import ClassVar

import jax.numpy as jnp
import numpy as np

from ambfit.physics.bearing import PAPER_BEARING
from ambfit.physics.stages import _ax, _set
from ambfit.rig.zoo_shapes import Shape, ZooLaw, log_uniform, numerics, random_shape, signed

B_REF = 0.8
"""Reference flux density [T]: about the largest the zoo's protocols reach on the paper's bearing (2.2 A on a
725 µm pole gap); the knee laws are scaled by what they do there."""
I_REF = 2.0
"""Reference coil current [A] of the current-dependent laws (about the largest coil current of the protocols)."""
Y_REF = 50e-6
"""Reference displacement [m] of the cross-coupling polynomials (about the largest of the protocols)."""


def _known(value):
    return jnp.where(jnp.isnan(value), 0.0, value)


def _rises(force_of_current) -> bool:
    """Whether a pole's force rises with its current over 0.02-3 A (draw-time check, numpy)."""
    i = np.linspace(0.02, PAPER_BEARING.max_current, 300)
    return bool(np.all(np.diff(np.asarray(force_of_current(i))) > 0))


def _b(i):
    """Ideal-circuit flux density [T] of current ``i`` [A] at the paper bearing's nominal gap (draw-time checks)."""
    return PAPER_BEARING.flux_density(i, PAPER_BEARING.nominal_gap)


def _scale_k(ctx, factor):
    return _set(ctx, k_top=ctx.k_top * factor(ctx.b_top()), k_bottom=ctx.k_bottom * factor(ctx.b_bottom()))


class KneeSaturation(ZooLaw):
    """Saturation with a random monotone knee: the pole force is scaled by ``1 / (1 + depth f(B / B_REF))``.

    ``f`` is a random increasing :class:`Shape` (powers ``u^2``-``u^8``, logistic steps, smooth ramps) of the
    ideal-circuit flux density ``B`` with ``f(1) = 1``; ``depth`` sets the force deficit at ``B_REF`` (2-15 %, as the
    library's Froehlich knee has at 0.8 T over its ``RANGES``).  Schweitzer & Maslen 2009, sec. 3.2, pp. 73-76.
    """

    depth: jnp.ndarray
    shape: Shape
    name: ClassVar[str] = "zoo_saturation_knee"
    family: ClassVar[str] = "saturation"

    def factor(self, b):
        return 1.0 / (1.0 + self.depth * self.shape(b / B_REF))

    def coil(self, ctx):
        return _scale_k(ctx, self.factor)

    @classmethod
    def _draw(cls, rng, duration_s):
        while True:
            deficit = log_uniform(rng, 0.02, 0.15)
            law = cls(np.asarray(deficit / (1.0 - deficit)),
                      random_shape(rng, kinds=("power", "step", "knee"), power=(2.0, 8.0), centre=(0.5, 1.6),
                                   width=(0.05, 0.4)))
            if _rises(lambda i: i**2 * law.factor(_b(i))):
                return law


class CurveSaturation(ZooLaw):
    """Saturation as a random anhysteretic curve: ``B_eff = b_s phi(B / b_s)``, the force scaled by ``(B_eff / B)^2``.

    ``phi`` is a random mixture (``weights``) of ``tanh x``, ``(2 / pi) atan(pi x / 2)`` and the Froehlich curve
    ``x / (1 + x^p)^(1 / p)`` (random ``p``): all rise as ``x`` at first and level off at 1.  ``b_s`` is set so
    that the force deficit at ``B_REF`` is 2-15 % (Jiles & Atherton, J. Magn. Magn. Mater. 61, 1986).
    """

    b_s: jnp.ndarray
    weights: jnp.ndarray
    p: jnp.ndarray
    name: ClassVar[str] = "zoo_saturation_curve"
    family: ClassVar[str] = "saturation"

    def factor(self, b):
        xp = numerics(b)
        x = xp.maximum(xp.abs(b), 1e-9) / self.b_s
        curves = (xp.tanh(x), 2.0 / xp.pi * xp.arctan(xp.pi * x / 2.0), x / (1.0 + x**self.p) ** (1.0 / self.p))
        return (sum(w * c for w, c in zip(self.weights, curves)) / x) ** 2

    def coil(self, ctx):
        return _scale_k(ctx, self.factor)

    @classmethod
    def _draw(cls, rng, duration_s):
        weights, p = np.asarray(rng.dirichlet(np.full(3, 0.7))), np.asarray(rng.uniform(2.0, 8.0))
        deficit = log_uniform(rng, 0.02, 0.15)
        lo, hi = np.log(0.3), np.log(30.0)      # b_s [T], bisected: the deficit falls as b_s grows
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            short = 1.0 - float(cls(np.asarray(np.exp(mid)), weights, p).factor(B_REF)) > deficit
            lo, hi = (mid, hi) if short else (lo, mid)
        return cls(np.asarray(np.exp(hi)), weights, p)


class ShapeIron(ZooLaw):
    """Finite iron permeability with a random B-dependence: the magnetic gap grows by ``base (1 + growth f(B / B_REF))``.

    ``base = l_fe / (2 mu_i)`` (iron path 60-120 mm, initial permeability 1500-6000: 5-40 µm), and the reluctivity
    rises with the flux density along a random increasing :class:`Shape` ``f`` by 3-15 µm of gap at ``B_REF``
    (Schweitzer & Maslen 2009, sec. 4.2, eq. 4.8, p. 83).
    """

    base: jnp.ndarray
    growth: jnp.ndarray
    shape: Shape
    name: ClassVar[str] = "zoo_iron_shape"
    family: ClassVar[str] = "iron_reluctance"

    def extra_gap(self, b):
        return self.base * (1.0 + self.growth * self.shape(b / B_REF))

    def gap(self, ctx):
        def extra(i, g):
            return self.extra_gap(ctx.bearing.flux_density(i, g))

        return _set(ctx, g_top=ctx.g_top + extra(ctx.i_top, ctx.g_top),
                    g_bottom=ctx.g_bottom + extra(ctx.i_bottom, ctx.g_bottom))

    @classmethod
    def _draw(cls, rng, duration_s):
        while True:
            base = rng.uniform(0.06, 0.12) / (2.0 * rng.uniform(1500.0, 6000.0))
            law = cls(np.asarray(base), np.asarray(log_uniform(rng, 3e-6, 15e-6) / base),
                      random_shape(rng, kinds=("power", "step", "knee"), power=(2.0, 8.0), centre=(0.5, 1.6),
                                   width=(0.05, 0.4)))
            g = PAPER_BEARING.nominal_gap
            if _rises(lambda i: (i / (g + law.extra_gap(_b(i)))) ** 2):
                return law


class FroehlichIron(ZooLaw):
    """Finite iron permeability after a Froehlich-Kennelly B-H curve: ``mu(B) = mu_i (1 - (B / b_s)^q)``.

    The extra gap ``l_fe / (2 mu(B)) = base / (1 - (B / b_s)^q)`` (floored at 5 % of ``mu_i``) grows without
    bound towards ``b_s``; ``q`` = 1-3, and ``b_s`` is set so that it has grown by 3-15 µm at ``B_REF`` (Froehlich
    1881, Kennelly 1891; Bozorth, *Ferromagnetism*, 1951, ch. 2).
    """

    base: jnp.ndarray
    b_s: jnp.ndarray
    q: jnp.ndarray
    name: ClassVar[str] = "zoo_iron_froehlich"
    family: ClassVar[str] = "iron_reluctance"

    def extra_gap(self, b):
        xp = numerics(b)
        return self.base / xp.maximum(1.0 - (xp.abs(b) / self.b_s) ** self.q, 0.05)

    gap = ShapeIron.gap

    @classmethod
    def _draw(cls, rng, duration_s):
        while True:
            base = rng.uniform(0.06, 0.12) / (2.0 * rng.uniform(1500.0, 6000.0))
            r, q = log_uniform(rng, 3e-6, 15e-6) / base, rng.uniform(1.0, 3.0)
            law = cls(np.asarray(base), np.asarray(B_REF * ((1.0 + r) / r) ** (1.0 / q)), np.asarray(q))
            g = PAPER_BEARING.nominal_gap
            if _rises(lambda i: (i / (g + law.extra_gap(_b(i)))) ** 2):
                return law


class ShapeFringing(ZooLaw):
    """Fringing as a random gap-dependent area factor: each pole's force constant times ``1 + amount f(g / g_n)``.

    ``f`` is a random increasing :class:`Shape` of the pole gap over the bearing's nominal gap ``g_n`` (powers
    ``u^0.5``-``u^3``, steps, ramps, settling curves), and ``amount`` sets the area's elasticity ``d ln A / d ln g``
    at ``g_n`` to 0.08-0.35, as the library's fringing coefficients 0.3-1.0 give on the paper's poles (Roters,
    *Electromagnetic Devices*, 1941, ch. 5).
    """

    amount: jnp.ndarray
    shape: Shape
    name: ClassVar[str] = "zoo_fringing_shape"
    family: ClassVar[str] = "fringing"

    def area(self, g, bearing):
        return 1.0 + self.amount * self.shape(g / bearing.nominal_gap)

    def coil(self, ctx):
        return _set(ctx, k_top=ctx.k_top * self.area(ctx.g_top, ctx.bearing),
                    k_bottom=ctx.k_bottom * self.area(ctx.g_bottom, ctx.bearing))

    @classmethod
    def _draw(cls, rng, duration_s):
        while True:
            shape = random_shape(rng, power=(0.5, 3.0), centre=(0.5, 1.5), width=(0.1, 0.5), tau=(0.2, 2.0))
            elasticity, slope = rng.uniform(0.08, 0.35), float(shape.slope(1.0))
            if slope > 1.2 * elasticity:
                return cls(np.asarray(elasticity / (slope - elasticity)), shape)


class RotersFringing(ZooLaw):
    """Fringing after Roters: each pole side widens the face by ``c (g / pi) ln(1 + pi d / g)``.

    The area factor is ``(1 + 2 c_w F(g, d_w) / w) (1 + 2 c_l F(g, d_l) / l)`` with the pole face's width ``w``
    and length ``l`` from the bearing description, fringe depths ``d`` of 0.5-5 mm (about the slot opening)
    and factors ``c`` of 0.5-1.5 drawn for each side independently (Roters, *Electromagnetic Devices*, Wiley
    1941, ch. 5, the flux tube beside a pole side).
    """

    depth: jnp.ndarray
    c: jnp.ndarray
    name: ClassVar[str] = "zoo_fringing_roters"
    family: ClassVar[str] = "fringing"

    def area(self, g, bearing):
        def widen(d, c):
            return c * g / jnp.pi * jnp.log1p(jnp.pi * d / g)

        return ((1.0 + 2.0 * widen(self.depth[0], self.c[0]) / bearing.pole_width)
                * (1.0 + 2.0 * widen(self.depth[1], self.c[1]) / bearing.pole_length))

    coil = ShapeFringing.coil

    @classmethod
    def _draw(cls, rng, duration_s):
        return cls(np.asarray(log_uniform(rng, 0.5e-3, 5e-3, 2)), np.asarray(rng.uniform(0.5, 1.5, 2)))


class CurrentLeakage(ZooLaw):
    """Leakage that grows with the coil current: the gap flux is ``1 - sigma0 - rise f(|i| / I_REF)`` of the ideal.

    The slot leakage of a pole pair carries the coil's whole MMF while the gap flux is limited by the iron, so
    its share rises with the current; ``f`` is a random increasing :class:`Shape`, ``sigma0`` 3-15 %, ``rise``
    1-4.5 % at ``I_REF`` (Schweitzer & Maslen 2009, sec. 4.2.3, p. 87; Meeker, Maslen & Noh 1996).
    """

    sigma0: jnp.ndarray
    rise: jnp.ndarray
    shape: Shape
    name: ClassVar[str] = "zoo_leakage_current"
    family: ClassVar[str] = "leakage"

    def factor(self, i):
        return (1.0 - self.sigma0 - self.rise * self.shape(i / I_REF)) ** 2

    def coil(self, ctx):
        return _set(ctx, k_top=ctx.k_top * self.factor(ctx.i_top), k_bottom=ctx.k_bottom * self.factor(ctx.i_bottom))

    @classmethod
    def _draw(cls, rng, duration_s):
        while True:
            law = cls(np.asarray(rng.uniform(0.03, 0.15)), np.asarray(log_uniform(rng, 0.01, 0.045)),
                      random_shape(rng, kinds=("power", "step", "knee"), power=(1.0, 3.0), centre=(0.3, 1.2),
                                   width=(0.05, 0.4)))
            if _rises(lambda i: i**2 * law.factor(i)):
                return law


class SlotLeakage(ZooLaw):
    """Leakage as a permeance in parallel with the gap: the gap's share of the flux is ``1 / (1 + lam g / g_n)``.

    The gap permeance falls as ``1 / g`` while the slot's does not, so leakage grows with the gap; through the
    pole bodies' saturation it also grows with the current: ``lam = lam0 (1 + rise f(|i| / I_REF))`` with a
    random increasing :class:`Shape` ``f``.  ``lam0`` 0.05-0.25 (5-20 % leakage), the current raising the leakage
    by 1-4 points at ``I_REF`` (Schweitzer & Maslen 2009, sec. 4.2.3, p. 87).
    """

    lam0: jnp.ndarray
    rise: jnp.ndarray
    shape: Shape
    name: ClassVar[str] = "zoo_leakage_slot"
    family: ClassVar[str] = "leakage"

    def factor(self, i, g, bearing):
        lam = self.lam0 * (1.0 + self.rise * self.shape(i / I_REF))
        return (1.0 + lam * g / bearing.nominal_gap) ** -2

    def coil(self, ctx):
        return _set(ctx, k_top=ctx.k_top * self.factor(ctx.i_top, ctx.g_top, ctx.bearing),
                    k_bottom=ctx.k_bottom * self.factor(ctx.i_bottom, ctx.g_bottom, ctx.bearing))

    @classmethod
    def _draw(cls, rng, duration_s):
        while True:
            lam0 = rng.uniform(0.05, 0.25)
            sigma1 = lam0 / (1.0 + lam0) + log_uniform(rng, 0.01, 0.04)
            law = cls(np.asarray(lam0), np.asarray(sigma1 / (1.0 - sigma1) / lam0 - 1.0),
                      random_shape(rng, kinds=("power", "step", "knee"), power=(1.0, 3.0), centre=(0.3, 1.2),
                                   width=(0.05, 0.4)))
            if _rises(lambda i: i**2 * law.factor(i, PAPER_BEARING.nominal_gap, PAPER_BEARING)):
                return law


def _polynomial(rng, magnitudes, chances):
    """Per-axis coefficients array[2, 3] of a random polynomial: each term present with its chance, at least one."""
    while True:
        present = rng.random((2, 3)) < np.asarray(chances)
        if present.any(axis=1).all():
            lo_hi = np.asarray(magnitudes)
            return present * signed(rng, lo_hi[:, 0], lo_hi[:, 1], (2, 3))


class PositionCoupling(ZooLaw):
    """Cross-coupling through the other axis' displacement as a random polynomial, scaled with the bias.

    ``F += (b / 1.3 A)^n sum_j coef_j (y' / Y_REF)^j`` for ``j`` = 1-3, with ``y' = y0 + y`` the other axis'
    displacement from the bearing centre, ``b`` the mean of this axis' coil currents and ``n`` 0, 1 or 2 (shared
    back iron carries this axis' bias flux).  The linear term is 0.06-0.2 N at ``Y_REF`` (1200-4000 N/m, about
    the library's ``kappa``), the others 0.02-0.08 N; each axis draws its own (Schweitzer & Maslen 2009, sec. 4.4).
    """

    coef: jnp.ndarray
    power: jnp.ndarray
    name: ClassVar[str] = "zoo_coupling_position"
    family: ClassVar[str] = "cross_coupling"

    def force(self, ctx, force):
        u = (ctx.y0 + ctx.y) / Y_REF
        c = self.coef[ctx.axis]
        poly = c[..., 0] * u + c[..., 1] * u**2 + c[..., 2] * u**3
        return force + (0.5 * (ctx.i_top + ctx.i_bottom) / 1.3) ** _ax(self.power, ctx.axis) * poly

    @classmethod
    def _draw(cls, rng, duration_s):
        coef = _polynomial(rng, [(0.06, 0.2), (0.02, 0.08), (0.02, 0.08)], (0.85, 0.4, 0.35))
        return cls(np.asarray(coef), np.asarray(rng.choice([0.0, 1.0, 2.0], 2)))


class CurrentsCoupling(ZooLaw):
    """Cross-coupling through the other axis' control current as a random polynomial.

    ``F += coef_1 c' + coef_2 c' |c'| / 1 A + coef_3 c' c / 1 A`` with ``c'`` the other axis' control current
    ``(i_top' - i_bottom') / 2`` read at the same moment, ``c`` this axis' own: flux of the other horseshoe closing
    through this axis' poles (Meeker, Maslen & Noh 1996).  ``coef_1`` 0.3-1.2 N/A (1-4 % of the force-current
    gain), the others 0.2-0.8 N/A^2; rows without the other axis' currents get none.
    """

    coef: jnp.ndarray
    name: ClassVar[str] = "zoo_coupling_currents"
    family: ClassVar[str] = "cross_coupling"
    needs_other_axis: ClassVar[bool] = True

    def force(self, ctx, force):
        co = _known(0.5 * (ctx.i_top_other - ctx.i_bottom_other))
        c = self.coef[ctx.axis]
        return force + c[..., 0] * co + c[..., 1] * co * jnp.abs(co) + c[..., 2] * co * 0.5 * (ctx.i_top - ctx.i_bottom)

    @classmethod
    def _draw(cls, rng, duration_s):
        return cls(np.asarray(_polynomial(rng, [(0.3, 1.2), (0.2, 0.8), (0.2, 0.8)], (0.85, 0.4, 0.35))))


MAGNETIC: dict[str, tuple[type[ZooLaw], ...]] = {
    "saturation": (KneeSaturation, CurveSaturation),
    "iron_reluctance": (ShapeIron, FroehlichIron),
    "fringing": (ShapeFringing, RotersFringing),
    "leakage": (CurrentLeakage, SlotLeakage),
    "cross_coupling": (PositionCoupling, CurrentsCoupling),
}
"""The zoo's law classes of the iron and the gaps by contract family."""
