"""Figures as functions of results (STYLE.md section 9): each takes a result and an optional Axes.

matplotlib (and ArviZ's plotting) are imported inside the functions, so importing
ambfit stays fast.  New figures come from pyplot on whatever backend the caller
runs (inline in Jupyter, Agg for the command line, which sets it): library code
never switches the backend.
"""

from __future__ import annotations

import numpy as np


def _axes(ax):
    import matplotlib.pyplot as plt

    if ax is None:
        _, ax = plt.subplots(figsize=(7, 5))
    return ax


def figure_of(obj):
    """The matplotlib Figure behind an Axes, a Figure or an ArviZ plot collection."""
    if hasattr(obj, "get_viz"):          # arviz_plots PlotCollection (matplotlib backend)
        return obj.get_viz("figure")
    return obj.figure if hasattr(obj, "figure") and not hasattr(obj, "savefig") else obj


def save(obj, path, dpi: int = 120, *, close: bool = False) -> None:
    """Save an Axes, a Figure or an ArviZ plot collection to ``path`` (a file name or a binary buffer, PNG).

    ``close`` releases the figure afterwards (reports that draw many figures); a notebook keeps it to show.
    """
    import os

    fig = figure_of(obj)
    fig.tight_layout()
    # a file name gives the format by its suffix; a buffer has none
    fig.savefig(path, dpi=dpi, **({} if isinstance(path, (str, os.PathLike)) else {"format": "png"}))
    if close:
        import matplotlib.pyplot as plt

        plt.close(fig)


def plot_solution_space(space, *, result=None, samples=None, ax=None, levels=(2.3, 6.2, 11.8, 50, 200, 1000)):
    """The paper's Fig. 2 as a map: Δχ² over (origin, gap) in µm, with the least-squares point,
    its 1- and 2-sigma ellipses, posterior draws and the weakest Fisher direction if given.

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
    ax.contour(x, y, d, levels=list(levels), colors="w", linewidths=0.6)
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
    ax.set_xlabel(f"{space.axis}-axis origin [µm]")
    ax.set_ylabel(f"{space.axis}-axis effective gap [µm]")
    ax.set_title(f"Solution space, axis {space.axis} ({space.n_rows} readings)")
    ax.legend(loc="upper right", fontsize=7)
    return ax


PAIR_UNITS = {"g_v0": ("µm", 1e6), "v0": ("µm", 1e6), "g_w0": ("µm", 1e6), "w0": ("µm", 1e6),
              "k_v": ("10⁻⁶ N·m²/A²", 1e6), "k_w": ("10⁻⁶ N·m²/A²", 1e6)}
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

    from ambfit.estimation.results import DISPLAY, pm

    post = sampling.datatree.posterior
    names = list(var_names or [n for n in ("g_v0", "v0", "k_v", "g_w0", "w0", "k_w") if n in post])
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
    ax = _axes(ax)
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
    ax.invert_yaxis()
    return ax


def plot_residual_map(variable_values, z_before, z_after=None, *, label="", ax=None):
    """Standardized residuals against one operating variable, before and (optionally) after adding an effect."""
    ax = _axes(ax)
    ax.plot(variable_values, z_before, ".", ms=3, alpha=0.6, label="ideal model")
    if z_after is not None:
        ax.plot(variable_values, z_after, ".", ms=3, alpha=0.6, label="with the verdict effect")
    ax.axhspan(-2, 2, color="grey", alpha=0.15, label="±2 noise units")
    ax.set_xlabel(label)
    ax.set_ylabel("standardized residual z")
    ax.legend(fontsize=7)
    return ax


def plot_diagnosis_residuals(diagnosis, ax=None):
    """Residuals against the most structured operating variable, before and after adding the verdict's effects."""
    var = diagnosis.most_structured_variable
    return plot_residual_map(diagnosis.operating[var], diagnosis.residuals_before, diagnosis.residuals_after,
                             label=var, ax=ax)


def plot_ranking(diagnosis, ax=None):
    """Held-out excess residual (noise units) after adding each candidate effect; the baseline as a line.

    ``diagnosis``: a :class:`ambfit.Diagnosis` or its contract record (``to_json()``).
    """
    ax = _axes(ax)
    record = diagnosis.to_json() if hasattr(diagnosis, "to_json") else diagnosis
    rk = record["ranking"]
    names = [r["effect"] for r in rk]
    vals = [r["heldout_excess_after"] for r in rk]
    ax.barh(range(len(rk)), vals, color=["tab:green" if n == record["verdict"] else "tab:blue" for n in names])
    ax.axvline(record["heldout_excess_before"], color="k", ls="--", label="ideal model")
    ax.set_yticks(range(len(rk)), names)
    ax.invert_yaxis()
    ax.set_xscale("symlog", linthresh=1.0)
    ax.set_xlabel("held-out excess residual [noise units]")
    ax.set_title(f"verdict: {record['verdict']}, shrink {record['shrink']:.2f}")
    ax.legend(fontsize=7)
    return ax


def plot_discrepancy(diagnosis, ax=None):
    """Where the force law and the data part ways, as a function: the model-discrepancy correction [N] of every
    reading against the top coil's flux density, per axis, with the ideal law's force misfit for comparison.

    ``diagnosis``: a :class:`ambfit.Diagnosis` fitted with ``discrepancy=True``.
    """
    ax = _axes(ax)
    disc = diagnosis.discrepancy
    if disc is None or disc.get("fit") is None:
        raise ValueError("this diagnosis has no discrepancy term (diagnose(..., discrepancy=True))")
    op = diagnosis.operating
    b = op["b_top_T"].to_numpy()
    axis = op["axis"].to_numpy() if "axis" in op else np.zeros(len(b))
    corr = disc["fit"].row_correction_n
    host = disc["host"]
    misfit_n = -diagnosis.baseline.residuals * disc["fit"].row_noise_n      # load - force [N]
    for a, (name, colour) in enumerate((("v", "tab:blue"), ("w", "tab:orange"))):
        m = (axis == a) | (axis == name)
        if not np.any(m):
            continue
        ax.scatter(b[m], corr[m], s=8, color=colour, label=f"{name}: correction to {host.model}")
        if host.model == "ideal":
            ax.scatter(b[m], misfit_n[m], s=8, marker="x", color=colour, alpha=0.35,
                       label=f"{name}: ideal law's misfit (load - force)")
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set_xlabel("top-coil flux density [T] (ideal circuit)")
    ax.set_ylabel("force [N]")
    ax.set_title(f"discrepancy of {host.model}: what no parameter of it expresses")
    ax.legend(fontsize=7)
    return ax


# --- the paper's figures (ambfit.studies.paper) ------------------------------------------------------------------

def plot_fig2_surface(space, *, limit_dchi2: float = 11.8, fig=None):
    """The paper's Fig. 2 as drawn there: RMS force misfit over the v-axis effective gap (600-1000 µm, left
    axis) and origin (-100...100 µm, right axis) as a 3-D surface, and the same seen from above with the set
    of "solutions" (Δχ² below ``limit_dchi2``, 3 sigma in 2-D) marked: a long valley, not a point."""
    import matplotlib.pyplot as plt

    fig = fig or plt.figure(figsize=(12, 5))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    G, X = np.meshgrid(space.gap * 1e6, space.origin * 1e6, indexing="ij")
    rms = np.where(np.isfinite(space.rms), space.rms, np.nan) * 1e3
    # full resolution: the valley is a few grid steps wide and coarser meshes alias it into spikes
    ax3.plot_surface(G, X, np.log10(rms), cmap="viridis", rcount=len(space.gap), ccount=len(space.origin),
                     linewidth=0, antialiased=False)
    ax3.set_xlabel(f"{space.axis}-axis effective gap [µm]")
    ax3.set_ylabel(f"{space.axis}-axis origin [µm]")
    ax3.set_zlabel("log10 RMS force error [mN]")
    ax3.view_init(elev=28, azim=-60)
    ax3.set_title("Fig. 2: solution space (current-position)")
    ax = fig.add_subplot(1, 2, 2)
    d = space.delta_chi2()
    ax.pcolormesh(space.origin * 1e6, space.gap * 1e6, np.log10(rms), shading="auto", cmap="viridis")
    ax.contourf(space.origin * 1e6, space.gap * 1e6, np.where(np.isfinite(d), d, np.inf), levels=[0, limit_dchi2],
                colors=["tab:red"], alpha=0.6)
    g_min, x_min = space.minimum
    ax.plot(x_min * 1e6, g_min * 1e6, "w+", ms=10)
    ax.set_xlabel(f"{space.axis}-axis origin [µm]")
    ax.set_ylabel(f"{space.axis}-axis effective gap [µm]")
    ax.set_title(f"from above: red = solutions within the noise (Δχ² < {limit_dchi2:g})")
    return fig


def plot_fig3_positions(search, *, backup_clearance: float | None = None, ax=None):
    """The paper's Fig. 3: the symmetric position pairs of an origin search in the (v, w) plane (sensor
    coordinates, µm), one colour per iteration, with the back-up bearing clearance [m] (default: the paper
    rig's, :data:`ambfit.PAPER_BEARING`) and the true effective origin ``(-v0, -w0)``."""
    from ambfit.physics.bearing import PAPER_BEARING

    backup_clearance = PAPER_BEARING.backup_clearance if backup_clearance is None else backup_clearance
    ax = _axes(ax)
    df = search.data
    import matplotlib.pyplot as plt

    cmap = plt.get_cmap("viridis")
    its = sorted(df["iteration"].astype(int).unique())
    for k, it in enumerate(its):
        sub = df[(df["iteration"].astype(int) == it)]
        v = sub[sub["axis"] == "v"]["v_um"].to_numpy()
        w = sub[sub["axis"] == "v"]["w_um"].to_numpy()
        ax.plot(v, w, "o", ms=4, color=cmap(k / max(len(its) - 1, 1)),
                label=f"iteration {it}" if k in (0, len(its) - 1) else None)
        c = search.centers[k] * 1e6
        ax.plot(c[0], c[1], "x", color=cmap(k / max(len(its) - 1, 1)), ms=6)
    t = np.linspace(0, 2 * np.pi, 200)
    r = backup_clearance * 1e6
    ax.plot(r * np.cos(t), r * np.sin(t), "k--", lw=0.8, label=f"back-up bearing clearance ({r:.0f} µm)")
    truth = next(iter(search.truth.get("params", {}).values()), None) if search.truth else None
    if truth:
        ax.plot(-truth["v0_um"], -truth["w0_um"], "r*", ms=12, label="true effective origin (−v0, −w0)")
    ax.set_aspect("equal")
    ax.set_xlabel("v position [µm]")
    ax.set_ylabel("w position [µm]")
    ax.set_title("Fig. 3: position pairs (o readings, x centres)")
    ax.legend(fontsize=7, loc="upper left")
    return ax


def plot_fig5_iterations(reproduction, *, fig=None):
    """The paper's Fig. 5: rotor origins and effective gaps over the 10 iterations of Table 2 (Table 1's
    experiment 2): the paper's values, this reproduction and the rig's 90 % band over replicates."""
    import matplotlib.pyplot as plt

    from ambfit.studies.paper import QUANTITIES, load_table

    rep = reproduction
    j = rep.table2_index
    t2 = load_table(2)
    fig = fig or plt.figure(figsize=(10, 7))
    axes = fig.subplots(2, 1, sharex=True)
    its = np.arange(1, rep.run.shape[1] + 1)
    for ax, qs, ylabel in ((axes[0], (0, 1), "rotor origin [µm]"), (axes[1], (2, 3), "effective gap [µm]")):
        for q, color in zip(qs, ("tab:blue", "tab:orange")):
            name = QUANTITIES[q].removesuffix("_um")
            lo, hi = np.quantile(rep.replicates[:, j, :, q], [0.05, 0.95], axis=0)
            ax.fill_between(its, lo, hi, color=color, alpha=0.15, label=f"{name} rig 90 % band")
            ax.plot(its, rep.run[j, :, q], "-o", color=color, ms=4, label=f"{name} ambfit rig")
            ax.plot(np.arange(1, len(t2) + 1), t2[QUANTITIES[q]], "s--", color=color, mfc="none", ms=6,
                    label=f"{name} paper")
        ax.set_ylabel(ylabel)
        lo_y, hi_y = ax.get_ylim()
        ax.set_ylim(lo_y, hi_y + 0.35 * (hi_y - lo_y))   # room for the legend above the data
        ax.legend(fontsize=7, ncol=3, loc="upper center")
    axes[1].set_xlabel("iteration")
    axes[0].set_title("Fig. 5: rotor origins and effective gap values (Table 2 protocol)")
    return fig


def plot_spread(spread, ax=None):
    """Each table's spread: the paper's sample sd against the rig's 5-95 % range (log scale)."""
    ax = _axes(ax)
    y = np.arange(len(spread))
    med = spread["rig_median"].to_numpy()
    ax.errorbar(med, y, xerr=[med - spread["rig_lo"].to_numpy(), spread["rig_hi"].to_numpy() - med], fmt="o",
                color="tab:blue", label="rig: median and 5-95 % of the sd")
    ax.plot(spread["paper_sd"], y, "rs", label="paper")
    ax.set_yticks(y, [f"T{t} {q.removesuffix('_um')} ({'cal.' if r == 'calibration' else 'pred.'})" for t, q, r in
                      zip(spread["table"], spread["quantity"], spread["role"])])
    ax.set_xscale("log")
    ax.set_xlabel("standard deviation [µm]")
    ax.invert_yaxis()
    ax.legend(fontsize=7)
    ax.set_title("Spread: Table 2 iterations (calibration), table rows (prediction)", fontsize=10)
    return ax


def plot_recommendation(rec, data=None, *, clearance_um: float | None = None, fig=None):
    """A design recommendation: where the next set-points lie (numbered, coloured by bias) next to the
    readings so far and the back-up clearance, and the target's predicted standard error step by step.

    ``rec`` is a :class:`ambfit.estimation.design.Recommendation`; ``data`` the data set it starts from.
    """
    import matplotlib.pyplot as plt

    fig = fig or plt.figure(figsize=(10, 4.5))
    ax, ax2 = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.1, 1]})
    if data is not None:
        frame = data.frame if hasattr(data, "frame") else data
        ax.scatter(frame["v_um"], frame["w_um"], s=10, color="0.6", label="readings so far")
    st = rec.steps
    sc = ax.scatter(st["v_set_um"], st["w_set_um"], c=st["bias_A"], cmap="viridis", s=60, edgecolor="k",
                    label="recommended", zorder=3)
    for i, r in enumerate(st.itertuples(), 1):
        ax.annotate(str(i), (r.v_set_um, r.w_set_um), textcoords="offset points", xytext=(5, 5), fontsize=8)
    fig.colorbar(sc, ax=ax, label="bias [A]")
    if clearance_um:
        t = np.linspace(0, 2 * np.pi, 200)
        ax.plot(clearance_um * np.cos(t), clearance_um * np.sin(t), "r--", lw=1, label="back-up clearance")
    ax.set(xlabel="v set-point [µm]", ylabel="w set-point [µm]", aspect="equal", title="where to measure next")
    ax.legend(fontsize=8, loc="lower left")
    f, unit = rec._unit()
    std = np.concatenate([[rec.std_now], st["predicted_std_after"].to_numpy()]) * f
    ax2.plot(np.arange(len(std)), std, "o-")
    ax2.set(xlabel="steps run", ylabel=f"predicted std of {rec.target} [{unit}]", ylim=(0, None),
            title=f"{rec.criterion}-optimal for {rec.target}")
    return fig
