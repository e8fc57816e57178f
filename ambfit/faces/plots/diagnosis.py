"""Figures of a sim-to-real diagnosis: residuals against an operating variable, the candidates' ranking, the
model-discrepancy correction."""

from __future__ import annotations

import numpy as np
from matplotlib.ticker import ScalarFormatter

from ambfit.faces.plots.figures import _axes


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


VARIABLE_LABELS = {"position_own_um": "position on the axis [µm]", "position_other_um": "position on the other axis [µm]",
                   "bias_A": "bias current [A]", "control_current_A": "control current [A]",
                   "b_top_T": "top-coil flux density [T] (ideal circuit)",
                   "b_bottom_T": "bottom-coil flux density [T] (ideal circuit)", "load_N": "known load [N]",
                   "time_s": "time [s]", "temperature_C": "temperature [°C]",
                   "sweep_direction": "bias sweep direction (-1 down, +1 up)"}
"""Axis labels of the operating variables (:func:`ambfit.diagnosis.residuals.operating_variables`)."""


def plot_diagnosis_residuals(diagnosis, ax=None):
    """Residuals against the most structured operating variable, before and after adding the verdict's effects."""
    var = diagnosis.most_structured_variable
    ax = plot_residual_map(diagnosis.operating[var], diagnosis.residuals_before, diagnosis.residuals_after,
                           label=VARIABLE_LABELS.get(var, var), ax=ax)
    grade = getattr(diagnosis, "grade", None)
    after = f", and with {grade.model}" if diagnosis.residuals_after is not None and grade is not None else ""
    ax.set_title(f"where the model fails: residuals of the ideal law{after}", fontsize=10)
    return ax


def plot_ranking(diagnosis, ax=None):
    """Held-out excess residual (noise units) after adding each candidate effect; the baseline as a line.

    When the ideal law's held-out residuals sit on the noise floor (its excess is 0, so every candidate's bar would
    be empty: there is nothing to remove), each bar is instead the model's held-out RMS standardized residual,
    drawn against the noise floor (RMS 1 if the model were right) and the ideal law's.

    ``diagnosis``: a :class:`ambfit.Diagnosis` or its contract record (``to_json()``).
    """
    ax = _axes(ax)
    record = diagnosis.to_json() if hasattr(diagnosis, "to_json") else diagnosis
    rk = record["ranking"]
    names = [r["effect"] for r in rk]
    # (a none verdict may keep a small excess within its standard error: nothing to remove either)
    on_floor = not record["heldout_excess_before"] > 0 or record["verdict"] == "none"
    colours = ["tab:green" if n == record["verdict"] else "tab:blue" for n in names]
    if not rk:
        ax.text(0.5, 0.5, "no candidate effect was scored", ha="center", va="center", transform=ax.transAxes)
        ax.set_axis_off()
        return ax
    if on_floor:
        vals = [r["heldout_rms_after"] for r in rk]
        before = rk[0]["heldout_rms_before"]
        ax.barh(range(len(rk)), vals, color=colours)
        ax.axvline(1.0, color="grey", lw=1.5, label="noise floor: RMS 1 if the model were right")
        ax.axvline(before, color="k", ls="--", label="ideal model")
        ax.set_xlim(0.0, 1.15 * max(1.0, before, *vals))
        ax.set_xlabel("held-out RMS standardized residual [noise units]")
        ax.set_title(f"verdict: {record['verdict']}\nheld-out residuals on the noise floor: nothing to remove")
    else:
        vals = [r["heldout_excess_after"] for r in rk]
        ax.barh(range(len(rk)), vals, color=colours)
        ax.axvline(record["heldout_excess_before"], color="k", ls="--", label="ideal model")
        ax.set_xscale("symlog", linthresh=1.0)
        ax.xaxis.set_major_formatter(ScalarFormatter())         # 0, 1, 10, 100: not 5.73977×10⁻¹
        ax.set_xlabel("held-out excess residual [noise units]")
        ax.set_title(f"verdict: {record['verdict']}, shrink {record['shrink']:.2f}")
    ax.set_yticks(range(len(rk)), names)
    ax.invert_yaxis()
    if on_floor:        # the bars fill the axes up to the floor: the legend goes below them
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2)
    else:
        ax.legend(fontsize=7)
    return ax


def plot_discrepancy(diagnosis, ax=None):
    """Where the force law and the data part ways, as a function: the model-discrepancy correction [N] of every
    reading against the top coil's flux density, per axis, with the ideal law's force misfit for comparison.

    ``diagnosis``: a :class:`ambfit.Diagnosis` fitted with ``discrepancy=True``.
    """
    ax = _axes(ax)
    disc = diagnosis.ceiling
    if disc is None:
        raise ValueError("this diagnosis has no discrepancy term (diagnose(..., discrepancy=True))")
    op = diagnosis.operating
    b = op["b_top_T"].to_numpy()
    axis = op["axis"].to_numpy() if "axis" in op else np.zeros(len(b))
    corr = disc.fit.row_correction_n
    host = disc.host
    misfit_n = -diagnosis.baseline.residuals * disc.fit.row_noise_n      # load - force [N]
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
