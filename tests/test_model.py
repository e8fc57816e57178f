"""Force model (Eq. 3-4) against values computed by hand with the math module."""

import math

import jax
import numpy as np
import pytest

from ambfit import MU_0, PAPER_BEARING, BearingParams, Readings, axis_force, ideal_force, pole_gaps
from ambfit.physics.model import evaluate


def test_float64_is_on():
    assert jax.numpy.zeros(1).dtype == np.float64


def test_force_hand_computed():
    # g0 = 800 µm, x0 = 10 µm, x = 20 µm, alpha = 22.5°, k = 3e-6, i = (2, 1) A:
    # u = 30 µm cos(22.5°); g_t = 772.2836140246614 µm, g_b = 827.7163859753386 µm;
    # F = 3e-6 (4/g_t² - 1/g_b²) = 15.74115217109283 N (python math, see git history).
    f = ideal_force(800e-6, 10e-6, 3e-6, 2.0, 1.0, 20e-6)
    assert float(f) == pytest.approx(15.74115217109283, rel=1e-13)
    gt, gb = pole_gaps(800e-6, 10e-6, 20e-6)
    assert float(gt) == pytest.approx(0.0007722836140246614, rel=1e-14)
    assert float(gb) == pytest.approx(0.0008277163859753386, rel=1e-14)


def test_flux_density_hand_computed():
    # B = mu0 (2 N) i / (2 g) = 4e-7 pi * 480 * 2 / (2 * 772.28 µm) = 0.7810418070970215 T (2 x 240 turns)
    b = PAPER_BEARING.with_(turns_per_pole=240.0)
    assert float(b.flux_density(2.0, 0.0007722836140246614)) == pytest.approx(0.7810418070970215, rel=1e-14)


def test_paper_load_capacity():
    # The paper: 53.4 N at the 3.0 A saturation current, rotor centred, 762 µm gap.
    k = 53.4 * 762e-6**2 / 9.0
    p = BearingParams.from_values(762e-6, 0.0, k)
    r = Readings.build(axis=[0, 1], i_top=[3.0, 3.0], i_bottom=[0.0, 0.0], x=[0.0, 0.0])
    np.testing.assert_allclose(axis_force(p, r), [53.4, 53.4], rtol=1e-13)


def test_force_constant_formula():
    # 0.25 mu0 A (2N)^2 cos(alpha) lamination, A = 50 mm², 2N = 480, lamination 0.95
    expected = 0.25 * 4e-7 * math.pi * 50e-6 * 480**2 * math.cos(math.radians(22.5)) * 0.95
    b = PAPER_BEARING.with_(pole_area=50e-6, turns_per_pole=240.0)
    assert b.force_constant(0.95) == pytest.approx(expected, rel=1e-15)
    assert MU_0 == pytest.approx(4e-7 * math.pi)


def test_axes_use_their_own_parameters():
    p = BearingParams.from_values(g0=(775e-6, 763e-6), x0=(33e-6, -11e-6), k=(3.4e-6, 3.5e-6))
    r = Readings.build(axis=[0, 1], i_top=[1.6, 1.6], i_bottom=[1.2, 1.2], x=[5e-6, 5e-6], y=[7e-6, 7e-6])
    f = axis_force(p, r)
    assert float(f[0]) == pytest.approx(float(ideal_force(775e-6, 33e-6, 3.4e-6, 1.6, 1.2, 5e-6)), rel=1e-14)
    assert float(f[1]) == pytest.approx(float(ideal_force(763e-6, -11e-6, 3.5e-6, 1.6, 1.2, 5e-6)), rel=1e-14)


def test_symmetry_and_sign():
    # Mirror the rotor and swap the coils: the force flips sign.  More top current pulls towards +axis.
    p = BearingParams.from_values(760e-6, 0.0, 3.4e-6)
    a = axis_force(p, Readings.build(axis=[0], i_top=[1.7], i_bottom=[1.3], x=[12e-6]))
    b = axis_force(p, Readings.build(axis=[0], i_top=[1.3], i_bottom=[1.7], x=[-12e-6]))
    assert float(a[0]) == pytest.approx(-float(b[0]), rel=1e-13)
    assert float(a[0]) > 0


def test_context_exposes_gaps_and_flux():
    p = BearingParams.from_values(800e-6, 10e-6, 3e-6)
    f, ctx = evaluate(p, Readings.build(axis=[0], i_top=[2.0], i_bottom=[1.0], x=[20e-6]),
                      bearing=PAPER_BEARING.with_(turns_per_pole=240.0))
    assert float(ctx.g_top[0]) == pytest.approx(0.0007722836140246614, rel=1e-14)
    assert float(ctx.b_top()[0]) == pytest.approx(0.7810418070970215, rel=1e-14)


def test_force_is_jittable_and_differentiable():
    p = BearingParams.from_values(775e-6, 30e-6, 3.4e-6)
    r = Readings.build(axis=[0, 1], i_top=[1.6, 1.5], i_bottom=[1.2, 1.3], x=[5e-6, -5e-6])
    g = jax.jit(jax.grad(lambda q: axis_force(q, r).sum()))(p)
    # dF/dk = F/k exactly
    assert float(g.k.sum()) == pytest.approx(float(axis_force(p, r).sum()) / 3.4e-6, rel=1e-12)


def test_parameters_from_values_are_read_only_and_work_closed_over_by_a_jitted_function():
    """Concrete parameters are NumPy pairs (no JAX dispatch per simulation); a jitted function that closes over
    them indexes them by its traced axes, and traced values still give JAX arrays."""
    p = BearingParams.from_values(g0=762e-6, x0=(33e-6, -11e-6), k=3.4452e-6)
    assert isinstance(p.g0, np.ndarray) and not p.g0.flags.writeable
    r = Readings.build(axis=[0, 1, 1], i_top=[1.6, 1.5, 1.2], i_bottom=[1.4, 1.5, 1.7], x=[0.0, 1e-6, -4e-6])
    np.testing.assert_allclose(jax.jit(lambda r: axis_force(p, r))(r), axis_force(p, r), rtol=1e-14)
    traced = jax.jit(lambda g: BearingParams.from_values(g0=g, x0=0.0, k=3.4e-6).g0 * 2.0)(np.asarray(762e-6))
    np.testing.assert_allclose(traced, [1524e-6, 1524e-6])
