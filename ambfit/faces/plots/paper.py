"""The seed paper's figures rerun on the virtual rig (:mod:`ambfit.studies.paper`): Figs. 2, 3 and 5, and each
table's spread against the rig's."""

from __future__ import annotations

import numpy as np

from ambfit.faces.plots.figures import _axes


def plot_fig2_surface(space, *, limit_dchi2: float = 11.8, fig=None):
    """The paper's Fig. 2 as drawn there: RMS force misfit over the v-axis effective gap (600-1000 µm, left
    axis) and origin (-100...100 µm, right axis) as a 3-D surface, and the same seen from above with the set
    of "solutions" (Δχ² below ``limit_dchi2``, 3 sigma in 2-D) marked: a long valley, not a point."""
    import matplotlib.pyplot as plt

    fig = fig or plt.figure(figsize=(13, 5))
    fig.subplots_adjust(left=0.02, right=0.97, wspace=0.3)     # (the 3-D z label clear of the map's axis)
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    G, X = np.meshgrid(space.gap * 1e6, space.origin * 1e6, indexing="ij")
    rms = np.where(np.isfinite(space.rms), space.rms, np.nan) * 1e3
    # full resolution: the valley is a few grid steps wide and coarser meshes alias it into spikes
    ax3.plot_surface(G, X, np.log10(rms), cmap="viridis", rcount=len(space.gap), ccount=len(space.origin),
                     linewidth=0, antialiased=False)
    ax3.set_xlabel(f"{space.axis}-axis effective gap [µm]")
    ax3.set_ylabel(f"{space.axis}-axis origin [µm]")
    ax3.set_zlabel("log10 RMS force error [mN]", labelpad=8)
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
