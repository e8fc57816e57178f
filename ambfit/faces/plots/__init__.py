"""Figures as functions of results (STYLE.md section 9): each takes a result and an optional Axes.

matplotlib (and ArviZ's plotting) are imported inside the functions, so importing
ambfit stays fast.  New figures come from pyplot on whatever backend the caller
runs (inline in Jupyter, Agg for the command line, which sets it): library code
never switches the backend.

Layout: :mod:`~ambfit.faces.plots.figures` (axes and saving),
:mod:`~ambfit.faces.plots.estimation` (solution space, pair plot, designs, recommendation),
:mod:`~ambfit.faces.plots.diagnosis` (residual maps, ranking, discrepancy),
:mod:`~ambfit.faces.plots.paper` (the paper's figures); this package is their public API.
"""

from ambfit.faces.plots.diagnosis import plot_diagnosis_residuals, plot_discrepancy, plot_ranking, plot_residual_map
from ambfit.faces.plots.estimation import (
    PAIR_UNITS,
    pair_label,
    plot_design_comparison,
    plot_pair,
    plot_recommendation,
    plot_solution_space,
)
from ambfit.faces.plots.figures import figure_of, save
from ambfit.faces.plots.paper import plot_fig2_surface, plot_fig3_positions, plot_fig5_iterations, plot_spread

__all__ = ["PAIR_UNITS", "figure_of", "pair_label", "plot_design_comparison", "plot_diagnosis_residuals",
           "plot_discrepancy", "plot_fig2_surface", "plot_fig3_positions", "plot_fig5_iterations", "plot_pair",
           "plot_ranking", "plot_recommendation", "plot_residual_map", "plot_solution_space", "plot_spread", "save"]
