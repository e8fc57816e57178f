"""Where a figure is drawn and how it is saved: new Axes from pyplot, the Figure behind any plot, PNG output."""

from __future__ import annotations


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
