"""The magnetic equivalent circuit of the 8-pole bearing: its parameters, its network and its nodal equations.

:class:`MECParams` holds the physical parameters a designer can estimate.  The network (the
diagram in :mod:`ambfit.physics.circuit`): per pole a yoke node, a leakage point, a tip and a
rotor node, the coil MMF and pole iron between yoke and tip, the gap permeance with Roters
fringing between tip and rotor, slot leakage between neighbouring leakage points, and the yoke
and rotor rings.  :func:`_residual` writes Kirchhoff's and the branch laws on its 64 nodal
unknowns ("modified nodal analysis"); the solver (:mod:`ambfit.physics.circuit.solve`) works
on an equivalent smaller system and reports this residual of its solution.  SI units.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ambfit.physics.bearing import MU_0, PAPER_BEARING, Bearing
from ambfit.physics.circuit.iron import MU_R_MAX, _iron_h, bh_curve

POLE_SPLIT, YOKE_SPLIT, ROTOR_SPLIT = 0.25, 0.35, 0.15
"""How the mean iron path ``l_fe`` of one horseshoe circuit is shared: each of its two poles
``0.25 l_fe``, the yoke arc between them ``0.35 l_fe``, the rotor arc ``0.15 l_fe`` (a 45° arc at
the mean yoke radius of a 35 mm bore stator is about twice the rotor's).  Every yoke and rotor
segment (poles are equally spaced) gets the same length."""

_N_POLES = 8
_INTRA = np.array([False, True, False, True, False, True, False, True])
"""Yoke segment k joins poles k and k+1; True where both belong to one horseshoe (7-0, 1-2, 3-4, 5-6)."""
_COIL = np.array([0, 2, 2, 1, 1, 3, 3, 0])
"""Coil of pole k in the order (v top, v bottom, w top, w bottom)."""
_POLARITY = {"NNSS": np.array([1, 1, -1, -1, 1, 1, -1, -1], dtype=float),
             "NSNS": np.array([1, -1, 1, -1, 1, -1, 1, -1], dtype=float)}
"""Sign of each pole's MMF (+1: N, flux from the stator into the gap), poles 0..7 from +α."""


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


# --- the network ------------------------------------------------------------------------------------------

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
