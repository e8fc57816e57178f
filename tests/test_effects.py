"""Each unmodelled effect's physics against numbers computed by hand (python ``math``), one test per law.

Reference operating point (as in ``test_model.py``): axis v, ``g0`` = 800 µm, ``x0`` = 10 µm,
``x`` = 20 µm, ``k`` = 3e-6 N m²/A², ``i_top`` = 2 A, ``i_bottom`` = 1 A on the paper bearing
(alpha = 22.5°, 2 x 240 turns).  By hand: ``u = 30 µm cos(22.5°)``, ``g_t = 800 µm - u``,
``g_b = 800 µm + u``, ``B = MU_0 480 i / (2 g)`` (the ideal horseshoe circuit).
"""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from ambfit.physics import effects as E
from ambfit.physics.bearing import MU_0, PAPER_BEARING
from ambfit.physics.model import BearingParams, Readings, evaluate, ideal_force

# Every reference below is a closed-form expression of a few float64 operations; 1e-12 leaves room for the
# round-off of the library's different operation order (observed <= 1e-15) while any formula error (a wrong
# exponent, a missing factor 2, a hard-coded angle) moves the values by 1e-4 or more.
REL = 1e-12

G0, X0, K, IT, IB, X = 800e-6, 10e-6, 3e-6, 2.0, 1.0, 20e-6
COS = math.cos(math.radians(22.5))
SIN = math.sin(math.radians(22.5))
G_T = G0 - (X0 + X) * COS            # 772.2836140246614 µm
G_B = G0 + (X0 + X) * COS            # 827.7163859753386 µm
TURNS = 2 * 240.0                    # a horseshoe of the paper bearing


def b_of(i, g):
    """Ideal-circuit gap flux density by hand [T]."""
    return 4e-7 * math.pi * TURNS * i / (2.0 * g)


def one_row(effects=(), *, bearing=PAPER_BEARING, axis=0, i_top=IT, i_bottom=IB, x=X, y=0.0, g0=G0, x0=X0,
            x0_other=0.0, temperature=None, dir_top=None, dir_bottom=None, **kw):
    """Force [N] and context of one reading under ``effects``."""
    x0_pair = (x0, x0_other) if axis == 0 else (x0_other, x0)
    p = BearingParams.from_values(g0=g0, x0=x0_pair, k=K)
    r = Readings.build(axis=[axis], i_top=[i_top], i_bottom=[i_bottom], x=[x], y=[y],
                       temperature=None if temperature is None else [temperature],
                       dir_top=None if dir_top is None else [dir_top],
                       dir_bottom=None if dir_bottom is None else [dir_bottom])
    f, ctx = evaluate(p, r, tuple(effects), bearing=bearing, **kw)
    return float(f[0]), ctx


def test_reference_point_is_the_hand_computed_one():
    assert PAPER_BEARING.horseshoe_turns == TURNS and MU_0 == 4e-7 * math.pi
    f, ctx = one_row()
    assert float(ctx.g_top[0]) == pytest.approx(7.722836140246614e-4, rel=REL)
    assert float(ctx.b_top()[0]) == pytest.approx(b_of(IT, G_T), rel=REL)
    assert f == pytest.approx(K * (IT**2 / G_T**2 - IB**2 / G_B**2), rel=REL)


# --- saturation ------------------------------------------------------------------------------------------

def test_saturation_factor_at_the_knee_is_two_to_minus_two_over_p():
    # (1 + (B/b_sat)^p)^(-2/p) at B = b_sat is 2^(-2/p): p = 4 -> 2^-0.5 = 0.7071067811865476,
    # p = 6 -> 2^(-1/3) = 0.7937005259840998 (python: 2 ** (-2 / p)).
    sat = E.Saturation(b_sat=jnp.asarray([1.0, 1.3]), sharpness=jnp.asarray([4.0, 6.0]))
    assert float(sat.factor(1.0, 0)) == pytest.approx(0.7071067811865476, rel=REL)
    assert float(sat.factor(1.3, 1)) == pytest.approx(0.7937005259840998, rel=REL)
    # the sign of B does not matter (a coil current of either sign saturates the iron)
    assert float(sat.factor(-1.0, 0)) == pytest.approx(0.7071067811865476, rel=REL)


def test_saturation_is_negligible_at_low_flux_and_grows_with_it():
    sat = E.Saturation(b_sat=1.2, sharpness=5.0)
    # (1 + (0.12/1.2)^5)^(-0.4) = 1 - 0.4e-5 + O(1e-10): the square law holds far below the knee
    assert float(sat.factor(0.12, 0)) == pytest.approx(1.0 - 0.4e-5, abs=1e-9)
    f = np.asarray(sat.factor(jnp.linspace(0.0, 2.0, 41), 0))
    assert np.all(np.diff(f) < 0) and f[0] == 1.0


def test_saturation_scales_each_coils_force_by_its_own_flux_density():
    sat = E.Saturation(b_sat=0.9, sharpness=4.0)
    bt, bb = b_of(IT, G_T), b_of(IB, G_B)           # 0.7810 T and 0.3644 T

    def fac(b):
        return (1.0 + (b / 0.9) ** 4) ** (-0.5)

    f, ctx = one_row((sat,))
    assert float(ctx.k_top[0]) == pytest.approx(K * fac(bt), rel=REL)
    assert float(ctx.k_bottom[0]) == pytest.approx(K * fac(bb), rel=REL)
    assert f == pytest.approx(K * fac(bt) * IT**2 / G_T**2 - K * fac(bb) * IB**2 / G_B**2, rel=REL)


# --- iron reluctance -------------------------------------------------------------------------------------

def test_iron_reluctance_adds_l_fe_over_2_mu_r_at_low_flux():
    # i_bottom = 0: B = 0, mu = mu_r, extra gap = 0.08 / (2 * 2000) = 20 µm exactly.
    ir = E.IronReluctance(l_fe=0.08, mu_r=2000.0, b_knee=1.3)
    _, ctx = one_row((ir,), i_bottom=0.0)
    assert float(ctx.g_bottom[0]) - G_B == pytest.approx(20e-6, rel=1e-9)   # 1e-9: a difference of ~8e-4 m numbers
    # a small current: (B/b_knee)^4 ~ 1e-15, still 20 µm
    _, ctx = one_row((ir,), i_bottom=1e-3)
    assert float(ctx.g_bottom[0]) - G_B == pytest.approx(20e-6, rel=1e-9)


def test_iron_reluctance_doubles_at_the_knee_and_enters_the_square_law():
    # At B = b_knee, mu_r(B) = mu_r / 2: the extra gap doubles to 40 µm.  i = b_knee 2 g_t / (MU_0 480).
    ir = E.IronReluctance(l_fe=0.08, mu_r=2000.0, b_knee=0.7)
    i_knee = 0.7 * 2.0 * G_T / (4e-7 * math.pi * TURNS)
    f, ctx = one_row((ir,), i_top=i_knee)
    assert float(ctx.g_top[0]) - G_T == pytest.approx(40e-6, rel=1e-9)
    e_b = 0.08 / (2.0 * 2000.0 / (1.0 + (b_of(IB, G_B) / 0.7) ** 4))
    assert f == pytest.approx(K * i_knee**2 / (G_T + 40e-6) ** 2 - K * IB**2 / (G_B + e_b) ** 2, rel=REL)


# --- fringing --------------------------------------------------------------------------------------------

def test_fringing_area_factor_uses_the_bearings_pole_width_and_length():
    c = 0.5
    w, length = PAPER_BEARING.pole_width, PAPER_BEARING.pole_area / PAPER_BEARING.pole_width
    assert w == 5e-3 and length == pytest.approx(10.84e-3, rel=2e-3)    # the docstring's 5 mm x 10.84 mm face

    def factor(g, w, length):
        # A_eff / A = (w + 2 c g)(l + 2 c g) / (w l)
        return (1.0 + 2.0 * c * g / w) * (1.0 + 2.0 * c * g / length)

    # literal value at g_t, l = 10.845944737479712 mm (python math): (1 + 772.28e-6/5e-3)(1 + 772.28e-6/l)
    assert factor(G_T, w, length) == pytest.approx(1.2366596135353192, rel=REL)
    f, ctx = one_row((E.Fringing(coefficient=c),))
    assert float(ctx.k_top[0]) / K == pytest.approx(factor(G_T, w, length), rel=REL)
    assert float(ctx.k_bottom[0]) / K == pytest.approx(factor(G_B, w, length), rel=REL)
    assert f == pytest.approx(K * factor(G_T, w, length) * IT**2 / G_T**2
                              - K * factor(G_B, w, length) * IB**2 / G_B**2, rel=REL)
    # another face with the same area: a square 7.36 mm pole fringes less in width, more in length
    square = PAPER_BEARING.with_(pole_width=math.sqrt(PAPER_BEARING.pole_area))
    _, ctx2 = one_row((E.Fringing(coefficient=c),), bearing=square)
    side = math.sqrt(PAPER_BEARING.pole_area)
    assert float(ctx2.k_top[0]) / K == pytest.approx(factor(G_T, side, side), rel=REL)
    assert abs(float(ctx2.k_top[0]) - float(ctx.k_top[0])) > 1e-3 * K


def test_fringing_grows_with_the_gap():
    fr = E.Fringing(coefficient=0.8)
    a = [float(fr.area_factor(g, 0, PAPER_BEARING)) for g in (200e-6, 500e-6, 1000e-6)]
    assert a[0] < a[1] < a[2] and float(fr.area_factor(0.0, 0, PAPER_BEARING)) == 1.0


# --- leakage ---------------------------------------------------------------------------------------------

def test_leakage_factor_hand_computed():
    lk = E.Leakage(sigma0=0.1, sigma1=0.03)
    # B = 1 T: (1 - 0.1 - 0.03 tanh(1))^2 = 0.769395938670936 (python math)
    assert float(lk.factor(1.0, 0)) == pytest.approx((1 - 0.1 - 0.03 * math.tanh(1.0)) ** 2, rel=REL)
    assert float(lk.factor(1.0, 0)) == pytest.approx(0.769395938670936, rel=1e-9)
    # B = 0: only the constant part, (1 - 0.1)^2 = 0.81
    assert float(lk.factor(0.0, 0)) == pytest.approx(0.81, rel=REL)
    f, ctx = one_row((lk,))

    def fac(b):
        return (1.0 - 0.1 - 0.03 * math.tanh(b**2)) ** 2

    assert float(ctx.k_top[0]) / K == pytest.approx(fac(b_of(IT, G_T)), rel=REL)
    assert f == pytest.approx(K * fac(b_of(IT, G_T)) * IT**2 / G_T**2 - K * fac(b_of(IB, G_B)) * IB**2 / G_B**2,
                              rel=REL)


# --- sensor effects --------------------------------------------------------------------------------------

SENSORS = [
    E.CurrentOffset(top=jnp.asarray([0.005, -0.012]), bottom=jnp.asarray([-0.004, 0.009])),
    E.CurrentGain(mismatch=jnp.asarray([0.02, -0.01])),
    E.PositionGain(gain_error=jnp.asarray([0.03, -0.015])),
]


@pytest.mark.parametrize("effect", SENSORS, ids=lambda e: e.name)
def test_sense_and_unsense_are_inverses(effect):
    rng = np.random.default_rng(4)
    axis = jnp.asarray([0, 1, 0, 1, 1])
    phys = [jnp.asarray(rng.uniform(0.5, 2.5, 5)), jnp.asarray(rng.uniform(0.5, 2.5, 5)),
            jnp.asarray(rng.uniform(-40e-6, 40e-6, 5)), jnp.asarray(rng.uniform(-40e-6, 40e-6, 5))]
    back = effect.unsense(axis, *effect.sense(axis, *phys))
    again = effect.sense(axis, *effect.unsense(axis, *phys))
    for a, b, c in zip(phys, back, again):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=REL, atol=1e-18)
        np.testing.assert_allclose(np.asarray(c), np.asarray(a), rtol=REL, atol=1e-18)
    # and it is not the identity: the effect changes what the sensors report
    assert any(not np.allclose(np.asarray(s), np.asarray(a), rtol=1e-6, atol=0)
               for s, a in zip(effect.sense(axis, *phys), phys))


def test_sensor_laws_hand_computed():
    ax = jnp.asarray([0, 1])
    one, two = jnp.asarray([1.5, 1.5]), jnp.asarray([1.2, 1.2])
    x, y = jnp.asarray([10e-6, 10e-6]), jnp.asarray([-20e-6, -20e-6])
    it, ib, _, _ = SENSORS[0].sense(ax, one, two, x, y)          # reading = physical + offset of the axis
    np.testing.assert_allclose(np.asarray(it), [1.505, 1.488], rtol=REL)
    np.testing.assert_allclose(np.asarray(ib), [1.196, 1.209], rtol=REL)
    it, ib, _, _ = SENSORS[1].sense(ax, one, two, x, y)          # top x (1 + m/2), bottom x (1 - m/2)
    np.testing.assert_allclose(np.asarray(it), [1.5 * 1.01, 1.5 * 0.995], rtol=REL)
    np.testing.assert_allclose(np.asarray(ib), [1.2 * 0.99, 1.2 * 1.005], rtol=REL)
    _, _, xs, ys = SENSORS[2].sense(ax, one, two, x, y)          # own axis' gain on x, the other axis' on y
    np.testing.assert_allclose(np.asarray(xs), [10e-6 * 1.03, 10e-6 * 0.985], rtol=REL)
    np.testing.assert_allclose(np.asarray(ys), [-20e-6 * 0.985, -20e-6 * 1.03], rtol=REL)


@pytest.mark.parametrize("effect", SENSORS, ids=lambda e: e.name)
def test_model_reads_sensor_values_back_to_physics(effect):
    # The force of sensed readings under the effect equals the ideal force of the physical readings.
    ax = jnp.asarray([0])
    sensed = effect.sense(ax, jnp.asarray([IT]), jnp.asarray([IB]), jnp.asarray([X]), jnp.asarray([5e-6]))
    f, _ = one_row((effect,), i_top=float(sensed[0][0]), i_bottom=float(sensed[1][0]), x=float(sensed[2][0]),
                   y=float(sensed[3][0]))
    assert f == pytest.approx(float(ideal_force(G0, X0, K, IT, IB, X)), rel=REL)
    # physical=True (the rig's view) skips the sensor stage
    f_phys, _ = one_row((effect,), physical=True)
    assert f_phys == pytest.approx(float(ideal_force(G0, X0, K, IT, IB, X)), rel=REL)


# --- cross coupling --------------------------------------------------------------------------------------

@pytest.mark.parametrize("angle_deg", [22.5, 30.0])
def test_cross_coupling_geometry_uses_the_bearings_pole_angle(angle_deg):
    # Rotor centred on its own axis (x0 + x = 0: g_t = g_b = g0), other axis at y' = 5 + 15 = 20 µm.
    # Each horseshoe's force grows by ((1 - a)^-2 + (1 + a)^-2) / 2, a = y' sin(alpha) / g0:
    # 22.5° -> a = 0.009567085809127244, 30° -> a = 0.0125 (python math).
    bearing = PAPER_BEARING.with_(pole_angle=math.radians(angle_deg))
    a = 20e-6 * math.sin(math.radians(angle_deg)) / G0
    pair = 0.5 * ((1 - a) ** -2 + (1 + a) ** -2)
    ideal = K * (IT**2 - IB**2) / G0**2
    f, _ = one_row((E.CrossCoupling(kappa=0.0, geometric=1.0),), bearing=bearing, x0=-X, y=15e-6, x0_other=5e-6)
    assert f == pytest.approx(ideal * pair, rel=REL)
    assert pair - 1.0 > 2e-4        # the effect is visible at this tolerance (3 a^2 ~ 3e-4)


def test_cross_coupling_differs_between_pole_angles():
    # guards against a hard-coded 22.5°: the same geometry on a 30° bearing gives a larger force
    cc = (E.CrossCoupling(kappa=0.0, geometric=1.0),)
    f22, _ = one_row(cc, x0=-X, y=15e-6, x0_other=5e-6)
    f30, _ = one_row(cc, bearing=PAPER_BEARING.with_(pole_angle=math.radians(30.0)), x0=-X, y=15e-6, x0_other=5e-6)
    assert (f30 - f22) / f22 > 1e-4


def test_cross_coupling_stiffness_acts_on_the_other_axis_displacement():
    # geometric = 0 leaves only kappa y': F = F_ideal + 1500 N/m * (5 + 15) µm = F_ideal + 0.03 N
    f, _ = one_row((E.CrossCoupling(kappa=1500.0, geometric=0.0),), y=15e-6, x0_other=5e-6)
    assert f - float(ideal_force(G0, X0, K, IT, IB, X)) == pytest.approx(0.03, rel=1e-9)  # difference of ~15 N values


# --- hysteresis ------------------------------------------------------------------------------------------

def test_hysteresis_play_operator_sequence():
    # Dead band of half-width 10 mA, demagnetised start m = 0:
    #   i = 1.000 -> m = clip(0, 0.990, 1.010) = 0.990 (rising: lags by the width)
    #   i = 1.005 -> m = clip(0.990, 0.995, 1.015) = 0.995
    #   i = 1.000 -> m = clip(0.995, 0.990, 1.010) = 0.995 (inside the band: unchanged)
    #   i = 0.980 -> m = clip(0.995, 0.970, 0.990) = 0.990 (falling: leads by the width)
    h = E.Hysteresis(width=0.01)
    m, out = 0.0, []
    for i in (1.0, 1.005, 1.0, 0.98):
        m = float(h.play(i, m, 0))
        out.append(m)
    np.testing.assert_allclose(out, [0.99, 0.995, 0.995, 0.99], rtol=REL)


def test_hysteresis_force_depends_on_the_approach_direction():
    h = E.Hysteresis(width=0.01)
    # no history: m = i - width * direction
    rising, _ = one_row((h,), dir_top=1.0, dir_bottom=0.0)
    falling, _ = one_row((h,), dir_top=-1.0, dir_bottom=0.0)
    assert rising == pytest.approx(K * 1.99**2 / G_T**2 - K * IB**2 / G_B**2, rel=REL)
    # the difference is k ((i + h)^2 - (i - h)^2) / g_t^2 = 4 k i h / g_t^2
    assert falling - rising == pytest.approx(4 * K * IT * 0.01 / G_T**2, rel=1e-9)
    # with history (the rig): top from 1.5 A rises to 1.99 A, bottom at 1.0 A stays inside its band
    f, ctx = one_row((h,), m_prev_top=jnp.asarray([1.5]), m_prev_bottom=jnp.asarray([1.0]), physical=True)
    assert float(ctx.m_top[0]) == pytest.approx(1.99, rel=REL) and float(ctx.m_bottom[0]) == 1.0
    assert f == pytest.approx(rising, rel=REL)


# --- thermal drift ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("temp", [32.0, 42.0, 12.0])
def test_thermal_drift_shifts_gap_and_origin_linearly(temp):
    td = E.ThermalDrift(dg_dT=0.2e-6, dx0_dT=jnp.asarray([1e-6, -2e-6]), ref_C=22.0)
    dt = temp - 22.0
    f, ctx = one_row((td,), temperature=temp, x0_other=7e-6)
    assert float(ctx.g0[0]) == pytest.approx(G0 + 0.2e-6 * dt, rel=REL)
    assert float(ctx.x0[0]) == pytest.approx(X0 + 1e-6 * dt, rel=REL)
    assert float(ctx.y0[0]) == pytest.approx(7e-6 - 2e-6 * dt, rel=REL)      # the other axis' coefficient
    assert f == pytest.approx(float(ideal_force(G0 + 0.2e-6 * dt, X0 + 1e-6 * dt, K, IT, IB, X)), rel=REL)
    # the w axis uses its own coefficient
    _, ctx_w = one_row((td,), axis=1, temperature=temp)
    assert float(ctx_w.x0[0]) == pytest.approx(X0 - 2e-6 * dt, rel=REL)


def test_thermal_drift_without_temperature_is_at_the_reference_and_heats_exponentially():
    td = E.ThermalDrift(dg_dT=0.2e-6, dx0_dT=1e-6, heating_K=15.0, tau_s=900.0)
    f, ctx = one_row((td,))          # temperature NaN (unknown): taken at ref_C
    assert float(ctx.g0[0]) == G0 and f == pytest.approx(float(ideal_force(G0, X0, K, IT, IB, X)), rel=REL)
    # T(t) = ambient + heating (1 - exp(-t / tau)): at t = tau, 22 + 15 (1 - 1/e) = 31.48180833... °C
    assert float(td.temperature(900.0, 22.0)) == pytest.approx(22.0 + 15.0 * (1.0 - math.exp(-1.0)), rel=REL)
    assert float(td.temperature(0.0, 22.0)) == 22.0


# --- names -----------------------------------------------------------------------------------------------

CONTRACT_NAMES = ("saturation", "iron_reluctance", "fringing", "leakage", "current_offset", "current_gain",
                  "position_gain", "cross_coupling", "hysteresis", "thermal_drift")


def test_every_contract_name_is_an_effect():
    assert set(CONTRACT_NAMES) <= set(E.EFFECTS)
    for name in CONTRACT_NAMES:
        assert E.effect_by_name(name).name == name


def test_effect_by_name_errors_list_the_valid_names():
    with pytest.raises(ValueError, match="unknown effect 'saturaton'") as exc:
        E.effect_by_name("saturaton")
    for name in CONTRACT_NAMES:
        assert name in str(exc.value)
    with pytest.raises(ValueError, match="b_sat") as exc:
        E.effect_by_name("saturation", bsat=1.1)
    assert "bsat" in str(exc.value) and "sharpness" in str(exc.value)
    sat = E.effect_by_name("saturation", b_sat=[1.1, 1.2])
    assert float(sat.factor(1.2, 1)) == pytest.approx(2 ** (-2 / 5.0), rel=REL)   # default sharpness 5
