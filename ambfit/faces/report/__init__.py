"""Self-contained HTML reports, written as templates over results.

:func:`data_report` (``ambfit report DATA.csv --out DIR``) identifies one data set,
samples its posterior, maps its solution space, recommends the next perturbations and
diagnoses the sim-to-real gap; :func:`paper_report` (``ambfit paper --out reports/paper``)
reruns the seed paper's Tables 1-4 and Figs. 2, 3 and 5 on the virtual rig and sets them
beside the paper.

Layout: :mod:`~ambfit.faces.report.render` (the Jinja2 environment, figures, tables),
:mod:`~ambfit.faces.report.dataset` and :mod:`~ambfit.faces.report.paper_sections` (one
function per section: a result in, the section template's context out),
:mod:`~ambfit.faces.report.paper` (the paper report's files), ``templates/`` (page
layout, style and every sentence of prose).
"""

from ambfit.faces.report.dataset import data_report
from ambfit.faces.report.paper import paper_report

__all__ = ["data_report", "paper_report"]
