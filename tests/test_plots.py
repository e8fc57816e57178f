"""Figures are functions of results (STYLE.md section 9): each plotting function, called on a small
hand-made object, draws the data it is given, with labels and units, on its own Axes.
"""

import io
import os
import subprocess
import sys
import textwrap
import types

import matplotlib
import numpy as np
import pandas as pd
import pytest

from ambfit.estimation.conditioning import SolutionSpace
from ambfit.faces import plots
from ambfit.studies.paper import QUANTITIES, load_table

matplotlib.use("Agg")   # the test session's own choice (headless); the library must not make it
import matplotlib.pyplot as plt  # noqa: E402

# Plotted coordinates are the inputs times 1e6 (m -> µm) or unchanged: 1e-9 relative is round-off of that
# product; a wrong unit is a factor 1e3 or more.
REL = 1e-9


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


# --- small inputs -----------------------------------------------------------------------------------------

G_STAR, X_STAR = 775e-6, 33e-6          # grid minimum [m]


def small_space(axis="v"):
    """A quadratic χ² bowl around (775 µm, 33 µm): sd 10 µm in gap, 2 µm in origin."""
    gap = np.linspace(745e-6, 805e-6, 31)
    origin = np.linspace(27e-6, 39e-6, 25)
    chi2 = ((gap[:, None] - G_STAR) / 10e-6) ** 2 + ((origin[None, :] - X_STAR) / 2e-6) ** 2 + 12.0
    return SolutionSpace(axis=axis, gap=gap, origin=origin, chi2=chi2, rms=np.sqrt(chi2) * 1e-3, n_rows=40)


def small_result():
    """The least-squares point and covariance (names, values, cov) of a fit, nothing else."""
    return types.SimpleNamespace(names=["g_v0", "v0"], values=np.array([776e-6, 32e-6]),
                                 cov=np.diag([(10e-6) ** 2, (2e-6) ** 2]))


RANKING = {"verdict": "saturation", "shrink": 0.87, "heldout_excess_before": 6.5,
           "ranking": [{"effect": "saturation", "heldout_excess_after": 0.8},
                       {"effect": "fringing", "heldout_excess_after": 4.0},
                       {"effect": "leakage", "heldout_excess_after": 5.5}]}

DESIGNS = pd.DataFrame({"design": ["paper", "rich", "one point"], "crlb_gap_um": [3.0, 0.5, np.inf],
                        "condition": [1e3, 50.0, np.inf], "loads": ["known", "known", ""]})

SPREAD = pd.DataFrame({"table": [2, 1], "quantity": ["v0_um", "g_v0_um"], "role": ["calibration", "prediction"],
                       "paper_sd": [4.0, 20.0], "rig_median": [3.0, 18.0], "rig_lo": [2.0, 12.0],
                       "rig_hi": [4.5, 30.0]})


def small_search(iterations=3):
    rows = []
    for it in range(1, iterations + 1):
        for v, w in ((10.0 * it, -5.0), (-10.0 * it, 5.0)):
            rows += [{"axis": "v", "iteration": it, "v_um": v, "w_um": w},
                     {"axis": "w", "iteration": it, "v_um": v, "w_um": w}]
    centers = np.array([[-30e-6 + it * 1e-6, 10e-6] for it in range(iterations)])
    return types.SimpleNamespace(data=pd.DataFrame(rows), centers=centers,
                                 truth={"params": {"0": {"v0_um": 33.3, "w0_um": -11.3}}})


def small_reproduction(iterations=10, replicates=5):
    rng = np.random.default_rng(0)
    run = np.stack([np.full(iterations, v) for v in (33.0, -11.0, 775.0, 763.0)], axis=-1)[None]  # [row, it, q]
    reps = run[None] + rng.normal(0, 1.0, (replicates, 1, iterations, 4))
    return types.SimpleNamespace(table2_index=0, run=run, replicates=reps)


def small_diagnosis():
    op = pd.DataFrame({"b_top_T": [0.5, 0.7, 0.9, 1.1]})
    return types.SimpleNamespace(most_structured_variable="b_top_T", operating=op,
                                 residuals_before=np.array([0.1, 1.0, 3.0, 8.0]),
                                 residuals_after=np.array([0.2, -0.3, 0.1, 0.4]))


def labels(ax):
    leg = ax.get_legend()
    return [t.get_text() for t in leg.get_texts()] if leg else []


def line(ax, label):
    return next(ln for ln in ax.lines if ln.get_label() == label)


# --- each function: labels, units, data ---------------------------------------------------------------------

def test_residual_map_draws_before_and_after_against_the_variable():
    x, zb, za = [0.5, 0.7, 0.9], [0.1, 2.5, 7.0], [0.1, -0.2, 0.3]
    ax = plots.plot_residual_map(x, zb, za, label="b_top_T")
    assert ax.get_xlabel() == "b_top_T" and ax.get_ylabel() == "standardized residual z"
    np.testing.assert_array_equal(line(ax, "ideal model").get_xydata(), np.column_stack([x, zb]))
    np.testing.assert_array_equal(line(ax, "with the verdict effect").get_ydata(), za)
    assert "±2 noise units" in labels(ax)
    only = plots.plot_residual_map(x, zb)
    assert [ln.get_label() for ln in only.lines] == ["ideal model"]


def test_diagnosis_residuals_use_the_most_structured_variable():
    d = small_diagnosis()
    ax = plots.plot_diagnosis_residuals(d)
    assert ax.get_xlabel() == "top-coil flux density [T] (ideal circuit)"
    np.testing.assert_array_equal(line(ax, "ideal model").get_xdata(), d.operating["b_top_T"])
    np.testing.assert_array_equal(line(ax, "with the verdict effect").get_ydata(), d.residuals_after)


def test_discrepancy_is_drawn_against_flux_density_per_axis_in_newtons():
    op = pd.DataFrame({"b_top_T": [0.5, 0.7, 0.9, 1.1], "axis": ["v", "v", "w", "w"]})
    fit = types.SimpleNamespace(row_correction_n=np.array([0.01, 0.02, -0.03, 0.04]),
                                row_noise_n=np.array([0.1, 0.1, 0.2, 0.2]))
    d = types.SimpleNamespace(operating=op, baseline=types.SimpleNamespace(residuals=np.array([1.0, 2.0, 3.0, 4.0])),
                              ceiling=types.SimpleNamespace(fit=fit, host=types.SimpleNamespace(model="ideal")))
    ax = plots.plot_discrepancy(d)
    assert ax.get_xlabel().startswith("top-coil flux density [T]") and ax.get_ylabel() == "force [N]"
    got = {c.get_label(): c.get_offsets() for c in ax.collections}
    np.testing.assert_allclose(got["v: correction to ideal"], [[0.5, 0.01], [0.7, 0.02]])
    np.testing.assert_allclose(got["w: correction to ideal"], [[0.9, -0.03], [1.1, 0.04]])
    # the ideal law's misfit in newtons: load - force = -z * s
    np.testing.assert_allclose(got["w: ideal law's misfit (load - force)"], [[0.9, -0.6], [1.1, -0.8]])
    with pytest.raises(ValueError, match="no discrepancy"):
        plots.plot_discrepancy(types.SimpleNamespace(ceiling=None))


def test_ranking_has_one_bar_per_candidate_and_the_baseline():
    ax = plots.plot_ranking(RANKING)
    bars = ax.patches
    assert len(bars) == len(RANKING["ranking"]) == 3
    np.testing.assert_allclose([b.get_width() for b in bars], [0.8, 4.0, 5.5], rtol=REL)
    assert [t.get_text() for t in ax.get_yticklabels()] == ["saturation", "fringing", "leakage"]
    green = matplotlib.colors.to_rgba("tab:green")
    assert [b.get_facecolor() == green for b in bars] == [True, False, False]      # the verdict
    base = line(ax, "ideal model")
    assert tuple(base.get_xdata()) == (6.5, 6.5)                                    # excess before
    assert ax.get_xlabel() == "held-out excess residual [noise units]"
    assert ax.get_title() == "verdict: saturation, shrink 0.87"
    # a Diagnosis-like object is read through its contract record
    obj = types.SimpleNamespace(to_json=lambda: RANKING)
    assert len(plots.plot_ranking(obj).patches) == 3


def test_ranking_on_the_noise_floor_draws_the_residuals_not_empty_bars():
    """Issue 24: with the verdict none every excess is 0 and the chart was an empty axes."""
    floor = {"verdict": "none", "shrink": 0.0, "heldout_excess_before": 0.0,
             "ranking": [{"effect": e, "heldout_excess_after": 0.0, "heldout_rms_before": 0.97,
                          "heldout_rms_after": r} for e, r in (("fringing", 0.95), ("leakage", 0.99))]}
    ax = plots.plot_ranking(floor)
    widths = [b.get_width() for b in ax.patches]
    np.testing.assert_allclose(widths, [0.95, 0.99], rtol=REL)        # something to see in every bar
    assert tuple(line(ax, "noise floor: RMS 1 if the model were right").get_xdata()) == (1.0, 1.0)
    assert tuple(line(ax, "ideal model").get_xdata()) == (0.97, 0.97)
    assert ax.get_xlabel() == "held-out RMS standardized residual [noise units]"
    assert "noise floor" in ax.get_title()
    none = plots.plot_ranking(dict(floor, ranking=[]))
    assert [t.get_text() for t in none.texts] == ["no candidate effect was scored"]


def test_design_comparison_marks_unbounded_designs():
    ax = plots.plot_design_comparison(DESIGNS)
    bars = ax.patches
    assert len(bars) == len(DESIGNS)
    # an unbounded design is drawn grey at 100 x the largest finite bound
    np.testing.assert_allclose([b.get_width() for b in bars], [3.0, 0.5, 300.0], rtol=REL)
    assert bars[2].get_facecolor() == matplotlib.colors.to_rgba("tab:gray")
    assert [t.get_text() for t in ax.get_yticklabels()] == ["paper (known)", "rich (known)", "one point"]
    assert ax.get_xscale() == "log" and ax.get_xlabel().endswith("[µm] (grey: unbounded)")
    texts = [t.get_text() for t in ax.texts]
    assert texts[0] == "  cond 1e+03" and texts[2].endswith("not identifiable")


def test_solution_space_is_in_micrometres_with_ellipses_of_the_covariance():
    space, res = small_space(), small_result()
    draws = np.array([[770e-6, 30e-6], [780e-6, 35e-6]])          # (gap, origin) [m]
    ax = plots.plot_solution_space(space, result=res, samples=draws)
    assert ax.get_xlabel() == "v-axis origin [µm]" and ax.get_ylabel() == "v-axis effective gap [µm]"
    assert ax.get_title() == "Solution space, axis v (40 readings)"
    # the map: cells centred on the grid in µm, coloured by log10(1 + Δχ²)
    mesh = ax.collections[0]
    edges = mesh.get_coordinates()
    np.testing.assert_allclose((edges[0, 1:, 0] + edges[0, :-1, 0]) / 2, space.origin * 1e6, rtol=REL)
    np.testing.assert_allclose((edges[1:, 0, 1] + edges[:-1, 0, 1]) / 2, space.gap * 1e6, rtol=REL)
    np.testing.assert_allclose(mesh.get_array(), np.log10(1.0 + space.chi2 - 12.0), rtol=REL, atol=1e-12)
    np.testing.assert_allclose(line(ax, "grid minimum").get_xydata()[0], [33.0, 775.0], rtol=REL)
    np.testing.assert_allclose(line(ax, "posterior draws").get_xydata(), [[30.0, 770.0], [35.0, 780.0]], rtol=REL)
    ls_point = line(ax, "least squares (68/95 % ellipses)").get_xydata()[0]
    np.testing.assert_allclose(ls_point, [32.0, 776.0], rtol=REL)
    # 68 % ellipse (Δχ² = 2.3 in 2-D): half-widths sqrt(2.3) x (2 µm origin, 10 µm gap) about the estimate
    ell = next(ln for ln in ax.lines if len(ln.get_xdata()) == 200 and ln.get_linestyle() == "-")
    xy = ell.get_xydata()
    np.testing.assert_allclose(np.ptp(xy, axis=0) / 2, [np.sqrt(2.3) * 2.0, np.sqrt(2.3) * 10.0], rtol=1e-3)
    # (1e-3: the ellipse is sampled at 200 angles, the extreme is missed by at most 1 - cos(pi/200) ~ 1e-4)
    # weakest direction: along the gap, 6 sd = ±60 µm
    weak = line(ax, "weakest Fisher direction").get_xydata()
    np.testing.assert_allclose(np.abs(weak[1] - weak[0]), [0.0, 120.0], atol=1e-9)
    cbar = [a for a in ax.figure.axes if a is not ax]
    assert len(cbar) == 1 and cbar[0].get_ylabel() == "log10(1 + Δχ²)"


def test_fig2_surface_has_the_surface_and_the_map_from_above():
    fig = plots.plot_fig2_surface(small_space())
    ax3, ax = fig.axes
    assert ax3.name == "3d" and ax3.get_zlabel() == "log10 RMS force error [mN]"
    assert ax3.get_xlabel() == "v-axis effective gap [µm]" and ax3.get_ylabel() == "v-axis origin [µm]"
    assert ax.get_xlabel() == "v-axis origin [µm]" and "Δχ² < 11.8" in ax.get_title()
    np.testing.assert_allclose(ax.lines[0].get_xydata()[0], [33.0, 775.0], rtol=REL)


def test_fig3_positions_one_colour_per_iteration_and_the_clearance():
    s = small_search(iterations=3)
    ax = plots.plot_fig3_positions(s, backup_clearance=60e-6)
    assert ax.get_xlabel() == "v position [µm]" and ax.get_ylabel() == "w position [µm]"
    readings = [ln for ln in ax.lines if ln.get_marker() == "o"]
    assert len(readings) == 3
    np.testing.assert_array_equal(readings[2].get_xydata(), [[30.0, -5.0], [-30.0, 5.0]])
    circle = line(ax, "back-up bearing clearance (60 µm)").get_xydata()
    np.testing.assert_allclose(np.hypot(circle[:, 0], circle[:, 1]), 60.0, rtol=REL)
    star = line(ax, "true effective origin (−v0, −w0)").get_xydata()[0]
    np.testing.assert_allclose(star, [-33.3, 11.3], rtol=REL)
    centres = [ln for ln in ax.lines if ln.get_marker() == "x"]
    np.testing.assert_allclose(centres[0].get_xydata()[0], [-30.0, 10.0], rtol=REL)


def test_fig5_iterations_shows_paper_and_rig_per_quantity():
    rep = small_reproduction()
    fig = plots.plot_fig5_iterations(rep)
    top, bottom = fig.axes
    assert top.get_ylabel() == "rotor origin [µm]" and bottom.get_ylabel() == "effective gap [µm]"
    assert bottom.get_xlabel() == "iteration"
    t2 = load_table(2)
    np.testing.assert_allclose(line(top, "v0 paper").get_ydata(), t2[QUANTITIES[0]], rtol=REL)
    np.testing.assert_allclose(line(bottom, "g_w0 ambfit rig").get_ydata(), rep.run[0, :, 3], rtol=REL)
    assert set(labels(bottom)) >= {"g_v0 rig 90 % band", "g_v0 ambfit rig", "g_v0 paper"}


def test_spread_compares_paper_sd_with_the_rig_range():
    ax = plots.plot_spread(SPREAD)
    assert ax.get_xscale() == "log" and ax.get_xlabel() == "standard deviation [µm]"
    assert [t.get_text() for t in ax.get_yticklabels()] == ["T2 v0 (cal.)", "T1 g_v0 (pred.)"]
    np.testing.assert_array_equal(line(ax, "paper").get_xdata(), [4.0, 20.0])
    assert "rig: median and 5-95 % of the sd" in labels(ax)


def small_posterior():
    """A posterior DataTree in the units a Posterior writes (µm, N·m²/A²): g_v0 and v0 97 % correlated (the Fig. 2
    valley), k_v independent; 2 chains x 50 draws."""
    import arviz as az

    rng = np.random.default_rng(0)
    g = rng.normal(775.0, 1.0, (2, 50))
    v = 33.0 + 0.3 * (g - 775.0) + rng.normal(0.0, 0.075, (2, 50))
    k = rng.normal(3.45e-6, 1.5e-8, (2, 50))
    return types.SimpleNamespace(datatree=az.from_dict({"posterior": {"g_v0": g, "v0": v, "k_v": k}})), (g, v, k)


def pair_result():
    """Least squares' point and covariance (SI) for g_v0, v0, k_v, with a nuisance load first."""
    names = ["load[x]", "g_v0", "v0", "k_v"]
    values = np.array([6.9, 774.6e-6, 32.9e-6, 3.44e-6])
    sd = np.array([0.1, 1.0e-6, 0.3e-6, 1.5e-8])
    corr = np.eye(4)
    corr[1, 2] = corr[2, 1] = 0.9
    return types.SimpleNamespace(names=names, values=values, cov=corr * np.outer(sd, sd))


def panel(fig, n, i, j):
    return fig.axes[i * n + j]


def test_pair_plot_shows_the_draws_in_display_units_with_units_in_the_labels():
    post, (g, v, k) = small_posterior()
    fig = plots.plot_pair(post, var_names=["g_v0", "v0"])
    assert isinstance(fig, matplotlib.figure.Figure)
    assert len(fig.axes) == 4                                            # a 2 x 2 matrix, nothing else
    cross = panel(fig, 2, 1, 0)
    assert cross.get_xlabel() == "g_v0 [µm]" and cross.get_ylabel() == "v0 [µm]"
    pts = np.concatenate([c.get_offsets() for c in cross.collections])   # one scatter per chain
    np.testing.assert_allclose(pts, np.column_stack([g.ravel(), v.ravel()]), rtol=REL)
    # all variables present by default; k in 10⁻⁶ N·m²/A², so its ticks read 3.45, not 3.45e-06
    fig = plots.plot_pair(post)
    assert len(fig.axes) == 9
    bottom = [panel(fig, 3, 2, j).get_xlabel() for j in range(3)]
    assert bottom == ["g_v0 [µm]", "v0 [µm]", "k_v [10⁻⁶ N·m²/A²]"]
    kv = panel(fig, 3, 2, 0)
    np.testing.assert_allclose(np.concatenate([c.get_offsets()[:, 1] for c in kv.collections]), k.ravel() * 1e6,
                               rtol=REL)
    lo, hi = panel(fig, 3, 2, 2).get_xlim()
    assert 3.3 < lo < hi < 3.6


def test_pair_plot_diagonal_has_no_density_ticks_and_states_mean_and_sd():
    post, (g, v, k) = small_posterior()
    fig = plots.plot_pair(post)
    for j in range(3):
        assert list(panel(fig, 3, j, j).get_yticks()) == []
    title = panel(fig, 3, 0, 0).get_title()
    assert title.startswith("g_v0 = ") and title.endswith(" µm")
    from ambfit.estimation.units import pm

    assert title == f"g_v0 = {pm(np.mean(g), np.std(g))} µm"


def test_pair_plot_upper_triangle_gives_the_correlation_of_the_valley():
    post, (g, v, k) = small_posterior()
    res = pair_result()
    fig = plots.plot_pair(post, result=res)
    texts = [t.get_text() for t in panel(fig, 3, 0, 1).texts]        # above the (g_v0, v0) panel
    rho = np.corrcoef(g.ravel(), v.ravel())[0, 1]
    assert rho > 0.9 and texts[0] == f"ρ = {rho:+.2f}"
    assert texts[1] == "least squares +0.90"
    # shaded by |ρ|: the valley's panel is much more opaque than the independent one's
    assert panel(fig, 3, 0, 1).get_facecolor()[3] > 0.5 > 0.2 > panel(fig, 3, 0, 2).get_facecolor()[3]


def test_pair_plot_marks_the_least_squares_estimate_on_every_panel_in_display_units():
    post, _ = small_posterior()
    res = pair_result()
    fig = plots.plot_pair(post, result=res)
    mu = {"g_v0": 774.6, "v0": 32.9, "k_v": 3.44}                      # µm, µm, 10⁻⁶ N·m²/A²
    names = ["g_v0", "v0", "k_v"]
    for i in range(3):
        diag = panel(fig, 3, i, i)
        np.testing.assert_allclose(line(diag, "least squares").get_xdata(), [mu[names[i]]] * 2, rtol=REL)
        for j in range(i):
            point = line(panel(fig, 3, i, j), "least squares").get_xydata()[0]
            np.testing.assert_allclose(point, [mu[names[j]], mu[names[i]]], rtol=REL)
    # the 68 % ellipse of (g_v0, v0): half-widths sqrt(2.3) x (1.0, 0.3) µm
    ell = next(ln for ln in panel(fig, 3, 1, 0).lines if ln.get_linestyle() == "-" and len(ln.get_xdata()) == 100)
    np.testing.assert_allclose(np.ptp(ell.get_xydata(), axis=0) / 2, np.sqrt(2.3) * np.array([1.0, 0.3]), rtol=2e-3)
    # (2e-3: the ellipse is sampled at 100 angles; its extreme is missed by at most 1 - cos(pi/100) ~ 5e-4)
    # without a result, nothing is marked
    bare = plots.plot_pair(post)
    assert not any(ln.get_label() == "least squares" for ax in bare.axes for ln in ax.lines)


def test_pair_plot_uses_the_given_figure_and_leaves_the_current_one_alone():
    post, _ = small_posterior()
    fig0 = plt.figure()
    mine = plt.figure()
    assert plots.plot_pair(post, fig=mine) is mine and not fig0.axes
    assert plots.plot_pair(post) is not fig0 and not fig0.axes


def test_save_writes_a_png_and_figure_of_finds_the_figure():
    ax = plots.plot_ranking(RANKING)
    assert plots.figure_of(ax) is ax.figure and plots.figure_of(ax.figure) is ax.figure
    buf = io.BytesIO()
    plots.save(ax, buf)
    assert buf.getvalue()[:8] == b"\x89PNG\r\n\x1a\n"


# --- no global state ---------------------------------------------------------------------------------------

CALLS = {
    "residual_map": lambda ax: plots.plot_residual_map([1, 2], [0.1, 0.2], label="x", ax=ax),
    "diagnosis_residuals": lambda ax: plots.plot_diagnosis_residuals(small_diagnosis(), ax=ax),
    "ranking": lambda ax: plots.plot_ranking(RANKING, ax=ax),
    "design_comparison": lambda ax: plots.plot_design_comparison(DESIGNS, ax=ax),
    "solution_space": lambda ax: plots.plot_solution_space(small_space(), result=small_result(), ax=ax),
    "fig3_positions": lambda ax: plots.plot_fig3_positions(small_search(), ax=ax),
    "spread": lambda ax: plots.plot_spread(SPREAD, ax=ax),
}


@pytest.mark.parametrize("name", CALLS)
def test_plots_draw_on_their_own_axes_not_the_callers_current_one(name):
    fig0, ax0 = plt.subplots()          # the caller's current figure and axes
    backend = matplotlib.get_backend()
    ax = CALLS[name](None)
    assert ax is not ax0 and ax.figure is not fig0
    assert not (ax0.lines or ax0.patches or ax0.collections or ax0.texts)
    assert plt.fignum_exists(fig0.number)                       # the caller's figure is left open
    mine_fig, mine = plt.subplots()
    assert CALLS[name](mine) is mine                            # a given Axes is used, nothing else is created
    assert len(mine_fig.axes) in (1, 2)                         # (2: the solution space's colour bar)
    assert matplotlib.get_backend().lower() == backend.lower()


@pytest.mark.parametrize("name", ["fig2_surface", "fig5_iterations"])
def test_figure_plots_use_the_given_figure(name):
    fig0 = plt.figure()
    call = {"fig2_surface": lambda fig: plots.plot_fig2_surface(small_space(), fig=fig),
            "fig5_iterations": lambda fig: plots.plot_fig5_iterations(small_reproduction(), fig=fig)}[name]
    mine = plt.figure()
    assert call(mine) is mine and len(mine.axes) == 2 and not fig0.axes
    assert call(None) is not fig0 and not fig0.axes


def _run_with_backend(code: str) -> str:
    """Run ``code`` in a fresh interpreter whose matplotlib backend is chosen by the caller (svg)."""
    env = {**os.environ, "MPLBACKEND": "svg"}
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


def test_importing_the_plots_does_not_switch_the_backend():
    out = _run_with_backend("""
        import matplotlib, matplotlib.pyplot as plt
        before = matplotlib.get_backend()
        import ambfit, ambfit.faces.plots
        print(before, matplotlib.get_backend())
    """)
    assert out == "svg svg"


def test_plotting_does_not_switch_the_callers_backend():
    out = _run_with_backend("""
        import matplotlib, matplotlib.pyplot as plt
        fig = plt.figure()
        from ambfit.faces import plots
        plots.plot_residual_map([1, 2], [0.1, 0.2], label="x")
        print(matplotlib.get_backend(), plt.fignum_exists(fig.number))
    """)
    assert out == "svg True"


def test_recommendation_shows_the_steps_inside_the_clearance_and_the_predicted_std():
    import pandas as pd

    from ambfit.estimation.design import Recommendation

    steps = pd.DataFrame({"v_set_um": [50.0, -50.0], "w_set_um": [0.0, 10.0], "bias_A": [1.2, 1.8],
                          "predicted_std_after": [1.2e-6, 1.0e-6]})
    rec = Recommendation(steps=steps, target="g_v0", std_now=1.4e-6, criterion="A", centre_um=(-33.0, 11.0),
                         radius_um=57.0)
    fig0 = plt.figure()
    fig = plots.plot_recommendation(rec, pd.DataFrame({"v_um": [20.0], "w_um": [20.0]}), clearance_um=60.0)
    assert fig is not fig0 and not fig0.axes
    where, std = fig.axes[0], fig.axes[1]
    pts = where.collections[1].get_offsets()
    np.testing.assert_array_equal(pts, [[50.0, 0.0], [-50.0, 10.0]])
    np.testing.assert_allclose(where.collections[1].get_array(), [1.2, 1.8])       # coloured by bias
    # the clearance and the allowed radius about the estimated bearing centre, not the sensor origin
    lines = {ln.get_label(): ln.get_xydata() for ln in where.lines}
    np.testing.assert_allclose(lines["estimated bearing centre"], [[-33.0, 11.0]])
    for label, radius in (("back-up clearance about it", 60.0), ("allowed (less the origin's uncertainty)", 57.0)):
        xy = lines[label]
        np.testing.assert_allclose(np.hypot(xy[:, 0] + 33.0, xy[:, 1] - 11.0), radius)
    np.testing.assert_allclose(std.lines[0].get_ydata(), [1.4, 1.2, 1.0])          # µm, now then after each step
    assert "µm" in std.get_ylabel()
