"""Solving the magnetic equivalent circuit per reading: Newton's method on the loop fluxes, and the forces.

The circuit is solved by Newton's method (at most :data:`MAX_NEWTON` steps, stopping at a
relative step of :data:`NEWTON_STOP`; a reading whose solve is still moving by more than :data:`NEWTON_FAILED` after
:data:`MAX_NEWTON` steps gets a NaN force, so that a fit names its rows instead of using a wrong number); derivatives with respect to the parameters and inputs come from one
extra Newton step whose Jacobian is held constant (the implicit-function theorem), so
:func:`mec_forces` is jit-able, vmap-able and differentiable in float64.  Newton runs on 17 loop
fluxes (the flux law solved in advance, see ``_loop_system``) with a hand-written Jacobian; it takes
the same steps as on the 64 nodal unknowns of :mod:`~ambfit.physics.circuit.network`, whose residual it reports.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ambfit._arrays import traced
from ambfit.physics.bearing import MU_0, Bearing
from ambfit.physics.circuit.iron import MU_R_MAX, _iron_h, bh_curve
from ambfit.physics.circuit.network import (
    _COIL,
    _INTRA,
    _N_POLES,
    POLE_SPLIT,
    ROTOR_SPLIT,
    YOKE_SPLIT,
    MECParams,
    _gap_permeance,
    _geometry,
    _residual,
    _scales,
)

MAX_NEWTON = 40
"""Upper bound on the Newton steps of one circuit solve (typically 2-8 are used: 2 with linear iron, up to 8 at
readings deep in saturation)."""

NEWTON_STOP = 1e-10
"""Newton's method stops once a step moves the fluxes by at most this (relative); must stay below
:data:`NEWTON_FAILED`.  Its convergence is quadratic, so the fluxes that step returns are within about the square of
this of the solution, below round-off; the implicit-function step that follows adds the derivatives, from factors
taken at most this far from the solution (:data:`NEWTON_FAILED` for a solve that used all its steps), about 1e-11
relative.  A vmapped solve runs every reading for as many steps as its hardest one: on the finite-element development
bearing's readings a stop at 1e-13 takes a fifth step on a quarter of them only to confirm convergence, this one
takes four (the forces agree to 1e-15 relative).  A stop at 1e-8 saves no further step there and moves the
derivatives by 1e-7."""

WARM_NEWTON = 10
"""A solve started from fluxes other than zero (a warm start: the solution at nearby parameters,
:func:`row_axis_force_and_flux`) that still moves after this many steps starts again from zero flux, with the steps
left of :data:`MAX_NEWTON`.  From the fluxes of a fit's previous point Newton takes 2-5 steps on the finite-element
development bearing, from zero 4-8; a start far off could take longer than from zero, or diverge."""

WARM_STOP = 1e-12
"""The stop of a warm start's solve (:data:`NEWTON_STOP` from zero flux).  From nearby fluxes Newton's steps shrink
from 1e-3 or so, and a last step just below 1e-10 leaves the factors the derivatives come from that far from the
solution: derivatives 1e-8 off where a start from zero, whose steps reach the stop from further off, ends far below
it.  At 1e-12 the derivatives agree with a start from zero to 1e-9."""

NEWTON_FAILED = 1e-8
"""A solve whose last Newton step still moved the fluxes by more than this (relative) after :data:`MAX_NEWTON`
steps did not converge: its force is NaN.  One that used all its steps but last moved by less is accepted (its
fluxes are within about the square of this of the solution)."""


class MECSolution(eqx.Module):
    """One solved reading (arrays over the eight poles, pole ``k`` at ``α + k·45°`` from +v).

    ``force`` is ``(F_v, F_w)`` [N] on the rotor; ``pole_force`` the pull towards each pole [N];
    ``gaps`` [m]; ``gap_flux`` [Wb] (face plus fringe); ``b_gap`` the face flux density
    ``MU_0 U / g`` [T]; ``b_pole`` the flux density in each pole's iron between the yoke and the
    leakage point (the most loaded part), ``b_tip`` between the leakage point and the tip [T]; ``b_yoke``,
    ``b_rotor`` in the segments joining pole k and k+1 [T]; ``mmf_gap`` the drop across each gap [A];
    ``residual`` the largest scaled circuit residual after the solve, ``iterations`` the Newton steps.  A reading
    whose solve failed has NaN in every field but ``gaps`` and ``iterations``, and an infinite ``residual``.
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

FLUX_WIDTH = _NX
"""The unknowns of one reading's solve (the loop fluxes, scaled): the width of a warm start."""


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


def _newton(p, bearing, currents, gaps, x0):
    """Newton's method on the loop fluxes from ``x0`` (zero flux, or a warm start: :data:`WARM_NEWTON`); returns
    ``x``, the steps, the last LU factors and whether it converged (see :data:`NEWTON_FAILED`)."""
    warm = jnp.any(x0 != 0.0)
    stop = jnp.where(warm, WARM_STOP, NEWTON_STOP)

    def cond(state):
        _, step, res, it, _ = state
        return (step > stop) & (res > 1e-14) & (it < MAX_NEWTON)

    def body(state):
        x, _, _, it, _ = state
        r, jac, _ = _loop_system(x, p, bearing, currents, gaps, with_jacobian=True)
        lu = jax.scipy.linalg.lu_factor(jac)
        dx = jax.scipy.linalg.lu_solve(lu, r)
        scale = jnp.maximum(jnp.max(jnp.abs(x)), 1.0)
        step = jnp.max(jnp.abs(dx)) / scale
        # a warm start still moving after its steps: again from zero flux
        again = warm & (it + 1 == WARM_NEWTON) & (step > stop)
        return (jnp.where(again, 0.0, x - dx), jnp.where(again, jnp.inf, step),
                jnp.where(again, jnp.inf, jnp.max(jnp.abs(r))), it + 1, lu)

    inf = jnp.asarray(jnp.inf)
    lu0 = (jnp.zeros((_NX, _NX)), jnp.zeros(_NX, dtype=jnp.int32))
    x, step, res, it, lu = jax.lax.while_loop(cond, body, (x0, inf, inf, jnp.asarray(0), lu0))
    return x, it, lu, (step <= NEWTON_FAILED) | (res <= 1e-14)


def _solve_one(p: MECParams, bearing: Bearing, i_vt, i_vb, i_wt, i_wb, dv, dw, full: bool = True, start=None):
    """One reading's solve: its :class:`MECSolution` (``full``), else its force and the loop fluxes it converged to
    (zero where it did not), from ``start`` (zero flux if None)."""
    cos_t, sin_t, _ = _geometry(bearing)
    currents = jnp.stack([jnp.asarray(c, dtype=float) for c in (i_vt, i_vb, i_wt, i_wb)])
    gaps = p.gap - dv * jnp.asarray(cos_t) - dw * jnp.asarray(sin_t)
    x0 = jnp.zeros(_NX) if start is None else jax.lax.stop_gradient(jnp.where(jnp.isfinite(start), start, 0.0))
    x_star, iterations, lu, converged = _newton(jax.lax.stop_gradient(p), bearing, jax.lax.stop_gradient(currents),
                                                jax.lax.stop_gradient(gaps), x0)
    x_star, lu = jax.lax.stop_gradient((x_star, lu))
    # A solve that failed goes on with stand-ins (zero flux, unit factors, no current, the centred gaps) whose numbers
    # are all replaced by NaN below: its own inputs and factors, NaN or far off, would turn every gradient of the
    # parameters the rows share NaN in reverse mode, where a NaN is multiplied by the zero that masks it.
    x_star = jnp.where(converged, x_star, 0.0)
    lu = (jnp.where(converged, lu[0], jnp.eye(_NX)), jnp.where(converged, lu[1], jnp.arange(_NX, dtype=lu[1].dtype)))
    currents = jnp.where(converged, currents, 0.0)
    true_gaps, gaps = gaps, jnp.where(converged, gaps, p.gap)
    # One more Newton step with the Jacobian held constant (the last step's factors, taken one step of at most
    # NEWTON_STOP before x_star, NEWTON_FAILED when the solve used all its steps): the same value, and
    # implicit-function derivatives.
    res, _, _ = _loop_system(x_star, p, bearing, currents, gaps, with_jacobian=False)
    x = x_star - jax.scipy.linalg.lu_solve(lu, res)
    _, _, ((f_root, fg, fr, fy), (u_mr, u_yr)) = _loop_system(x, p, bearing, currents, gaps, with_jacobian=False)

    perm, pull = _gap_permeance(p, bearing, gaps)
    drop = fg / perm
    pole_force = 0.5 * drop**2 * pull
    force = jnp.stack([jnp.sum(pole_force * jnp.asarray(cos_t)), jnp.sum(pole_force * jnp.asarray(sin_t))])
    force = jnp.where(converged, force, jnp.nan)          # never a wrong number: the caller sees NaN rows
    if not full:
        return force, x_star                             # (zero flux where the solve failed: the stand-in)
    # The nodal unknowns, for the nodal residual of the solution (MECSolution.residual).
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

    def solved(a):                                       # NaN where the solve failed (the stand-ins' numbers)
        return jnp.where(converged, a, jnp.nan)

    return MECSolution(
        force=force, pole_force=solved(pole_force), gaps=true_gaps, gap_flux=solved(fg),
        b_gap=solved(MU_0 * drop / gaps), b_pole=solved(f_root / (area * p.pole_area_ratio)),
        b_tip=solved(fg / (area * p.pole_area_ratio)), b_yoke=solved(fy / (area * p.iron_area_ratio)),
        b_rotor=solved(fr / (area * p.iron_area_ratio)), mmf_gap=solved(drop),
        residual=jnp.where(converged, jnp.max(jnp.abs(res_mna)), jnp.inf), iterations=iterations,
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
    >>> from ambfit.physics.bearing import PAPER_BEARING
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


def _own_force_of(bearing, p, is_v, i_vt, i_vb, i_wt, i_wb, dv, dw, start):
    """One reading's force along its own axis (``is_v``: v, else w) and the loop fluxes it converged to
    (:func:`_solve_one`)."""
    force, flux = _solve_one(p, bearing, i_vt, i_vb, i_wt, i_wb, dv, dw, full=False, start=start)
    return jnp.where(is_v, force[0], force[1]), flux


_own_force = jax.custom_jvp(_own_force_of, nondiff_argnums=(0,))
""":func:`_own_force_of` with its derivatives by one reverse pass through the implicit-function step (one adjoint
solve), applied to every tangent: a fit pushes a tangent per parameter and per reading through each solve (twenty and
more), and in forward mode each is another pass through the loop equations and the triangular solves.  The same
derivatives to round-off."""


@_own_force.defjvp
def _own_force_jvp(bearing, primals, tangents):
    p, is_v, *row, start = primals
    dp, _, *drow, _ = tangents
    force, pullback, flux = jax.vjp(lambda p, *row: _own_force_of(bearing, p, is_v, *row, start), p, *row,
                                    has_aux=True)
    # a row whose solve failed has zero derivatives (its force is the stand-ins' masked by NaN: see _solve_one); the
    # fluxes are the solve's own (no derivative)
    terms = jax.tree_util.tree_map(lambda g, t: g * t, pullback(jnp.ones_like(force)), (dp, *drow))
    return (force, flux), (sum(jax.tree_util.tree_leaves(terms)), jnp.zeros_like(flux))


def _rows(params, bearing, is_v, i_vt, i_vb, i_wt, i_wb, dv, dw, start):
    """Each row's force along its own axis (``is_v``: v, else w) and its loop fluxes, over rows whose parameters differ
    row by row (every field shaped ``(n,)``), from ``start`` [n, FLUX_WIDTH] (zero flux if None)."""
    def one(p, own, *row):
        return _own_force(bearing, p, own, *row[:6], row[6] if start is not None else None)

    rows = (is_v, i_vt, i_vb, i_wt, i_wb, dv, dw) + ((start,) if start is not None else ())
    return jax.vmap(one)(params, *rows)


_solve_rows = jax.jit(_rows, static_argnums=1)
""":func:`_rows` compiled, for concrete inputs; traced inputs (a fit's compiled solve differentiating it) trace
:func:`_rows` in place, which is cheaper than transforming a nested program."""


def row_axis_force(params: MECParams, bearing: Bearing, axis, i_top, i_bottom, i_top_other, i_bottom_other,
                   x, y, x0, y0):
    """:func:`mec_axis_force` with parameters given per row (each field broadcast to the rows)."""
    return row_axis_force_and_flux(params, bearing, axis, i_top, i_bottom, i_top_other, i_bottom_other,
                                   x, y, x0, y0)[0]


def row_axis_force_and_flux(params: MECParams, bearing: Bearing, axis, i_top, i_bottom, i_top_other,
                            i_bottom_other, x, y, x0, y0, start=None):
    """:func:`row_axis_force` and each row's loop fluxes [n, :data:`FLUX_WIDTH`] (scaled; zero where its solve did
    not converge), solved from ``start`` (such fluxes, e.g. at a fit's previous parameters; zero flux if None).

    The force does not depend on the start: every solve converges to the circuit's one solution and ends with the
    same implicit-function step (it agrees with a solve from zero flux to round-off)."""
    axis = jnp.asarray(axis)
    n = axis.shape[0]
    rows = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(jnp.asarray(a, dtype=float), (n,)), params)
    is_v, inputs = _bearing_frame(axis, *(jnp.asarray(a, dtype=float) for a in (i_top, i_bottom, i_top_other,
                                                                              i_bottom_other, x, y, x0, y0)))
    return (_rows if traced(rows, inputs, start) else _solve_rows)(rows, bearing, is_v, *inputs, start)
