"""The paper's closed form (Eq. 5-7) checked against least squares on the same readings.

The closed form itself (:mod:`ambfit.estimation.closed_form`) sits below the fit pipeline and fits nothing; this
module, above both, hands it least squares as its reference, so that ``ambfit.closed_form(data)`` says when its
mean disagrees with least squares beyond their errors (the ``agrees_with_least_squares`` check: at higher noise
Eq. 6-7's mean is biased).
"""

from __future__ import annotations

import pandas as pd

from ambfit.data import Dataset
from ambfit.estimation.closed_form import ClosedFormResult, identify
from ambfit.estimation.fit import fit_many
from ambfit.physics.bearing import PAPER_BEARING, Bearing


def closed_form(data: Dataset | pd.DataFrame, *, by_experiment: bool = False, bearing: Bearing = PAPER_BEARING,
                reference=None) -> ClosedFormResult:
    """:func:`ambfit.estimation.closed_form.identify` with least squares of each estimate's rows as its reference
    (``reference``: another, as ``identify`` takes it)."""
    if reference is None:
        reference = lambda rows: fit_many([rows], bearing=bearing)[0]   # noqa: E731
    return identify(data, by_experiment=by_experiment, bearing=bearing, reference=reference)
