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


def plot_pair(sampling, var_names=None):
    """ArviZ pair plot of gap, origin and k (matplotlib backend); returns the plot collection."""
    import arviz as az

    post = sampling.datatree.posterior
    names = var_names or [n for n in ("g_v0", "v0", "k_v", "g_w0", "w0", "k_w") if n in post]
    return az.plot_pair(sampling.datatree, var_names=names, backend="matplotlib")


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
