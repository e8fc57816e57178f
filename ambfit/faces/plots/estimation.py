"""Figures of an identification: the solution space (the paper's Fig. 2 as a map), the posterior's pair plot,
designs compared by their Cramér-Rao bound, and a design recommendation."""

from __future__ import annotations

import numpy as np

from ambfit.estimation.units import FORCE_CONSTANTS, GEOMETRY
from ambfit.faces.plots.figures import _axes


def plot_solution_space(space, *, result=None, samples=None, ax=None, levels=(2.3, 6.2, 11.8, 50, 200, 1000),
                        label_contours: bool = False):
    """The paper's Fig. 2 as a map: Δχ² over (origin, gap) in µm with white contours at ``levels`` (each labelled
    with its Δχ² when ``label_contours``), the least-squares point, its 68 and 95 % ellipses, posterior draws and
    the weakest Fisher direction if given.

    ``space``: :class:`ambfit.estimation.conditioning.SolutionSpace`; ``result``: a
    :class:`ambfit.FitResult`; ``samples``: array[n, 2] of (gap, origin) draws [m].
    """
    import matplotlib.colors as mcolors

    ax = _axes(ax)
    d = space.delta_chi2()
    x, y = space.origin * 1e6, space.gap * 1e6
    im = ax.pcolormesh(x, y, np.log10(1.0 + d), shading="auto", cmap="viridis",
                       norm=mcolors.Normalize(vmin=0, vmax=np.nanpercentile(np.log10(1.0 + d), 99)))
    ax.figure.colorbar(im, ax=ax, label="log10(1 + Δχ²)")
    contours = ax.contour(x, y, d, levels=list(levels), colors="w", linewidths=0.6)
    if label_contours:
        ax.clabel(contours, fmt=lambda v: f"{v:.3g}", fontsize=7)
    g_min, x_min = space.minimum
    ax.plot(x_min * 1e6, g_min * 1e6, "w+", ms=10, label="grid minimum")
    if samples is not None and len(samples):
        s = np.asarray(samples)
        ax.plot(s[:, 1] * 1e6, s[:, 0] * 1e6, ".", color="tab:orange", ms=1.5, alpha=0.4, label="posterior draws")
    if result is not None:
        a = space.axis
        i, j = result.names.index(f"g_{a}0"), result.names.index(f"{a}0")
        mu = np.array([result.values[j], result.values[i]]) * 1e6
        cov = result.cov[np.ix_([j, i], [j, i])] * 1e12
        w, v = np.linalg.eigh(cov)
        t = np.linspace(0, 2 * np.pi, 200)
        for nsig, style in ((np.sqrt(2.3), "-"), (np.sqrt(6.2), "--")):
            ell = (v @ (np.sqrt(w)[:, None] * np.array([np.cos(t), np.sin(t)]))) * nsig
            ax.plot(mu[0] + ell[0], mu[1] + ell[1], "r" + style, lw=1)
        ax.plot(*mu, "r.", label="least squares (68/95 % ellipses)")
        long = v[:, -1] * np.sqrt(w[-1]) * 6
        ax.plot([mu[0] - long[0], mu[0] + long[0]], [mu[1] - long[1], mu[1] + long[1]], "r:", lw=1.5,
                label="weakest Fisher direction")
    ax.set_xlim(x.min(), x.max())          # the map's extent: the Fisher line must not widen it
    ax.set_ylim(y.min(), y.max())
    ax.set_xlabel(f"{space.axis}-axis origin [µm]")
    ax.set_ylabel(f"{space.axis}-axis effective gap [µm]")
    ax.set_title(f"Solution space, axis {space.axis} ({space.n_rows} readings)")
    ax.legend(loc="upper right", fontsize=7)
    return ax


PAIR_UNITS = {n: ("µm", 1e6) for n in GEOMETRY} | {n: ("10⁻⁶ N·m²/A²", 1e6) for n in FORCE_CONSTANTS}
"""Display unit and factor from SI of each pair-plot variable (k in 10⁻⁶ N·m²/A², so its ticks read 3.45, not 3.45e-06)."""


def pair_label(name: str) -> str:
    """``"g_v0 [µm]"``: a variable's axis label with its display unit."""
    return f"{name} [{PAIR_UNITS[name][0]}]" if name in PAIR_UNITS else name


def plot_pair(sampling, var_names=None, *, result=None, fig=None, max_points: int = 4000):
    """Pair plot of the posterior of gap, origin and k in display units (µm, 10⁻⁶ N·m²/A²); returns the Figure.

    Diagonal: each marginal (histogram; its height is relative, so no density axis) with the posterior mean ± sd
    in the title.  Lower triangle: the draws (at most ``max_points`` per chain, evenly thinned; the paper's Fig. 2
    valley shows as a narrow diagonal cloud when gap and origin are strongly correlated).  Upper triangle: the
    posterior correlation coefficient ρ, the panel shaded by it (red positive, blue negative), and least squares'
    ρ below it.  With ``result`` (a :class:`ambfit.FitResult` of the same data) its estimate is marked on every
    panel (a line on the diagonal, a point with its 68/95 % ellipses below it).

    ``sampling``: a :class:`ambfit.estimation.bayes.Posterior` (anything with ``datatree.posterior`` holding draws
    in the units the Posterior writes there, :data:`ambfit.estimation.results.DISPLAY`: µm and N·m²/A²);
    ``var_names``: the variables to show (default: those of g_v0, v0, k_v, g_w0, w0, k_w present).
    """
    import matplotlib.pyplot as plt
    from matplotlib.colors import to_rgba

    from ambfit.estimation.units import BY_AXIS, DISPLAY, pm

    post = sampling.datatree.posterior
    names = list(var_names or [n for n in BY_AXIS["v"] + BY_AXIS["w"] if n in post])
    n = len(names)
    factor = [PAIR_UNITS.get(v, ("", 1.0))[1] for v in names]                  # SI -> plotted unit
    from_tree = [f / DISPLAY.get(v, ("", 1.0))[1] for v, f in zip(names, factor)]   # tree unit -> plotted unit
    chains = [np.asarray(post[v].values, dtype=float).reshape(-1, np.shape(post[v].values)[-1]) * f
              for v, f in zip(names, from_tree)]                                # [variable][chain, draw]
    flat = [c.ravel() for c in chains]
    ls = None
    if result is not None:
        idx = [result.names.index(v) if v in result.names else None for v in names]
        ls = {"idx": idx, "mu": [None if i is None else float(result.values[i]) * f for i, f in zip(idx, factor)]}
        cov = np.asarray(result.cov)
    limits = []
    for j, x in enumerate(flat):
        lo, hi = np.percentile(x, [0.5, 99.5])
        if ls is not None and ls["mu"][j] is not None:
            sd = np.sqrt(cov[ls["idx"][j], ls["idx"][j]]) * factor[j]
            lo, hi = min(lo, ls["mu"][j] - 3 * sd), max(hi, ls["mu"][j] + 3 * sd)
        pad = 0.05 * (hi - lo) if hi > lo else max(abs(lo) * 1e-6, 1e-12)
        limits.append((lo - pad, hi + pad))

    fig = fig or plt.figure(figsize=(2.3 * n + 1.0, 2.3 * n + 0.6))
    axes = np.asarray(fig.subplots(n, n, squeeze=False))
    thin = max(1, int(np.ceil(chains[0].shape[1] / max_points)))
    for i in range(n):
        for j in range(n):
            ax = axes[i, j]
            if i == j:
                ax.hist(flat[j], bins=40, range=limits[j], density=True, color="tab:blue", alpha=0.6)
                ax.set_yticks([])
                mean, sd = float(np.mean(flat[j])), float(np.std(flat[j]))
                ax.set_title(f"{names[j]} = {pm(mean, sd)} {PAIR_UNITS.get(names[j], ('', 1))[0]}", fontsize=8)
                if ls is not None and ls["mu"][j] is not None:
                    ax.axvline(ls["mu"][j], color="r", lw=1.2, label="least squares")
            elif i > j:
                for c in range(chains[j].shape[0]):
                    ax.scatter(chains[j][c, ::thin], chains[i][c, ::thin], s=2, color="tab:blue", alpha=0.25,
                               linewidths=0, rasterized=True)
                if ls is not None and ls["mu"][i] is not None and ls["mu"][j] is not None:
                    _ellipses(ax, ls, cov, (j, i), (factor[j], factor[i]))
                ax.set_ylim(limits[i])
            else:
                rho = float(np.corrcoef(flat[j], flat[i])[0, 1])
                ax.set_facecolor(to_rgba("tab:red" if rho > 0 else "tab:blue", alpha=0.6 * abs(rho)))
                ax.text(0.5, 0.58, f"ρ = {rho:+.2f}", ha="center", va="center", fontsize=11,
                        transform=ax.transAxes)
                if ls is not None and None not in (ls["idx"][i], ls["idx"][j]):
                    a, b = ls["idx"][i], ls["idx"][j]
                    r_ls = cov[a, b] / np.sqrt(cov[a, a] * cov[b, b])
                    ax.text(0.5, 0.3, f"least squares {r_ls:+.2f}", ha="center", va="center", fontsize=7,
                            color="r", transform=ax.transAxes)
                ax.set_xticks([])
                ax.set_yticks([])
            ax.set_xlim(limits[j])
            ax.tick_params(labelsize=7)
            if i == n - 1:
                ax.set_xlabel(pair_label(names[j]), fontsize=8)
            elif i > j or i == j:
                ax.tick_params(labelbottom=False)
            if j == 0 and i > 0:
                ax.set_ylabel(pair_label(names[i]), fontsize=8)
            elif i > j:
                ax.tick_params(labelleft=False)
    draws = flat[0].size
    title = f"posterior, {draws} draws ({chains[0].shape[0]} chains)"
    if ls is not None:
        title += "; red: least squares (68/95 % ellipses)"
    fig.suptitle(title, fontsize=9)
    return fig


def _ellipses(ax, ls, cov, pair, factors):
    """The least-squares point and its 2-D 68/95 % ellipses (Δχ² 2.3 and 6.2) on an (x, y) panel, display units."""
    j, i = pair
    a, b = ls["idx"][j], ls["idx"][i]
    c = cov[np.ix_([a, b], [a, b])] * np.outer(factors, factors)
    w, v = np.linalg.eigh(c)
    t = np.linspace(0, 2 * np.pi, 100)
    mu = np.array([ls["mu"][j], ls["mu"][i]])
    for d2, style in ((2.3, "-"), (6.2, "--")):
        ell = (v @ (np.sqrt(np.clip(w, 0, None))[:, None] * np.array([np.cos(t), np.sin(t)]))) * np.sqrt(d2)
        ax.plot(mu[0] + ell[0], mu[1] + ell[1], "r" + style, lw=0.8)
    ax.plot(*mu, "r+", ms=9, mew=1.5, label="least squares")


def plot_design_comparison(table, ax=None):
    """Bar chart of the Cramér-Rao bound on the gap for each design (log scale), condition numbers annotated."""
    if ax is None:
        import matplotlib.pyplot as plt

        # (wide, and laid out, so the designs' names on the left and the notes on the right stay on the figure)
        _, ax = plt.subplots(figsize=(10, 0.45 * len(table) + 1.5), layout="constrained")
    y = np.arange(len(table))
    vals = np.asarray(table["crlb_gap_um"], dtype=float)
    finite = np.where(np.isfinite(vals), vals, np.nanmax(vals[np.isfinite(vals)]) * 100 if np.isfinite(vals).any()
                      else 1.0)
    ax.barh(y, finite, color=["tab:gray" if not np.isfinite(v) else "tab:blue" for v in vals])
    labels = [f"{d} ({l})" if "loads" in table and l else d for d, l in
              zip(table["design"], table["loads"] if "loads" in table else [""] * len(table))]
    ax.set_yticks(y, labels)
    ax.set_xscale("log")
    ax.set_xlabel("sqrt(CRLB) of the v-axis gap [µm] (grey: unbounded)")
    for yi, (v, c) in enumerate(zip(vals, table["condition"])):
        ax.text(finite[yi], yi, f"  cond {c:.2g}" + ("" if np.isfinite(v) else ", not identifiable"), va="center",
                fontsize=8)
    ax.set_xlim(None, finite.max() * 60)                      # room for the notes right of the longest bar
    ax.invert_yaxis()
    return ax


def plot_recommendation(rec, data=None, *, clearance_um: float | None = None, fig=None):
    """A design recommendation: where the next set-points lie (numbered, coloured by bias) next to the
    readings so far, the estimated bearing centre with the back-up clearance (``clearance_um``) and the allowed
    radius about it, and the target's predicted standard error step by step.

    ``rec`` is a :class:`ambfit.estimation.design.Recommendation`; ``data`` the data set it starts from.
    """
    import matplotlib.pyplot as plt

    fig = fig or plt.figure(figsize=(11, 5), layout="constrained")     # (the colour bar's label off the right panel)
    ax, ax2 = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.1, 1]})
    if data is not None:
        frame = data.frame if hasattr(data, "frame") else data
        ax.scatter(frame["v_um"], frame["w_um"], s=10, color="0.6", label="readings so far")
    st = rec.steps
    sc = ax.scatter(st["v_set_um"], st["w_set_um"], c=st["bias_A"], cmap="viridis", s=60, edgecolor="k",
                    label="recommended", zorder=3)
    at = {}                              # steps at one set-point share one label ("1, 2, 4"), not stacked numbers
    for i, r in enumerate(st.itertuples(), 1):
        at.setdefault((round(r.v_set_um, 6), round(r.w_set_um, 6)), []).append(str(i))
    for (v, w), numbers in at.items():
        ax.annotate(", ".join(numbers), (v, w), textcoords="offset points", xytext=(5, 5), fontsize=8)
    fig.colorbar(sc, ax=ax, label="bias [A]")
    # the clearance is measured from the bearing centre, which the sensors read at minus the origin
    cv, cw = rec.centre_um if rec.centre_um is not None else (0.0, 0.0)
    t = np.linspace(0, 2 * np.pi, 200)
    ax.plot(cv, cw, "rx", label="estimated bearing centre")
    if clearance_um:
        ax.plot(cv + clearance_um * np.cos(t), cw + clearance_um * np.sin(t), "r--", lw=1,
                label="back-up clearance about it")
    if rec.radius_um is not None:
        ax.plot(cv + rec.radius_um * np.cos(t), cw + rec.radius_um * np.sin(t), "r:", lw=1,
                label="allowed (less the origin's uncertainty)")
    ax.set(xlabel="v set-point [µm]", ylabel="w set-point [µm]", aspect="equal", title="where to measure next")
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.15), ncol=2)
    f, unit = rec._unit()
    std = np.concatenate([[rec.std_now], st["predicted_std_after"].to_numpy()]) * f
    ax2.plot(np.arange(len(std)), std, "o-")
    ax2.set(xlabel="steps run", ylabel=f"predicted std of {rec.target} [{unit}]", ylim=(0, None),
            title=f"{rec.criterion}-optimal for {rec.target}")
    return fig
