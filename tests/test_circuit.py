"""The magnetic equivalent circuit (ambfit.physics.circuit) against the ideal law and the physics it adds.

Every call below uses batches of ``BATCH`` readings so that the jitted solver compiles once per
bearing (compilation dominates the run time of this file).
"""

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ambfit.physics.bearing import PAPER_BEARING, Bearing
from ambfit.physics.circuit import MECParams, mec_axis_force, mec_forces, mec_solve, row_axis_force
from ambfit.physics.circuit.network import _residual, _unpack
from ambfit.physics.model import BearingParams, Readings, ideal_force

BATCH = 8
# An 8-pole bearing with a lamination B-H curve (the FEM development bearing's datasheet numbers).
FEM_BEARING = PAPER_BEARING.with_(
    name="fem-like", turns_per_pole=160.0, pole_area=116e-6, pole_width=5.8e-3,
    b_curve=(0.0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.2, 1.3, 1.4, 1.5, 1.6, 1.7, 1.8, 1.9),
    h_curve=(0.0, 31.9, 63.8, 96.0, 129.0, 166.0, 225.4, 291.3, 442.3, 844.7, 2032.8, 5818.9, 18703.1, 65355.4),
)
REAL = MECParams.drawing(FEM_BEARING, fringe_axial=0.0, fringe_depth=3.4e-3, pole_area_ratio=0.67)


def batch(*cols):
    """Columns padded/broadcast to ``BATCH`` rows."""
    return [jnp.resize(jnp.asarray(c, dtype=float), (BATCH,)) for c in cols]


def random_readings(seed, bias=1.5, reach=50e-6):
    rng = np.random.default_rng(seed)
    i_vt, i_vb, i_wt, i_wb = (bias + rng.uniform(-0.9, 0.9, BATCH) for _ in range(4))
    dv, dw = rng.uniform(-reach, reach, BATCH), rng.uniform(-reach, reach, BATCH)
    return batch(i_vt, i_vb, i_wt, i_wb, dv, dw)

def paired_rows(seed, n, bias):
    """``n`` contract rows of both axes (the other axis' currents beside each) around ``bias`` on the FEM-like
    bearing, and parameters for them: what a circuit effect evaluates."""
    rng = np.random.default_rng(seed)
    r = Readings.build(axis=np.arange(n) % 2, i_top=bias + rng.uniform(-0.9, 0.9, n),
                       i_bottom=bias + rng.uniform(-0.9, 0.9, n), x=rng.uniform(-80e-6, 80e-6, n),
                       y=rng.uniform(-80e-6, 80e-6, n), i_top_other=bias + rng.uniform(-0.9, 0.9, n),
                       i_bottom_other=bias + rng.uniform(-0.9, 0.9, n))
    return r, BearingParams.from_values([775e-6, 763e-6], [33e-6, -11e-6], FEM_BEARING.force_constant())



@pytest.mark.parametrize("bearing", [PAPER_BEARING, FEM_BEARING], ids=["linear-iron", "bh-curve"])
def test_ideal_assumptions_give_the_ideal_law(bearing):
    # Ideal iron, no fringing, no leakage, isolated horseshoes: each horseshoe is two gaps in series
    # and Eq. 3 holds exactly for both axes, also with the rotor off-centre on the other axis.
    # The only departure is the MU_R_MAX = 1e12 ceiling, ~1e-10 relative.
    i_vt, i_vb, i_wt, i_wb, dv, dw = random_readings(1)
    fv, fw = mec_forces(MECParams.ideal(bearing), bearing, i_vt, i_vb, i_wt, i_wb, dv, dw)
    k = bearing.force_constant(lamination=1.0)
    g = bearing.nominal_gap
    np.testing.assert_allclose(fv, ideal_force(g, 0.0, k, i_vt, i_vb, dv, bearing.cos_alpha), rtol=1e-9)
    np.testing.assert_allclose(fw, ideal_force(g, 0.0, k, i_wt, i_wb, dw, bearing.cos_alpha), rtol=1e-9)


def test_force_is_odd_under_the_mirror_of_an_axis():
    # Mirroring v -> -v maps the v top horseshoe onto the bottom one (and every N pole onto an S
    # pole, which the force does not see): F_v(-dv, i_vb, i_vt) = -F_v(dv, i_vt, i_vb), F_w unchanged.
    # Holds for the full nonlinear circuit; a wrong pole angle, polarity or coil map breaks it.
    i_vt, i_vb, i_wt, i_wb, dv, dw = random_readings(2, bias=2.0)
    s = mec_solve(REAL, FEM_BEARING, i_vt, i_vb, i_wt, i_wb, dv, dw)
    m = mec_solve(REAL, FEM_BEARING, i_vb, i_vt, i_wt, i_wb, -dv, dw)
    assert float(jnp.max(s.residual)) < 1e-12
    np.testing.assert_allclose(m.force[:, 0], -s.force[:, 0], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(m.force[:, 1], s.force[:, 1], rtol=1e-9, atol=1e-9)
    # and the same for w
    m = mec_solve(REAL, FEM_BEARING, i_vt, i_vb, i_wb, i_wt, dv, -dw)
    np.testing.assert_allclose(m.force[:, 1], -s.force[:, 1], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(m.force[:, 0], s.force[:, 0], rtol=1e-9, atol=1e-9)


def test_saturation_lowers_the_force_at_high_current():
    # One coil energised, rotor centred: the B-H curve's iron against ideal iron.  Far below the
    # knee the ratio is the (small) constant iron-reluctance loss; it falls steeply once the pole
    # body passes ~1.4 T.
    currents = jnp.linspace(0.5, 8.0, BATCH)
    zero = jnp.zeros(BATCH)
    iron = mec_forces(REAL, FEM_BEARING, currents, zero, zero, zero, zero, zero)[0]
    ideal_iron = mec_forces(REAL.replace(iron_h_scale=0.0), FEM_BEARING, currents, zero, zero, zero, zero, zero)[0]
    ratio = np.asarray(iron / ideal_iron)
    assert np.all(np.diff(ratio) < 0)
    assert 0.95 < ratio[0] < 1.0
    assert ratio[-1] < 0.6
    b_pole = np.abs(np.asarray(mec_solve(REAL, FEM_BEARING, currents, zero, zero, zero, zero, zero).b_pole)).max(1)
    assert b_pole[0] < 0.5 and b_pole[-1] > 1.6


def test_the_other_axis_bias_adds_negative_stiffness_growing_with_its_square():
    # With a solid back-iron ring the w horseshoes' poles (22.5 deg off the w axis, i.e. 67.5 deg
    # from v) pull the rotor along v when it moves on v: extra negative stiffness (dF_v/ddv > 0)
    # proportional to the w bias squared (linear iron).  Isolated horseshoes (link 0) have none:
    # each horseshoe's two gaps stay in series and the ideal law holds.
    h = 1e-7
    zero, v_bias = jnp.zeros(BATCH), jnp.full(BATCH, 1.0)
    w_bias = jnp.array([0.0, 1.0, 2.0, 0.0, 0.0, 1.0, 2.0, 0.0])
    link = jnp.array([1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0])

    def stiffness(link_value, rows):
        p = MECParams.ideal(PAPER_BEARING, link=link_value)
        f = lambda d: mec_forces(p, PAPER_BEARING, v_bias, v_bias, w_bias, w_bias, d, zero)[0]  # noqa: E731
        return np.asarray((f(jnp.full(BATCH, h)) - f(jnp.full(BATCH, -h))) / (2 * h))[rows]

    ring = stiffness(1.0, [0, 1, 2])
    isolated = stiffness(0.0, [4, 5, 6])
    extra = ring[1:] - ring[0]
    assert np.all(extra > 0)
    assert extra[1] / extra[0] == pytest.approx(4.0, rel=1e-4)
    np.testing.assert_allclose(isolated, isolated[0], rtol=1e-6)
    k = PAPER_BEARING.force_constant(lamination=1.0)
    g = PAPER_BEARING.nominal_gap
    ideal = 4 * k * PAPER_BEARING.cos_alpha * 1.0 / g**3           # d/dx of Eq. 4 at the centre, 1 A / 1 A
    assert isolated[0] == pytest.approx(ideal, rel=1e-6)
    assert link[0] == 1.0  # (documentation of the layout above)


def test_implicit_derivatives_match_finite_differences():
    # The solver's derivatives come from one Newton step with a frozen Jacobian; check them against
    # central differences of the converged solution in a parameter (gap) and an input (current).
    i_vt, i_vb, i_wt, i_wb, dv, dw = random_readings(3, bias=2.0)

    def fv(gap, i_top):
        return mec_forces(REAL.replace(gap=gap), FEM_BEARING, i_top, i_vb, i_wt, i_wb, dv, dw)[0]

    g0 = REAL.gap
    jac_g, jac_i = jax.jacfwd(fv, argnums=(0, 1))(g0, i_vt)     # one trace for both
    jac_i = jnp.diag(jac_i)
    hg, hi = 1e-9, 1e-6
    fd_g = (fv(g0 + hg, i_vt) - fv(g0 - hg, i_vt)) / (2 * hg)
    fd_i = (fv(g0, i_vt + hi) - fv(g0, i_vt - hi)) / (2 * hi)
    np.testing.assert_allclose(jac_g, fd_g, rtol=2e-6)
    np.testing.assert_allclose(jac_i, fd_i, rtol=2e-6)


def test_axis_force_picks_each_rows_axis_and_origin():
    i_vt, i_vb, i_wt, i_wb, dv, dw = random_readings(4)
    fv, fw = mec_forces(REAL, FEM_BEARING, i_vt, i_vb, i_wt, i_wb, dv, dw)
    x0, y0 = 12e-6, -7e-6
    axis = jnp.array([0, 1] * (BATCH // 2))
    is_v = axis == 0
    row = mec_axis_force(REAL, FEM_BEARING, axis, jnp.where(is_v, i_vt, i_wt), jnp.where(is_v, i_vb, i_wb),
                         jnp.where(is_v, i_wt, i_vt), jnp.where(is_v, i_wb, i_vb),
                         jnp.where(is_v, dv, dw) - x0, jnp.where(is_v, dw, dv) - y0, x0, y0)
    np.testing.assert_allclose(row, jnp.where(is_v, fv, fw), rtol=1e-12)
    assert math.isfinite(float(row[0]))


def test_bearing_without_a_bh_curve_uses_linear_iron():
    assert isinstance(PAPER_BEARING, Bearing) and PAPER_BEARING.b_curve == ()
    zero = jnp.zeros(BATCH)
    currents = jnp.linspace(0.5, 8.0, BATCH)
    p = MECParams.drawing(PAPER_BEARING, fringe_depth=0.0, leakage=0.0)
    f = np.asarray(mec_forces(p, PAPER_BEARING, currents, zero, zero, zero, zero, zero)[0])
    np.testing.assert_allclose(f / np.asarray(currents) ** 2, f[0] / 0.25, rtol=1e-9)   # no saturation



def test_the_bh_curve_has_its_slope_at_every_knot():
    # the monotone cubic's derivative at a knot (B = 0 among them, where Newton's method starts) is the knot's
    # slope, from either side: a clipped interval coordinate would halve it there
    from ambfit.physics.circuit.iron import bh_curve

    bh = bh_curve(FEM_BEARING)
    knots, slopes = np.array(bh.b), np.array(bh.d)
    for b, d in zip(knots[:-1], slopes[:-1]):
        _, at = jax.jvp(bh, (jnp.asarray(b),), (jnp.asarray(1.0),))
        left = (float(bh(jnp.asarray(b))) - float(bh(jnp.asarray(b - 1e-7)))) / 1e-7 if b > 0 else d
        np.testing.assert_allclose(float(at), d, rtol=1e-9)
        np.testing.assert_allclose(left, d, rtol=1e-4)

# --- the loop-flux solver against the nodal form of the same circuit -----------------------------------------

# Reference forces from Newton's method on the 64 nodal unknowns of ``_residual`` with a traced Jacobian
# (the nodal form) at a saturating operating point (pole iron up to 1.74 T), with dF_v / d(fringe_depth, leakage,
# iron_h_scale, pole_area_ratio): the solver must reproduce them to round-off.
SAVED_PARAMS = dict(fringe_axial=0.0, fringe_depth=1e-2, leakage=0.53, iron_h_scale=0.68, pole_area_ratio=0.71,
                    leakage_height=0.7, link=0.6)
SAVED_FV = [-47.5040158452094, 9.005810381898895, 10.068835424461755, -34.35992306945397, -21.28050037028682,
            20.52710130562216, 6.308101858882579, -39.931738017498354]
SAVED_FW = [-0.09006775666608473, -15.727653250826329, 23.795311392848614, -12.27694638354736, 14.478158066946026,
            8.429502830584081, -1.1717888505185825, -5.09820798184407]
SAVED_DFV = [[899.0930438233453, 8.88421004160588, 7.2790781025813205, -138.50580093574695],
             [-120.40292166875503, -1.1942894112671814, -1.6181214696799426, 19.327600144733182],
             [-117.20612005290083, -1.1995395989569935, -1.3494852898289615, 17.08306174376793],
             [183.8464919804422, 1.5442567492854848, 3.2313455418955783, -30.267315936906215],
             [167.501720813237, 1.2843683504869854, 2.159562780869211, -24.052156875562883],
             [-610.000523030257, -7.578914306057402, -4.106506984046255, 84.67373573968271],
             [-11.711075952222327, -0.152323510506004, -0.49759941545273656, 1.995700639383274],
             [659.6220472006829, 7.13160417010159, 5.926174711902079, -100.39520796936823]]


def test_reproduces_the_saved_nodal_forces_and_derivatives():
    p = MECParams.drawing(FEM_BEARING, **SAVED_PARAMS)
    args = random_readings(11, bias=2.5, reach=100e-6)
    fv, fw = mec_forces(p, FEM_BEARING, *args)
    np.testing.assert_allclose(fv, SAVED_FV, rtol=1e-10)
    np.testing.assert_allclose(fw, SAVED_FW, rtol=1e-10, atol=1e-12)

    def f(fd, lk, ih, par):
        return mec_forces(p.replace(fringe_depth=fd, leakage=lk, iron_h_scale=ih, pole_area_ratio=par), FEM_BEARING,
                          *args)[0]

    jac = jax.jacfwd(f, argnums=(0, 1, 2, 3))(p.fringe_depth, p.leakage, p.iron_h_scale, p.pole_area_ratio)
    np.testing.assert_allclose(np.stack(jac, 1), SAVED_DFV, rtol=1e-8)
    # and the same derivatives against central differences of the converged solution
    base = np.array([float(p.fringe_depth), float(p.leakage), float(p.iron_h_scale), float(p.pole_area_ratio)])
    for j in range(4):
        h = 1e-6 * base[j]
        up, dn = base.copy(), base.copy()
        up[j] += h
        dn[j] -= h
        fd = (f(*up) - f(*dn)) / (2 * h)
        np.testing.assert_allclose(jac[j], fd, rtol=1e-5, atol=1e-6 * float(jnp.max(jnp.abs(jac[j]))))


@jax.jit
def _nodal_solution(p, currents, gaps):
    """The nodal form solved directly: Newton on ``_residual``'s 64 unknowns (rows of ``currents``, ``gaps``)."""
    def one(c, g):
        fun = lambda z: _residual(z, p, FEM_BEARING, c, g)  # noqa: E731
        return jax.lax.fori_loop(0, 25, lambda _, z: z - jnp.linalg.solve(jax.jacfwd(fun)(z), fun(z)), jnp.zeros(64))
    return jax.vmap(one)(currents, gaps)


@pytest.mark.parametrize("params", [SAVED_PARAMS, dict(leakage=0.0, link=0.0, iron_h_scale=3.0)],
                         ids=["saturating", "no-leakage-isolated"])
def test_loop_fluxes_solve_the_nodal_equations(params):
    p = MECParams.drawing(FEM_BEARING, **params)
    i_vt, i_vb, i_wt, i_wb, dv, dw = random_readings(12, bias=2.5, reach=100e-6)
    s = mec_solve(p, FEM_BEARING, i_vt, i_vb, i_wt, i_wb, dv, dw)
    assert float(jnp.max(s.residual)) < 1e-12           # the nodal residual of the loop-flux solution
    currents = jnp.stack([i_vt, i_vb, i_wt, i_wb], axis=1)
    z = _nodal_solution(p, currents, s.gaps)
    (_, _, ut, ur), (f_root, f_tip, fr, fy) = jax.vmap(lambda zz: _unpack(zz, FEM_BEARING))(z)
    np.testing.assert_allclose(s.mmf_gap, ut - ur, rtol=1e-11, atol=1e-11 * float(jnp.max(jnp.abs(ut - ur))))
    area = FEM_BEARING.pole_area * p.lamination
    a_pole, a_back = area * p.pole_area_ratio, area * p.iron_area_ratio
    for mine, ref in ((s.b_pole, f_root / a_pole), (s.b_tip, f_tip / a_pole), (s.b_rotor, fr / a_back),
                      (s.b_yoke, fy / a_back)):
        np.testing.assert_allclose(mine, ref, rtol=1e-10, atol=1e-10 * float(jnp.max(jnp.abs(ref))))


def test_row_parameters_give_the_shared_parameters_forces_and_derivatives():
    # row_axis_force (parameters broadcast per row, the fit's path) against mec_axis_force.
    i_vt, i_vb, i_wt, i_wb, dv, dw = random_readings(13, bias=2.0)
    axis = jnp.array([0, 1] * (BATCH // 2))
    is_v = axis == 0
    cols = (jnp.where(is_v, i_vt, i_wt), jnp.where(is_v, i_vb, i_wb), jnp.where(is_v, i_wt, i_vt),
            jnp.where(is_v, i_wb, i_vb), jnp.where(is_v, dv, dw), jnp.where(is_v, dw, dv))

    def force(fn, gap, iron):
        return fn(REAL.replace(gap=gap, iron_h_scale=iron), FEM_BEARING, axis, *cols, 0.0, 0.0)

    np.testing.assert_allclose(force(row_axis_force, REAL.gap, 1.2), force(mec_axis_force, REAL.gap, 1.2), rtol=1e-12)
    # traced (a fit's compiled solve: the rows solved in place) and concrete (their compiled program) alike
    traced = jax.jit(lambda g: force(row_axis_force, g, 1.2))(REAL.gap)
    np.testing.assert_allclose(traced, force(row_axis_force, REAL.gap, 1.2), rtol=1e-12)
    ja = jax.jacfwd(lambda g, i: force(row_axis_force, g, i), argnums=(0, 1))(REAL.gap, 1.2)
    jb = jax.jacfwd(lambda g, i: force(mec_axis_force, g, i), argnums=(0, 1))(REAL.gap, 1.2)
    for a, b in zip(ja, jb):
        np.testing.assert_allclose(a, b, rtol=1e-10)


def test_row_force_derivatives_in_every_input_forward_and_reverse():
    # The fit's path (row_axis_force: each row's derivatives by one reverse pass, applied to every tangent, a custom
    # JVP) against the forward derivatives of mec_axis_force, in every circuit parameter and every reading of a row;
    # a gradient (a sampler's, jax.grad) takes the reverse of that rule, so both modes are checked.  Both sides take
    # the same implicit-function step: they agree to round-off.
    i_vt, i_vb, i_wt, i_wb, dv, dw = random_readings(29, bias=2.2)
    axis = jnp.array([0, 1] * (BATCH // 2))
    is_v = axis == 0
    names = tuple(f.name for f in dataclasses.fields(MECParams) if getattr(REAL, f.name) is not None)
    base = REAL.replace(fringe_axial=0.7, leakage_height=0.8, lamination=0.97, link=0.9, saturation=0.95,
                        iron_h_scale=1.3)

    def force(fn, theta):
        p = base.replace(**dict(zip(names, theta[:len(names)])))
        shift = theta[len(names):]
        cols = (jnp.where(is_v, i_vt, i_wt), jnp.where(is_v, i_vb, i_wb), jnp.where(is_v, i_wt, i_vt),
                jnp.where(is_v, i_wb, i_vb), jnp.where(is_v, dv, dw), jnp.where(is_v, dw, dv))
        return fn(p, FEM_BEARING, axis, *(c + d for c, d in zip(cols, shift[:6])), shift[6], shift[7])

    theta = jnp.concatenate([jnp.array([getattr(base, n) for n in names]), jnp.zeros(6), jnp.array([12e-6, -7e-6])])
    want = jax.jacfwd(lambda t: force(mec_axis_force, t))(theta)
    scale = np.max(np.abs(want), axis=0)
    assert np.all(scale > 0)                        # every input moves some row's force
    for got in (jax.jacfwd(lambda t: force(row_axis_force, t))(theta),
                jax.jacrev(lambda t: force(row_axis_force, t))(theta)):
        np.testing.assert_allclose(np.asarray(got) / scale, np.asarray(want) / scale, rtol=0, atol=1e-12)
    # the derivatives come from the rule, not from forward mode through the solve
    assert "custom_jvp_call" in str(jax.make_jaxpr(lambda t: force(row_axis_force, t))(theta))


def test_a_slope_of_the_row_force_has_the_forward_paths_gradient():
    # A fit's noise weights hold the force's slopes in the readings; a gradient-based sampler differentiates those
    # slopes again, through the rule.  Both paths hold the solve's fluxes and factors: they agree to round-off (4e-16
    # relative here).
    i_vt, i_vb, i_wt, i_wb, dv, dw = random_readings(37, bias=2.0)
    axis = jnp.array([0, 1] * (BATCH // 2))
    is_v = axis == 0
    cols = (jnp.where(is_v, i_vb, i_wb), jnp.where(is_v, i_wt, i_vt), jnp.where(is_v, i_wb, i_vb),
            jnp.where(is_v, dv, dw), jnp.where(is_v, dw, dv))
    top = jnp.where(is_v, i_vt, i_wt)

    def slope(fn, theta):
        def force(it):
            return fn(REAL.replace(gap=theta[0], iron_h_scale=theta[1]), FEM_BEARING, axis, it, *cols, 0.0, 0.0)
        return jnp.sum(jax.jvp(force, (top,), (jnp.ones_like(top),))[1] ** 2)

    theta = jnp.array([REAL.gap, 1.2])
    want = jax.grad(lambda t: slope(mec_axis_force, t))(theta)
    np.testing.assert_allclose(jax.grad(lambda t: slope(row_axis_force, t))(theta), want, rtol=1e-12)


def test_a_circuit_solve_that_has_not_converged_gives_nan_not_a_number_that_looks_right(monkeypatch):
    from ambfit.physics.circuit import solve

    b = PAPER_BEARING
    p = MECParams.ideal(b)
    with jax.disable_jit():                      # the step budget is read when the loop runs
        monkeypatch.setattr(solve, "MAX_NEWTON", 1)
        stopped = mec_forces(p, b, 2.0, 1.0, 1.5, 1.5, 0.0, 0.0)
        monkeypatch.setattr(solve, "MAX_NEWTON", 40)
        solved = mec_forces(p, b, 2.0, 1.0, 1.5, 1.5, 0.0, 0.0)
    assert np.isnan(float(stopped[0])) and np.isnan(float(stopped[1]))
    assert np.isfinite(float(solved[0])) and float(solved[0]) > 0


@pytest.mark.parametrize("fn", [row_axis_force, mec_axis_force], ids=["fit-path", "public"])
def test_a_row_without_a_solution_has_zero_slopes_and_spoils_no_other_rows(fn):
    # One row's other-axis current unknown (NaN): its force is NaN, its derivatives zero in both modes, and the
    # other rows' derivatives in the parameters they share stay finite and as they are without it; on the fits'
    # path (the rule) and on the public one (mec_solve).
    i_vt, i_vb, i_wt, i_wb, dv, dw = random_readings(31, bias=1.8)
    axis = jnp.array([0, 1] * (BATCH // 2))
    broken = i_wt.at[2].set(jnp.nan)

    def force(gap, other):
        return fn(REAL.replace(gap=gap), FEM_BEARING, axis, i_vt, i_vb, other, i_wb, dv, dw, 0.0, 0.0)

    assert np.isnan(force(REAL.gap, broken)[2]) and np.all(np.isfinite(np.delete(force(REAL.gap, broken), 2)))
    want = jax.jacfwd(force)(REAL.gap, i_wt)
    for slope in (jax.jacfwd(force)(REAL.gap, broken), jax.jacrev(force)(REAL.gap, broken)):
        assert slope[2] == 0.0
        np.testing.assert_allclose(np.delete(slope, 2), np.delete(want, 2), rtol=1e-12)


def test_a_reading_whose_solve_failed_has_no_number_that_looks_right():
    # One reading's top current unknown: every number of its solution NaN (its residual infinite), the others solved.
    i_vt, i_vb, i_wt, i_wb, dv, dw = random_readings(31, bias=1.8)
    sol = mec_solve(REAL, FEM_BEARING, i_vt.at[2].set(jnp.nan), i_vb, i_wt, i_wb, dv, dw)
    for name in ("force", "pole_force", "gap_flux", "b_gap", "b_pole", "b_tip", "b_yoke", "b_rotor", "mmf_gap"):
        value = np.asarray(getattr(sol, name))
        assert np.all(np.isnan(value[2])) and np.all(np.isfinite(np.delete(value, 2, axis=0))), name
    assert np.isinf(sol.residual[2]) and np.all(np.asarray(sol.residual)[[0, 1, 3]] < 1e-12)
    # the gaps are the reading's own, whatever the currents
    np.testing.assert_array_equal(sol.gaps, mec_solve(REAL, FEM_BEARING, i_vt, i_vb, i_wt, i_wb, dv, dw).gaps)


def test_a_held_circuit_parameter_is_not_fitted_and_survives_the_model_file():
    from ambfit.estimation.core import Model
    from ambfit.physics.effects import MagneticCircuit, effect_by_name

    e = MagneticCircuit(fringe_depth=jnp.asarray(1.5e-3), held=("fringe_depth",))
    names = Model.of([e]).names()
    assert "magnetic_circuit.fringe_depth" not in names and "magnetic_circuit.leakage" in names
    assert len(Model.of([MagneticCircuit()]).names()) == len(names) + 1
    again = effect_by_name("magnetic_circuit", **e.describe())        # the model JSON's round trip
    assert again.held == ("fringe_depth",) and float(again.fringe_depth) == 1.5e-3
    with pytest.raises(ValueError, match="bogus"):
        MagneticCircuit(held=("bogus",))


def test_newton_stops_a_step_early_without_losing_accuracy(monkeypatch):
    # the stop at NEWTON_STOP saves the step that only confirmed convergence: the fluxes are then within the square
    # of the last step of the solution, and the implicit-function step's derivatives come from factors that close
    from ambfit.physics.circuit import solve

    p = MECParams.drawing(FEM_BEARING, **SAVED_PARAMS)
    args = random_readings(11, bias=2.5, reach=100e-6)

    def solved():
        return jax.vmap(solve._solve_one, in_axes=(None, None, 0, 0, 0, 0, 0, 0))(p, FEM_BEARING, *args)

    def slopes():
        def f(lk, ih):
            return jax.vmap(functools.partial(solve._solve_one, full=False), in_axes=(None, None, 0, 0, 0, 0, 0, 0))(
                p.replace(leakage=lk, iron_h_scale=ih), FEM_BEARING, *args)[0][:, 0]

        return np.stack(jax.jacfwd(f, argnums=(0, 1))(p.leakage, p.iron_h_scale), 1)

    early, early_slopes = solved(), slopes()
    monkeypatch.setattr(solve, "NEWTON_STOP", 1e-13)
    late, late_slopes = solved(), slopes()
    assert int(jnp.sum(early.iterations)) < int(jnp.sum(late.iterations))
    np.testing.assert_allclose(early.force, late.force, rtol=1e-13, atol=1e-12)
    np.testing.assert_allclose(early_slopes, late_slopes, rtol=1e-9)
    assert float(jnp.max(early.residual)) < 1e-12


def test_a_warm_start_takes_fewer_steps_and_gives_the_same_forces_and_slopes():
    # a fit's next point starts each reading's solve from the fluxes of its last (row_axis_force_and_flux): fewer
    # Newton steps, the same force and derivatives; a start far off or not finite starts again from zero flux
    from ambfit.physics.circuit import solve

    p = MECParams.drawing(FEM_BEARING, **SAVED_PARAMS)
    near = p.replace(leakage=p.leakage * 1.01, iron_h_scale=p.iron_h_scale * 0.99, gap=p.gap * 1.001)
    args = random_readings(12, bias=2.5, reach=100e-6)
    cos_t, sin_t, _ = solve._geometry(FEM_BEARING)

    @jax.jit
    def newton_steps(params, start):
        def one(i_vt, i_vb, i_wt, i_wb, dv, dw, x0):
            gaps = params.gap - dv * jnp.asarray(cos_t) - dw * jnp.asarray(sin_t)
            return solve._newton(params, FEM_BEARING, jnp.stack([i_vt, i_vb, i_wt, i_wb]), gaps, x0)[1]
        return jax.vmap(one)(*args, start)

    @jax.jit
    def solved_(params, start):
        def f(lk, ih):
            return jax.vmap(lambda *row: solve._solve_one(params.replace(leakage=lk, iron_h_scale=ih), FEM_BEARING,
                                                          *row[:6], full=False, start=row[6]))(*args, start)
        (force, flux), slopes = f(params.leakage, params.iron_h_scale), jax.jacfwd(
            lambda lk, ih: f(lk, ih)[0], argnums=(0, 1))(params.leakage, params.iron_h_scale)
        return force, flux, jnp.stack(slopes, -1)

    def steps(params, start):
        return np.asarray(newton_steps(params, start))

    def solved(params, start):
        return tuple(np.asarray(a) for a in solved_(params, start))

    zero = jnp.zeros((BATCH, solve.FLUX_WIDTH))
    _, flux, _ = solved(p, zero)
    assert np.all(flux != 0) or np.count_nonzero(flux) > flux.size // 2
    assert steps(near, jnp.asarray(flux)).max() < steps(near, zero).max()
    cold, _, cold_slopes = solved(near, zero)
    far = jnp.asarray(flux) * 1e4 * np.random.default_rng(0).standard_normal(flux.shape)
    for start in (jnp.asarray(flux), far, jnp.full_like(zero, jnp.nan)):
        force, again, slopes = solved(near, start)
        np.testing.assert_allclose(force, cold, rtol=1e-13, atol=1e-12)
        np.testing.assert_allclose(slopes, cold_slopes, rtol=1e-9, atol=1e-9)
    assert np.all(steps(near, jnp.asarray(again)) <= 2)         # the fluxes returned are the solution


def test_each_rows_fluxes_come_back_for_the_next_evaluation():
    # what a fit carries from one point to the next (Model.flux_width wide): each row's own solution, whatever start
    # it was solved from
    from ambfit.estimation.core import IDEAL, Model
    from ambfit.physics.circuit import FLUX_WIDTH
    from ambfit.physics.effects import MagneticCircuit
    from ambfit.physics.model import evaluate

    n = 6
    r, params = paired_rows(5, n, bias=2.5)
    mec = MagneticCircuit()
    assert Model.of([mec], FEM_BEARING).flux_width == MagneticCircuit.FLUX_WIDTH == FLUX_WIDTH and IDEAL.flux_width == 0
    force, ctx = evaluate(params, r, [mec], bearing=FEM_BEARING)
    assert ctx.flux.shape == (n, FLUX_WIDTH) and np.all(np.any(np.asarray(ctx.flux) != 0, axis=1))
    for i in (0, 3):
        one = jax.tree.map(lambda a, i=i: a[i:i + 1], r)
        np.testing.assert_allclose(evaluate(params, one, [mec], bearing=FEM_BEARING)[1].flux[0], ctx.flux[i],
                                   rtol=1e-12, atol=1e-12)
    again, ctx2 = evaluate(params, r, [mec], bearing=FEM_BEARING, flux_start=ctx.flux[::-1])   # another row's
    np.testing.assert_allclose(again, force, rtol=1e-13)
    np.testing.assert_allclose(ctx2.flux, ctx.flux, rtol=1e-10, atol=1e-12)
    assert evaluate(params, r, [], bearing=FEM_BEARING)[1].flux is None


def test_a_piece_off_idles_exactly_the_parameters_it_names():
    # the refits of the circuit's pieces start these parameters at their prior centre (circuit_families): they must
    # be the ones the force no longer depends on, and only those
    import equinox as eqx

    from ambfit.physics.effects import MagneticCircuit
    from ambfit.physics.model import evaluate

    n = 8
    r, params = paired_rows(7, n, bias=2.0)
    names = ("fringe_depth", "leakage", "iron_scale", "pole_area_ratio")
    at = tuple(jnp.asarray(v) for v in (2.5e-3, 0.45, 1.1, 0.8))

    def force(values, mec):
        e = eqx.tree_at(lambda m: tuple(getattr(m, k) for k in names), mec, values)
        return evaluate(params, r, [e], bearing=FEM_BEARING)[0]

    pull = jax.jit(jax.jacfwd(force))               # (the pieces are an array: one program for all five)
    for piece in MagneticCircuit.PIECES:
        mec = MagneticCircuit().without(piece)
        # each parameter's pull on the force over its own size [N]: 0.1-6 N where it acts; with ideal iron slot
        # leakage keeps 4e-10 N, the reluctance of the MU_R_MAX ceiling
        size = [float(np.max(np.abs(np.asarray(d))) * v) for d, v in zip(pull(at, mec), (2.5e-3, 0.45, 1.1, 0.8))]
        assert all(np.isfinite(size)), piece
        assert {k for k, f in zip(names, size) if f < 1e-8 * max(size)} == set(mec.idle), piece


def test_a_warm_start_restarted_from_zero_flux_gives_the_cold_force(monkeypatch):
    # a warm start still moving after WARM_NEWTON steps starts again from zero flux; its residual, already at
    # round-off, must not end the fresh solve at zero flux (a wrong force flagged converged). Forced here: no step
    # is small enough to stop a warm solve, and the restart comes after four steps
    from ambfit.physics.circuit import solve

    p = MECParams.drawing(FEM_BEARING, **SAVED_PARAMS)

    def solver():                   # (jit reads the constants when it traces, at its first call)
        return jax.jit(lambda args, x0: jax.vmap(lambda *row: solve._solve_one(
            p, FEM_BEARING, *row[:6], full=False, start=row[6]))(*args, x0))

    cold, zero = solver(), jnp.zeros((BATCH, solve.FLUX_WIDTH))
    cases = [random_readings(seed, bias=bias, reach=100e-6) for seed, bias in ((1, 1.5), (13, 2.5))]
    solved = [cold(args, zero) for args in cases]            # traced and run before the patch
    monkeypatch.setattr(solve, "WARM_STOP", 0.0)
    monkeypatch.setattr(solve, "WARM_NEWTON", 4)
    restarted = solver()
    for args, (force, flux) in zip(cases, solved):
        for off in (1.02, 1.001):
            np.testing.assert_allclose(restarted(args, flux * off)[0], force, rtol=1e-12)
