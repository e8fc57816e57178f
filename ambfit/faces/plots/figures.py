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

    A file is written by :func:`ambfit._output.write_with` (atomically, through links, into devices), in the
    format its suffix names when matplotlib knows it, else PNG.  ``close`` releases the figure afterwards
    (reports that draw many figures); a notebook keeps it to show.
    """
    import os

    fig = figure_of(obj)
    fig.tight_layout()
    if isinstance(path, (str, os.PathLike)):
        from ambfit._output import write_with

        suffix = os.path.splitext(os.fspath(path))[1].lstrip(".").lower()
        fmt = suffix if suffix in fig.canvas.get_supported_filetypes() else "png"
        write_with(path, lambda f: fig.savefig(f, dpi=dpi, format=fmt))
    else:
        fig.savefig(path, dpi=dpi, format="png")
    if close:
        import matplotlib.pyplot as plt

        plt.close(fig)
