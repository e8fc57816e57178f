"""A nonlinear magnetic equivalent circuit (MEC) of the 8-pole heteropolar bearing, solved per reading.

The ideal law (:func:`ambfit.physics.model.ideal_force`) treats each horseshoe as two air gaps in
series driven by ``2 N i`` with ideal iron and nothing else.  This module keeps the whole stator and
rotor instead, so that one small set of parameters a designer recognises explains together what the
effect classes of :mod:`ambfit.physics.effects` patch one by one:

* **iron** (finite permeability *and* saturation as one physics): every iron branch obeys the
  lamination's B-H curve (:attr:`Bearing.b_curve`, :attr:`Bearing.h_curve`, interpolated by a
  monotone cubic), so its magnetic drop is ``l H(Φ / A)``;
* **fringing**: each pole's gap permeance has, besides the face term ``MU_0 w l / g``, the Roters
  side-fringe ("half annulus", pole face to a plane) of every pole side of length ``l``,
  ``(2 MU_0 l / π) ln(1 + t / g)`` with ``t`` the fringe depth; being gap dependent, it carries
  force (Roters, *Electromagnetic Devices*, Wiley 1941, ch. 5; Schweitzer & Maslen 2009, p. 84);
* **leakage**: a slot-leakage permeance ``MU_0 l λ`` between neighbouring poles, attached at a
  chosen height of the pole (the tips, or part-way down where it sees part of the coil MMF)
  (Meeker, Maslen & Noh, "An augmented circuit model for magnetic bearings including eddy
  currents, fringing, and leakage", IEEE Trans. Magn. 32(4), 1996);
* **coupling between horseshoes and axes**: the four horseshoes share the back-iron ring and the
  rotor, so when the rotor moves the flux redistributes over all eight poles.  The poles of the
  other axis' horseshoes sit 22.5° off this axis (at 67.5°), and with the polarity (``NNSS`` or
  ``NSNS``) this sets how strongly the axes talk.  A link coefficient ``κ`` scales the yoke links
  between neighbouring horseshoes: 1 for a solid laminated ring, 0 for isolated horseshoes.

Circuit (nodal analysis with the iron fluxes as extra unknowns, "modified nodal analysis", so
both infinite iron permeability, ``H ≡ 0``, and isolated horseshoes, ``κ = 0``, stay regular)::

      Y_k ──[yoke k: l_y H(Φ/A_y)]── Y_k+1          stator yoke ring, node Y_k at the root of pole k
       │
    [pole k: MMF ±N i, l_p H(Φ/A_p)]                coil MMF and pole iron in series
       │
      M_k ──[leak: MU_0 l λ]── M_k+1                leakage point (height h of the pole: a share
       │                                            h of the MMF and iron below it, 1 - h above)
      T_k                                           pole tip
       │
    [gap k: P(g_k), Roters fringing]
       │
      R_k ──[rotor k: l_r H(Φ/A_r)]── R_k+1         rotor ring (R_0 is the potential reference)

Pole ``k`` (k = 0..7) sits at ``θ_k = α + k·45°`` from +v towards +w (α = 22.5°); the horseshoes are
v top = poles (7, 0) at ∓α, w top = (1, 2), v bottom = (3, 4), w bottom = (5, 6).  The rotor's
physical displacement ``(dv, dw)`` from the geometric centre sets each gap,
``g_k = g - dv cos θ_k - dw sin θ_k``.  The force follows from the co-energy at constant coil
currents: only the gap permeances depend on the rotor position, so the rotor is pulled towards
pole ``k`` by ``f_k = ½ U_k² |dP/dg|(g_k)`` (``U_k`` the magnetic drop across gap ``k``) and
``F_v = Σ f_k cos θ_k``, ``F_w = Σ f_k sin θ_k`` (Schweitzer & Maslen (eds.), *Magnetic Bearings*,
Springer 2009, ch. 3-4, eq. 3.23 and sec. 4.2).  With ideal iron, no fringing, no leakage and
``κ = 0`` this is exactly Eq. 3 with ``k = 0.25 MU_0 A (2N)² cos α`` (lamination 1), the law the
rest of ambfit fits.

The circuit is solved by Newton's method (at most :data:`MAX_NEWTON` steps, stopping at a
relative step of 1e-13; a reading whose solve is still moving by more than :data:`NEWTON_FAILED` after
:data:`MAX_NEWTON` steps gets a NaN force, so that a fit names its rows instead of using a wrong number); derivatives with respect to the parameters and inputs come from one
extra Newton step whose Jacobian is held constant (the implicit-function theorem), so
:func:`mec_forces` is jit-able, vmap-able and differentiable in float64.  Newton runs on 17 loop
fluxes (the flux law solved in advance, see ``_loop_system``) with a hand-written Jacobian; it takes
the same steps as on the 64 nodal unknowns above, whose residual it reports.

Units: SI throughout (m, A, Wb, T, N).
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ambfit.physics.bearing import MU_0, PAPER_BEARING, Bearing

__all__ = [
    "MECParams", "MECSolution", "mec_solve", "mec_forces", "mec_axis_force", "bh_curve", "MAX_NEWTON", "NEWTON_FAILED",
    "POLE_SPLIT", "YOKE_SPLIT", "ROTOR_SPLIT", "DEFAULT_MU_R",
]

MAX_NEWTON = 40
"""Upper bound on the Newton steps of one circuit solve (typically 5-8 are used)."""

NEWTON_FAILED = 1e-8
"""A solve whose last Newton step still moved the fluxes by more than this (relative) after :data:`MAX_NEWTON`
steps did not converge: its force is NaN.  (Round-off can keep a converged solve from the 1e-13 stopping
step; it does not leave it moving by 1e-8.)"""

POLE_SPLIT, YOKE_SPLIT, ROTOR_SPLIT = 0.25, 0.35, 0.15
"""How the mean iron path ``l_fe`` of one horseshoe circuit is shared: each of its two poles
``0.25 l_fe``, the yoke arc between them ``0.35 l_fe``, the rotor arc ``0.15 l_fe`` (a 45° arc at
the mean yoke radius of a 35 mm bore stator is about twice the rotor's).  Every yoke and rotor
segment (poles are equally spaced) gets the same length."""

MU_R_MAX = 1e12
"""Ceiling on the iron's relative permeability: keeps the circulating flux of a ring of ideal iron
(``iron_h_scale = 0``) determined; changes forces by ~1e-10 relative."""

DEFAULT_MU_R = 4000.0
"""Relative permeability used when the bearing gives no B-H curve (unsaturated silicon iron)."""

_N_POLES = 8
_INTRA = np.array([False, True, False, True, False, True, False, True])
"""Yoke segment k joins poles k and k+1; True where both belong to one horseshoe (7-0, 1-2, 3-4, 5-6)."""
_COIL = np.array([0, 2, 2, 1, 1, 3, 3, 0])
"""Coil of pole k in the order (v top, v bottom, w top, w bottom)."""
_POLARITY = {"NNSS": np.array([1, 1, -1, -1, 1, 1, -1, -1], dtype=float),
             "NSNS": np.array([1, -1, 1, -1, 1, -1, 1, -1], dtype=float)}
"""Sign of each pole's MMF (+1: N, flux from the stator into the gap), poles 0..7 from +α."""


# --- the lamination's B-H curve -----------------------------------------------------------------------------

def _pchip_slopes(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Fritsch-Carlson slopes of the monotone cubic through ``(x, y)``."""
    h = np.diff(x)
    delta = np.diff(y) / h
    d = np.zeros_like(y)
    for j in range(1, len(x) - 1):
        if delta[j - 1] * delta[j] > 0:
            w1, w2 = 2 * h[j] + h[j - 1], h[j] + 2 * h[j - 1]
            d[j] = (w1 + w2) / (w1 / delta[j - 1] + w2 / delta[j])
    d[0] = delta[0]
    d[-1] = delta[-1]
    return d


class _BH(eqx.Module):
    """``H(B)`` [A/m] of the lamination: monotone cubic through the datasheet, odd in B, linear beyond."""

    b: tuple = eqx.field(static=True)
    h: tuple = eqx.field(static=True)
    d: tuple = eqx.field(static=True)

    def __call__(self, b):
        s = jnp.where(b < 0, -1.0, 1.0)                  # odd extension with the right slope at B = 0
        b_abs = s * b
        bk, hk, dk = (np.array(a) for a in (self.b, self.h, self.d))
        # One gather of the interval's ends (b, H, H') instead of six; the interval by comparison
        # with every knot (the table is short: cheaper to compile and run than a binary search).
        table = jnp.asarray(np.stack([bk[:-1], bk[1:], hk[:-1], hk[1:], dk[:-1], dk[1:]], axis=1))
        j = jnp.clip(jnp.sum(jnp.asarray(bk) <= b_abs[..., None], axis=-1) - 1, 0, len(self.b) - 2)
        row = table[j]
        x0, x1, y0, y1, d0, d1 = (row[..., c] for c in range(6))
        hh = x1 - x0
        t = jnp.clip((b_abs - x0) / hh, 0.0, 1.0)
        h00, h10 = 2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t
        h01, h11 = -2 * t**3 + 3 * t**2, t**3 - t**2
        inside = h00 * y0 + h10 * hh * d0 + h01 * y1 + h11 * hh * d1
        beyond = hk[-1] + dk[-1] * (b_abs - bk[-1])
        return s * jnp.where(b_abs > bk[-1], beyond, inside)


def _iron_h(p, bh: _BH, b):
    """``H(B)`` with ``p.saturation`` blending the curve (1) with its initial slope (0)."""
    return p.saturation * bh(b) + (1.0 - p.saturation) * b * bh.d[0]


@functools.lru_cache(maxsize=32)
def bh_curve(bearing: Bearing) -> _BH:
    """The bearing's ``H(B)`` (monotone cubic through its B-H table; linear ``DEFAULT_MU_R`` without one).

    Examples
    --------
    >>> h = bh_curve(PAPER_BEARING)            # no table: linear iron
    >>> round(float(h(1.0)) * MU_0 * DEFAULT_MU_R, 12)
    1.0
    """
    if len(bearing.b_curve) >= 2:
        b, h = np.asarray(bearing.b_curve, float), np.asarray(bearing.h_curve, float)
    else:
        b = np.array([0.0, 2.0])
        h = b / (MU_0 * DEFAULT_MU_R)
    return _BH(b=tuple(b.tolist()), h=tuple(h.tolist()), d=tuple(_pchip_slopes(b, h).tolist()))


# --- parameters --------------------------------------------------------------------------------------------

class MECParams(eqx.Module):
    """Physical parameters of the circuit (SI units, scalars; every one a designer can estimate).

    Parameters
    ----------
    gap : float [m]
        Radial air gap with the rotor at the geometric centre (the drawing's ``nominal_gap``).
    fringe_depth : float [m]
        Roters side-fringe depth ``t``: flux leaves each pole side over a depth ``t`` and crosses
        to the rotor on quarter circles, ``P_side = (2 MU_0 l / π) ln(1 + t / g)`` per side of
        length ``l``.  About half the slot opening or the pole-shoe height (1-5 mm); 0: no fringing.
    fringe_axial : float [-]
        Weight of the fringe at the two axial pole ends (sides of length ``w``): 1 for a real
        bearing, 0 for a 2-D (extruded) field such as a 2-D finite-element model.
    leakage : float [-]
        Slot-leakage shape factor ``λ``: the permeance between neighbouring pole tips is
        ``MU_0 l λ`` (parallel slot walls: ``λ ≈ depth / width`` of the leakage region; 0.2-2).
    iron_h_scale : float [-]
        Multiplies ``H(B)`` of the datasheet curve: 1 the datasheet iron, >1 a worse iron (cutting
        stress, a different grade), 0 ideal iron (infinite permeability, no saturation).
    iron_path : float [m]
        Mean iron path ``l_fe`` of one horseshoe circuit (poles, yoke arc and rotor arc), shared
        as :data:`POLE_SPLIT`, :data:`YOKE_SPLIT`, :data:`ROTOR_SPLIT`.
    iron_area_ratio : float [-]
        Cross-section of the yoke and rotor back iron relative to the pole face area.
    pole_area_ratio : float [-]
        Cross-section of the pole body relative to the pole face (< 1 with pole shoes).
    leakage_height : float [0, 1]
        Where along the pole, from the yoke (0) to the tip (1), the lumped slot leakage attaches:
        the leakage sees that fraction of the coil MMF and the pole iron below it carries the leakage
        flux too.  1 for pole-shoe (tip) leakage; about 2/3 for leakage spread evenly along a coil
        filling the slot.
    lamination : float [-]
        Iron stacking factor: the iron cross-sections are ``lamination`` times the geometric ones
        (the gap faces are not).  1 for a 2-D model; 0.95-0.98 for a real stack.
    link : float [0, 1]
        Magnetic link of the yoke between neighbouring horseshoes: 1 a solid ring, 0 isolated
        horseshoes (the ideal law's assumption); in between, the link carries an extra
        reluctance ``(1 - link) / link`` times that of one gap.
    saturation : float [0, 1]
        1: the iron follows its B-H curve; 0: a constant permeability, the curve's initial slope (what
        the knee of the curve adds is then switched off, finite permeability stays); in between, a blend.

    Examples
    --------
    >>> p = MECParams.drawing(PAPER_BEARING)
    >>> round(float(p.gap) * 1e6, 1), float(p.link)
    (762.0, 1.0)
    """

    gap: jnp.ndarray
    fringe_depth: jnp.ndarray
    fringe_axial: jnp.ndarray
    leakage: jnp.ndarray
    iron_h_scale: jnp.ndarray
    iron_path: jnp.ndarray
    iron_area_ratio: jnp.ndarray
    pole_area_ratio: jnp.ndarray
    leakage_height: jnp.ndarray
    lamination: jnp.ndarray
    link: jnp.ndarray
    saturation: jnp.ndarray

    @classmethod
    def drawing(cls, bearing: Bearing = PAPER_BEARING, **overrides) -> MECParams:
        """Parameters as the drawing suggests: drawn gap and iron path, datasheet iron, solid ring.

        Fringe depth: half the slot opening at the bore, capped at 3 mm; leakage ``λ`` = 0.5.
        """
        pitch = math.pi * bearing.bore_diameter / _N_POLES
        values = {
            "gap": bearing.nominal_gap,
            "fringe_depth": min(max(pitch - bearing.pole_width, 0.0) / 2.0, 3e-3),
            "fringe_axial": 1.0, "leakage": 0.5, "iron_h_scale": 1.0, "iron_path": bearing.iron_path,
            "iron_area_ratio": 1.0, "pole_area_ratio": 1.0, "leakage_height": 1.0, "lamination": 1.0,
            "link": 1.0, "saturation": 1.0,
        }
        values.update(overrides)
        return cls(**{k: jnp.asarray(v, dtype=float) for k, v in values.items()})

    @classmethod
    def ideal(cls, bearing: Bearing = PAPER_BEARING, **overrides) -> MECParams:
        """The ideal law's assumptions: ideal iron, no fringing, no leakage, isolated horseshoes."""
        values = {"fringe_depth": 0.0, "leakage": 0.0, "iron_h_scale": 0.0, "link": 0.0}
        values.update(overrides)
        return cls.drawing(bearing, **values)

    def replace(self, **changes) -> MECParams:
        """A copy with some parameters changed."""
        names = tuple(changes)
        return eqx.tree_at(lambda p: tuple(getattr(p, n) for n in names), self,
                           tuple(jnp.asarray(v, dtype=float) for v in changes.values()))


class MECSolution(eqx.Module):
    """One solved reading (arrays over the eight poles, pole ``k`` at ``α + k·45°`` from +v).

    ``force`` is ``(F_v, F_w)`` [N] on the rotor; ``pole_force`` the pull towards each pole [N];
    ``gaps`` [m]; ``gap_flux`` [Wb] (face plus fringe); ``b_gap`` the face flux density
    ``MU_0 U / g`` [T]; ``b_pole`` the flux density in each pole's iron between the yoke and the
    leakage point (the most loaded part), ``b_tip`` between the leakage point and the tip [T]; ``b_yoke``,
    ``b_rotor`` in the segments joining pole k and k+1 [T]; ``mmf_gap`` the drop across each gap [A];
    ``residual`` the largest scaled circuit residual after the solve, ``iterations`` the Newton steps.
    """

    force: jnp.ndarray
    pole_force: jnp.ndarray
    gaps: jnp.ndarray
    gap_flux: jnp.ndarray
    b_gap: jnp.ndarray
    b_pole: jnp.ndarray
    b_tip: jnp.ndarray
    b_yoke: jnp.ndarray
    b_rotor: jnp.ndarray
    mmf_gap: jnp.ndarray
    residual: jnp.ndarray
    iterations: jnp.ndarray


# --- the circuit -------------------------------------------------------------------------------------------

def _geometry(bearing: Bearing):
    theta = bearing.pole_angle + np.arange(_N_POLES) * (2 * np.pi / _N_POLES)
    return np.cos(theta), np.sin(theta), _POLARITY[bearing.polarity]


def _gap_permeance(p: MECParams, bearing: Bearing, g):
    """``P(g)`` [H] and ``-dP/dg`` [H/m] of one pole gap: face plus Roters side fringing."""
    w, l = bearing.pole_width, bearing.pole_length
    sides = 2.0 * l + 2.0 * p.fringe_axial * w          # fringing edge length around the face
    t = p.fringe_depth
    perm = MU_0 * (w * l / g + sides * (2.0 / jnp.pi) * jnp.log1p(t / g))
    pull = MU_0 * (w * l / g**2 + sides * (2.0 / jnp.pi) * t / (g * (g + t)))
    return perm, pull


def _scales(bearing: Bearing):
    """Reference magnetic potential [A], permeance [H] and flux [Wb] that make the unknowns O(1)."""
    u_ref = bearing.turns_per_pole * 1.0                 # 1 A through one pole coil
    p_ref = MU_0 * bearing.pole_area / bearing.nominal_gap   # one gap's permeance
    return u_ref, p_ref, u_ref * p_ref


def _unpack(z, bearing: Bearing):
    """Scaled unknowns -> (U_Y, U_M, U_T, U_R) [A] and (Φ_root, Φ_tip, Φ_rotor, Φ_yoke) [Wb], 8 each."""
    n = _N_POLES
    u_ref, _, f_ref = _scales(bearing)
    parts = [z[j * n:(j + 1) * n] for j in range(8)]
    return [a * u_ref for a in parts[:4]], [a * f_ref for a in parts[4:]]


def _residual(z, p: MECParams, bearing: Bearing, currents, gaps):
    """Scaled Kirchhoff and branch equations of the circuit.

    Nodes per pole: yoke ``Y``, leakage point ``M`` (at ``leakage_height`` of the pole, where the
    slot leakage attaches), tip ``T``, rotor ``R``.  Unknowns ``z`` (scaled): potentials
    ``U_Y, U_M, U_T, U_R`` and iron fluxes ``Φ_root`` (Y -> M), ``Φ_tip`` (M -> T), ``Φ_rotor``
    (R_k -> R_k+1), ``Φ_yoke`` (Y_k -> Y_k+1).
    """
    _, _, sign = _geometry(bearing)
    u_ref, p_ref, f_ref = _scales(bearing)
    bh = bh_curve(bearing)
    (uy, um, ut, ur), (f_root, f_tip, fr, fy) = _unpack(z, bearing)

    area = bearing.pole_area * p.lamination
    a_pole, a_back = area * p.pole_area_ratio, area * p.iron_area_ratio
    a_h = p.leakage_height
    l_pole, l_yoke, l_rotor = POLE_SPLIT * p.iron_path, YOKE_SPLIT * p.iron_path, ROTOR_SPLIT * p.iron_path

    def drop(length, b):                                 # l H(B); iron never better than MU_R_MAX
        return length * (p.iron_h_scale * _iron_h(p, bh, b) + b / (MU_0 * MU_R_MAX))

    perm, _ = _gap_permeance(p, bearing, gaps)
    fg = perm * (ut - ur)                                # gap flux, tip -> rotor
    p_leak = MU_0 * bearing.pole_length * p.leakage
    fl = p_leak * (um - jnp.roll(um, -1))                # leakage M_k -> M_k+1
    mmf = jnp.asarray(sign) * bearing.turns_per_pole * currents[jnp.asarray(_COIL)]

    kcl_y = f_root + fy - jnp.roll(fy, 1)
    kcl_m = -f_root + f_tip + fl - jnp.roll(fl, 1)
    kcl_t = -f_tip + fg
    kcl_r = -fg + fr - jnp.roll(fr, 1)
    kcl_r = kcl_r.at[0].set(ur[0] * p_ref)               # reference potential R_0 = 0
    br_root = um - uy - a_h * mmf + drop(a_h * l_pole, f_root / a_pole)
    br_tip = ut - um - (1.0 - a_h) * mmf + drop((1.0 - a_h) * l_pole, f_tip / a_pole)
    br_rotor = ur - jnp.roll(ur, -1) - drop(l_rotor, fr / a_back)
    kappa = jnp.where(jnp.asarray(_INTRA), 1.0, p.link)
    br_yoke = kappa * (uy - jnp.roll(uy, -1) - drop(l_yoke, fy / a_back)) - (1.0 - kappa) * fy / p_ref
    return jnp.concatenate([kcl_y / f_ref, kcl_m / f_ref, kcl_t / f_ref, kcl_r / f_ref,
                            br_root / u_ref, br_tip / u_ref, br_rotor / u_ref, br_yoke / u_ref])


# --- the solver: Newton on the loop fluxes ---------------------------------------------------------------
#
# Kirchhoff's flux law is linear, so it is solved once and for all: every branch flux of the MNA
# unknowns above is a fixed linear map of 17 "loop" fluxes x = (a, c, d),
#
#   Φ_yoke = a,  Φ_root,k = a_k-1 - a_k,  Φ_leak,k = c_k,  Φ_tip,k = Φ_gap,k = Φ_root,k - c_k + c_k-1,
#   Φ_rotor,k = d + Σ_j≤k Φ_gap,j,
#
# and only the magnetic-potential law around 17 independent loops remains (8 slot-leakage loops,
# 8 yoke loops, the rotor ring), each drop ``l H(Φ/A)`` or ``Φ/P`` explicit in the fluxes.  The
# slot-leakage loop is written as ``Φ_leak - P_leak · (drop along the pole tips and rotor)`` and the
# yoke loop multiplied by the link ``κ``, so that no leakage (``λ = 0``) and isolated horseshoes
# (``κ = 0``) stay regular exactly as in the nodal form.  The potentials follow from the fluxes
# by summing drops (R_0 = 0).  Newton's method on this system takes the same steps as on the nodal
# form (the eliminated unknowns enter linearly) with a 17x17 instead of a 64x64 matrix, and its
# Jacobian is written out (the iron's ``l H'(B) / A`` on the flux maps) instead of traced.

_NX = 2 * _N_POLES + 1


def _flux_maps():
    """Constant matrices ``(8, 17)``: loop fluxes -> Φ_root, Φ_gap (= Φ_tip), Φ_rotor, Φ_yoke, Φ_leak."""
    n = _N_POLES
    eye, zero = np.eye(n), np.zeros((n, n))
    prev = np.roll(eye, 1, axis=0)                      # (prev @ v)_k = v_k-1
    col0 = np.zeros((n, 1))
    root = np.hstack([prev - eye, zero, col0])
    gap = np.hstack([prev - eye, prev - eye, col0])
    rotor = np.tril(np.ones((n, n))) @ gap + np.hstack([zero, zero, np.ones((n, 1))])
    yoke = np.hstack([eye, zero, col0])
    leak = np.hstack([zero, eye, col0])
    return root, gap, rotor, yoke, leak


_S_ROOT, _S_GAP, _S_ROTOR, _S_YOKE, _S_LEAK = _flux_maps()


def _loop_system(x, p: MECParams, bearing: Bearing, currents, gaps, with_jacobian: bool):
    """Scaled loop equations ``r(x)`` (17) of the scaled loop fluxes ``x`` (and ``dr/dx``, 17x17).

    Also returns the branch fluxes [Wb] ``(Φ_root, Φ_gap, Φ_rotor, Φ_yoke)`` and the pole
    potentials relative to the rotor node, ``(U_M - U_R, U_Y - U_R)`` [A].
    """
    _, _, sign = _geometry(bearing)
    u_ref, p_ref, f_ref = _scales(bearing)
    bh = bh_curve(bearing)
    area = bearing.pole_area * p.lamination
    a_pole, a_back = area * p.pole_area_ratio, area * p.iron_area_ratio
    a_h = p.leakage_height
    l_pole, l_yoke, l_rotor = POLE_SPLIT * p.iron_path, YOKE_SPLIT * p.iron_path, ROTOR_SPLIT * p.iron_path
    mu_max = 1.0 / (MU_0 * MU_R_MAX)

    f_root = jnp.asarray(_S_ROOT) @ x * f_ref
    fg = jnp.asarray(_S_GAP) @ x * f_ref
    fr = jnp.asarray(_S_ROTOR) @ x * f_ref
    fy = x[:_N_POLES] * f_ref
    fl = x[_N_POLES:2 * _N_POLES] * f_ref

    def drop(length, a, flux):                          # l H(Φ/A) [A] and its slope d/dΦ [A/Wb]
        b = flux / a
        if with_jacobian:
            h, dh = jax.jvp(lambda bb: _iron_h(p, bh, bb), (b,), (jnp.ones_like(b),))
            return length * (p.iron_h_scale * h + b * mu_max), length * (p.iron_h_scale * dh + mu_max) / a
        return length * (p.iron_h_scale * _iron_h(p, bh, b) + b * mu_max), None

    perm, _ = _gap_permeance(p, bearing, gaps)
    mmf = jnp.asarray(sign) * bearing.turns_per_pole * currents[jnp.asarray(_COIL)]
    d_root, s_root = drop(a_h * l_pole, a_pole, f_root)
    d_tip, s_tip = drop((1.0 - a_h) * l_pole, a_pole, fg)
    d_rot, s_rot = drop(l_rotor, a_back, fr)
    d_yoke, s_yoke = drop(l_yoke, a_back, fy)
    u_mr = d_tip - (1.0 - a_h) * mmf + fg / perm        # U_M - U_R of each pole
    u_yr = u_mr + d_root - a_h * mmf                    # U_Y - U_R
    v = u_mr - jnp.roll(u_mr, -1) + d_rot               # U_M,k - U_M,k+1 along tips, gaps and rotor
    w = u_yr - jnp.roll(u_yr, -1) + d_rot               # U_Y,k - U_Y,k+1 along the poles
    p_leak = MU_0 * bearing.pole_length * p.leakage
    kappa = jnp.where(jnp.asarray(_INTRA), 1.0, p.link)
    # The rotor-ring row is scaled by the rotor iron's slope at zero flux (ideal iron: ~1e-11 of the others).
    slope0 = jax.jvp(bh, (jnp.zeros(()),), (jnp.ones(()),))[1]
    ring_scale = jax.lax.stop_gradient(a_back / (l_rotor * (p.iron_h_scale * slope0 + mu_max) * f_ref))
    r = jnp.concatenate([(fl - p_leak * v) / f_ref,
                         (kappa * (w - d_yoke) - (1.0 - kappa) * fy / p_ref) / u_ref,
                         (jnp.sum(d_rot) * ring_scale)[None]])
    out = (f_root, fg, fr, fy), (u_mr, u_yr)
    if not with_jacobian:
        return r, None, out
    s_gap = jnp.asarray(_S_GAP) * f_ref
    s_r = (s_rot * f_ref)[:, None] * jnp.asarray(_S_ROTOR)
    du_mr = (s_tip + 1.0 / perm)[:, None] * s_gap
    du_yr = du_mr + (s_root * f_ref)[:, None] * jnp.asarray(_S_ROOT)
    dv = du_mr - jnp.roll(du_mr, -1, axis=0) + s_r
    dw = du_yr - jnp.roll(du_yr, -1, axis=0) + s_r
    jac = jnp.concatenate([jnp.asarray(_S_LEAK) - p_leak / f_ref * dv,
                           (kappa[:, None] * dw - ((kappa * s_yoke + (1.0 - kappa) / p_ref) * f_ref)[:, None]
                            * jnp.asarray(_S_YOKE)) / u_ref,
                           (jnp.sum(s_r, axis=0) * ring_scale)[None]])
    return r, jac, out


def _newton(p, bearing, currents, gaps):
    """Newton's method on the loop fluxes from zero flux; returns ``x``, the steps, the last LU factors and
    whether it converged (see :data:`NEWTON_FAILED`)."""

    def cond(state):
        _, step, res, it, _ = state
        return (step > 1e-13) & (res > 1e-14) & (it < MAX_NEWTON)

    def body(state):
        x, _, _, it, _ = state
        r, jac, _ = _loop_system(x, p, bearing, currents, gaps, with_jacobian=True)
        lu = jax.scipy.linalg.lu_factor(jac)
        dx = jax.scipy.linalg.lu_solve(lu, r)
        scale = jnp.maximum(jnp.max(jnp.abs(x)), 1.0)
        return x - dx, jnp.max(jnp.abs(dx)) / scale, jnp.max(jnp.abs(r)), it + 1, lu

    x0 = jnp.zeros(_NX)
    inf = jnp.asarray(jnp.inf)
    lu0 = (jnp.zeros((_NX, _NX)), jnp.zeros(_NX, dtype=jnp.int32))
    x, step, res, it, lu = jax.lax.while_loop(cond, body, (x0, inf, inf, jnp.asarray(0), lu0))
    return x, it, lu, (step <= NEWTON_FAILED) | (res <= 1e-14)


def _solve_one(p: MECParams, bearing: Bearing, i_vt, i_vb, i_wt, i_wb, dv, dw, full: bool = True):
    cos_t, sin_t, _ = _geometry(bearing)
    currents = jnp.stack([jnp.asarray(c, dtype=float) for c in (i_vt, i_vb, i_wt, i_wb)])
    gaps = p.gap - dv * jnp.asarray(cos_t) - dw * jnp.asarray(sin_t)
    x_star, iterations, lu, converged = _newton(jax.lax.stop_gradient(p), bearing, jax.lax.stop_gradient(currents),
                                     jax.lax.stop_gradient(gaps))
    x_star, lu = jax.lax.stop_gradient((x_star, lu))
    # One more Newton step with the Jacobian held constant (the last step's factors: the iterate moved by
    # < 1e-13 since): same value, implicit-function derivatives.
    res, _, _ = _loop_system(x_star, p, bearing, currents, gaps, with_jacobian=False)
    x = x_star - jax.scipy.linalg.lu_solve(lu, res)
    _, _, ((f_root, fg, fr, fy), (u_mr, u_yr)) = _loop_system(x, p, bearing, currents, gaps, with_jacobian=False)

    perm, pull = _gap_permeance(p, bearing, gaps)
    drop = fg / perm
    pole_force = 0.5 * drop**2 * pull
    force = jnp.stack([jnp.sum(pole_force * jnp.asarray(cos_t)), jnp.sum(pole_force * jnp.asarray(sin_t))])
    force = jnp.where(converged, force, jnp.nan)          # never a wrong number: the caller sees NaN rows
    if not full:
        return force
    # The nodal unknowns, for the nodal residual of the solution (reported as before).
    u_ref, _, f_ref = _scales(bearing)
    bh = bh_curve(bearing)
    a_back = bearing.pole_area * p.lamination * p.iron_area_ratio
    d_rot = ROTOR_SPLIT * p.iron_path * (p.iron_h_scale * _iron_h(p, bh, fr / a_back)
                                          + fr / a_back / (MU_0 * MU_R_MAX))
    ur = jnp.concatenate([jnp.zeros(1), -jnp.cumsum(d_rot[:-1])])
    z = jnp.concatenate([(u_yr + ur) / u_ref, (u_mr + ur) / u_ref, (drop + ur) / u_ref, ur / u_ref,
                         f_root / f_ref, fg / f_ref, fr / f_ref, fy / f_ref])
    res_mna = _residual(jax.lax.stop_gradient(z), jax.lax.stop_gradient(p), bearing,
                        jax.lax.stop_gradient(currents), jax.lax.stop_gradient(gaps))
    area = bearing.pole_area * p.lamination
    return MECSolution(
        force=force, pole_force=pole_force, gaps=gaps, gap_flux=fg, b_gap=MU_0 * drop / gaps,
        b_pole=f_root / (area * p.pole_area_ratio), b_tip=fg / (area * p.pole_area_ratio),
        b_yoke=fy / (area * p.iron_area_ratio), b_rotor=fr / (area * p.iron_area_ratio),
        mmf_gap=drop, residual=jnp.max(jnp.abs(res_mna)), iterations=iterations,
    )


def mec_solve(params: MECParams, bearing: Bearing, i_vt, i_vb, i_wt, i_wb, dv, dw) -> MECSolution:
    """Solve the circuit for every reading (inputs broadcast together; SI units).

    Parameters
    ----------
    params : MECParams
    bearing : Bearing
        Turns, pole face (width and length), pole angle, polarity, B-H curve.
    i_vt, i_vb, i_wt, i_wb : array-like [A]
        Coil currents of the v top, v bottom, w top and w bottom horseshoes (non-negative in normal
        use; a horseshoe's two coils carry one current).
    dv, dw : array-like [m]
        Physical rotor displacement from the geometric centre (sensor reading plus effective
        origin, ``x + x0``, in the contract's convention).

    Returns
    -------
    MECSolution
        Fields with the broadcast shape of the inputs in front (``force[..., 0]`` is ``F_v``).
    """
    args = jnp.broadcast_arrays(*(jnp.asarray(a, dtype=float) for a in (i_vt, i_vb, i_wt, i_wb, dv, dw)))
    shape = args[0].shape
    flat = [a.reshape(-1) for a in args]
    sol = _solve_vmapped(params, bearing, *flat)
    return jax.tree_util.tree_map(lambda a: a.reshape(shape + a.shape[1:]), sol)


@functools.partial(jax.jit, static_argnums=1)
def _solve_vmapped(params, bearing, i_vt, i_vb, i_wt, i_wb, dv, dw):
    return jax.vmap(_solve_one, in_axes=(None, None, 0, 0, 0, 0, 0, 0))(params, bearing, i_vt, i_vb, i_wt,
                                                                       i_wb, dv, dw)


def mec_forces(params: MECParams, bearing: Bearing, i_vt, i_vb, i_wt, i_wb, dv, dw):
    """``(F_v, F_w)`` [N]: the force the bearing applies to the rotor along +v and +w.

    See :func:`mec_solve` for the arguments.  Jit-able, vmap-able and differentiable in every
    argument but ``bearing`` (static).

    Examples
    --------
    >>> b = PAPER_BEARING
    >>> fv, fw = mec_forces(MECParams.ideal(b), b, 2.0, 1.0, 1.5, 1.5, 0.0, 0.0)
    >>> k = b.force_constant(lamination=1.0)
    >>> round(float(fv) / (k * (2.0**2 - 1.0**2) / b.nominal_gap**2), 9), abs(round(float(fw), 9))
    (1.0, 0.0)
    """
    f = mec_solve(params, bearing, i_vt, i_vb, i_wt, i_wb, dv, dw).force
    return f[..., 0], f[..., 1]


def _bearing_frame(axis, i_top, i_bottom, i_top_other, i_bottom_other, x, y, x0, y0):
    """Per-row terms (own axis, other axis) -> the bearing's frame: ``(is_v, (i_vt, i_vb, i_wt, i_wb, dv, dw))``
    with ``dv``, ``dw`` the physical displacement ``x + x0`` from the geometric centre."""
    is_v = jnp.asarray(axis) == 0
    return is_v, (jnp.where(is_v, i_top, i_top_other), jnp.where(is_v, i_bottom, i_bottom_other),
                  jnp.where(is_v, i_top_other, i_top), jnp.where(is_v, i_bottom_other, i_bottom),
                  jnp.where(is_v, x + x0, y + y0), jnp.where(is_v, y + y0, x + x0))


def mec_axis_force(params: MECParams, bearing: Bearing, axis, i_top, i_bottom, i_top_other, i_bottom_other,
                   x, y, x0, y0):
    """Force [N] along each row's own axis, in the contract's per-row terms.

    ``axis`` 0 (v) or 1 (w); ``i_top``, ``i_bottom`` this axis' coil currents, ``i_*_other`` the
    other axis' (from the row read at the same ``time_s``); ``x``, ``y`` the sensor positions on
    this and the other axis and ``x0``, ``y0`` their effective origins [m], so the physical
    displacement is ``x + x0`` on the row's axis.
    """
    is_v, inputs = _bearing_frame(axis, i_top, i_bottom, i_top_other, i_bottom_other, x, y, x0, y0)
    f = mec_solve(params, bearing, *inputs).force
    return jnp.where(is_v, f[..., 0], f[..., 1])


@functools.partial(jax.jit, static_argnums=1)
def _solve_rows(params, bearing, i_vt, i_vb, i_wt, i_wb, dv, dw):
    """:func:`_solve_one`'s force over rows whose parameters differ row by row (every field shaped ``(n,)``)."""
    one = functools.partial(_solve_one, full=False)
    return jax.vmap(one, in_axes=(0, None, 0, 0, 0, 0, 0, 0))(params, bearing, i_vt, i_vb, i_wt, i_wb, dv, dw)


def row_axis_force(params: MECParams, bearing: Bearing, axis, i_top, i_bottom, i_top_other, i_bottom_other,
                   x, y, x0, y0):
    """:func:`mec_axis_force` with parameters given per row (each field broadcast to the rows)."""
    axis = jnp.asarray(axis)
    n = axis.shape[0]
    rows = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(jnp.asarray(a, dtype=float), (n,)), params)
    is_v, inputs = _bearing_frame(axis, i_top, i_bottom, i_top_other, i_bottom_other, x, y, x0, y0)
    f = _solve_rows(rows, bearing, *inputs)
    return jnp.where(is_v, f[:, 0], f[:, 1])
