"""Figures as functions of results (STYLE.md section 9): each takes a result and an optional Axes.

matplotlib (and ArviZ's plotting) are imported inside the functions, so importing
ambfit stays fast.
"""

from __future__ import annotations

import numpy as np


def _axes(ax):
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    if ax is None:
        _, ax = plt.subplots(figsize=(7, 5))
    return ax


def save(obj, path, dpi: int = 120) -> None:
    """Save an Axes, a Figure or an ArviZ plot collection to ``path``."""
    if hasattr(obj, "savefig") and not hasattr(obj, "figure"):
        obj.savefig(path)
        return
    fig = obj.figure if hasattr(obj, "figure") else obj
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)


def plot_solution_space(space, *, result=None, samples=None, ax=None, levels=(2.3, 6.2, 11.8, 50, 200, 1000)):
    """The paper's Fig. 2 as a map: Δχ² over (origin, gap) in µm, with the least-squares point,
    its 1- and 2-sigma ellipses, posterior draws and the weakest Fisher direction if given.

    ``space``: :class:`ambfit.conditioning.SolutionSpace`; ``result``: a
    :class:`ambfit.fit.FitResult`; ``samples``: array[n, 2] of (gap, origin) draws [m].
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


def plot_ranking(record: dict, ax=None):
    """Held-out excess residual (noise units) after adding each candidate effect; the baseline as a line."""
    ax = _axes(ax)
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
