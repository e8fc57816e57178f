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

The circuit is solved by Newton's method per reading (:mod:`~ambfit.physics.circuit.solve`), jit-able,
vmap-able and differentiable in float64.

Layout: :mod:`~ambfit.physics.circuit.iron` (the lamination's B-H curve),
:mod:`~ambfit.physics.circuit.network` (the parameters, the eight poles' network and its nodal
equations), :mod:`~ambfit.physics.circuit.solve` (Newton's method on the loop fluxes, the forces);
this package is their public API.

Units: SI throughout (m, A, Wb, T, N).
"""

from ambfit.physics.circuit.iron import DEFAULT_MU_R, bh_curve
from ambfit.physics.circuit.network import POLE_SPLIT, ROTOR_SPLIT, YOKE_SPLIT, MECParams
from ambfit.physics.circuit.solve import (
    FLUX_WIDTH,
    MAX_NEWTON,
    NEWTON_FAILED,
    NEWTON_STOP,
    MECSolution,
    mec_axis_force,
    mec_forces,
    mec_solve,
    row_axis_force,
    row_axis_force_and_flux,
)

__all__ = [
    "MECParams", "MECSolution", "mec_solve", "mec_forces", "mec_axis_force", "row_axis_force",
    "row_axis_force_and_flux", "bh_curve", "FLUX_WIDTH",
    "MAX_NEWTON", "NEWTON_FAILED", "NEWTON_STOP", "POLE_SPLIT", "YOKE_SPLIT", "ROTOR_SPLIT", "DEFAULT_MU_R",
]
