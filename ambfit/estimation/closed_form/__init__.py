"""The paper's closed form (Eq. 5-7): gap and origin from current-position perturbations.

At one rotor position ``x`` the same (unknown) load is carried at two bias
settings 1 and 2, so the gaps cancel out of Eq. 4's difference (Eq. 5) and::

    P = (g0 - (x0 + x) c) / (g0 + (x0 + x) c) = sqrt((i_t1^2 - i_t2^2) / (i_b1^2 - i_b2^2))   (Eq. 6)

with ``c = cos(alpha)``.  Each position gives one equation linear in
``X = (g0, x0 c)``::

    (1 - P) g0 - (1 + P) x0 c = (1 + P) x c                                                  (Eq. 7)

Two positions (the paper's symmetric pair ``±x1``) give the 2x2 system ``A X = C``
(the paper prints ``C`` with ``cos(theta)`` where ``x cos(alpha)`` is meant); more
positions are solved in the least-squares sense.  Neither the load nor ``k`` is
needed; with known loads ``k`` follows from Eq. 4 at the solution (the paper's
lamination-coefficient calibration).

:func:`solve` is the single-iteration solver; :func:`identify` groups a data set by
experiment, iteration and axis, solves each iteration and reports the mean and its
standard error as the paper's tables do.
"""

from ambfit.estimation.closed_form.equations import (
    MAX_CONDITION,
    MIN_STEP_SNR,
    POSITION_TOLERANCE,
    ClosedFormError,
    Solution,
    eq6,
    eq7,
    eq7_system,
    ratio,
    solve,
)
from ambfit.estimation.closed_form.iterations import (
    MAX_REJECTED_FRACTION,
    MAX_RELATIVE_SEM,
    MAX_SCATTER_RATIO,
    AxisEstimate,
    ClosedFormResult,
    identify,
    solve_rows,
)

__all__ = ["MAX_CONDITION", "MIN_STEP_SNR", "POSITION_TOLERANCE", "MAX_REJECTED_FRACTION", "MAX_RELATIVE_SEM",
           "MAX_SCATTER_RATIO", "ClosedFormError", "Solution", "AxisEstimate", "ClosedFormResult", "eq6", "eq7",
           "eq7_system", "ratio", "solve", "solve_rows", "identify"]
