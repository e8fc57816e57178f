"""A campaign: identification in windows of time, the drift of gap and origin, and change points.

A lab that logs one machine for days or weeks wants to know whether the bearing's effective
gap and origin stay put.  :func:`analyse` cuts the contract table into windows (rolling
windows of ``time_s``, :func:`windows`, or one per experiment, :func:`by_experiment`), fits
each with ambfit's least squares (:func:`ambfit.estimation.fit.fit`), and studies each
parameter's series of estimates ``y_j ± s_j`` at the windows' times ``t_j``:

Drift (:func:`drift`)
    The weighted least-squares line ``y = a + b t`` (weights ``1 / s_j^2``).  The slope's standard error
    is ``sqrt((X^T W X)^-1)_bb``; when the scatter about the line exceeds the error bars (reduced
    ``χ² > 1``) it is multiplied by ``sqrt(χ²/dof)`` (the Birge ratio; Birge, Phys. Rev. 40, 207, 1932; the
    scale factor S of the Particle Data Group's averages) and the result says so.

Change points (:func:`change_points`)
    The model with one step, ``y_j = a + b t_j + δ [j >= τ] + ε_j`` with ``ε_j ~ N(0, s_j^2)``, against the
    model without it.  For each candidate boundary ``τ`` (between consecutive experiments, or windows when the
    data name none) the jump ``δ̂_τ`` is fitted jointly with the drift, so the drift is removed without the jump
    leaking into it, and ``z_τ = δ̂_τ / se(δ̂_τ)``; ``max_τ z_τ^2`` is the likelihood-ratio statistic for one
    change point in a simple linear regression with known variances (Kim & Siegmund, Biometrika 76, 409,
    1989).  Its p-value is bounded by Bonferroni over the ``m`` candidates, ``p <= m P(χ²_1 >= max z²)``
    (conservative; Worsley, Biometrika 69, 297, 1982, gives a sharper bound for change points), or
    found by simulating the no-jump model (``method="simulation"``).  A step is flagged when ``p <= alpha``
    (1 %).  Further steps are searched one at a time with the flagged ones in the model (Bai, Econometric
    Theory 13, 315, 1997: estimating multiple breaks one at a time).  The windows' error bars are taken as
    known; when the model under test (drift, flagged steps and the candidate) scatters beyond them by more
    than chance (χ² p-value below 1 %), its errors are scaled by its Birge ratio and the p-value uses
    Student's t, as a t-test takes its variance from the full model.  (Scaling whenever χ²/dof > 1 would act
    on noise: a χ² of 8 degrees of freedom exceeds its mean by half in one case of seven.  A second jump not
    yet in the model inflates the scale and can mask the first: two jumps of similar size in one campaign
    are the test's weak case.)  The drift is a straight line: one that bends (exponential warm-up) leaves a
    curvature that the search reads as a step (``benchmarks/campaign.py``: most campaigns with an 8 h warm-up
    get a flag on v0); check the drift's χ²/dof and look at the series before reading a flag as a jump.

The drift is then reported from the model with the flagged steps in it.

Jumps against a drift measured elsewhere (:func:`differences`)
    With few windows (the paper's Table 1 has three experiments) a drift and a step cannot both be fitted.
    A drift measured inside the experiments (where no re-levitation happens) is then removed from each
    difference of neighbours, its error included: ``z = (y_j - y_{j-1} - b Δt) / sqrt(s_j² + s_{j-1}² +
    Δt² s_b²)``, Bonferroni over the boundaries.  :func:`paper_origins` applies it to the paper's Tables 1
    and 2; :func:`change_points` also takes such a drift (``drift=``, a Gaussian constraint on the slope).

Windows are independent estimates only when they share no readings: with overlapping
rolling windows (``step_s < width_s``) the tests use a subset that does not overlap, and say so.

Layout: :mod:`~ambfit.studies.campaign.window` (windows and their fits),
:mod:`~ambfit.studies.campaign.series` (a parameter's series, its line and drift),
:mod:`~ambfit.studies.campaign.steps` (change points, differences),
:mod:`~ambfit.studies.campaign.analysis` (:func:`analyse`, the :class:`Campaign` record),
:mod:`~ambfit.studies.campaign.paper_tables` (the paper's Tables 1 and 2 as a campaign).

Example
-------
>>> import numpy as np
>>> t = np.arange(8.0)
>>> s = Series("v0", t, 1e-6 * (0.2 * t + 3.0 * (t >= 4)), np.full(8, 0.1e-6), labels=tuple("ABCDEFGH"),
...            time_unit="h", seconds_per_unit=3600.0)
>>> cp = change_points(s)
>>> [f.at for f in cp.flagged], round(drift(s, steps=cp.steps).per_hour()[0] * 1e6, 3)
(['E'], 0.2)
"""

from ambfit.studies.campaign.analysis import Campaign, analyse
from ambfit.studies.campaign.paper_tables import PaperOrigins, paper_origins
from ambfit.studies.campaign.series import Drift, Series, drift
from ambfit.studies.campaign.steps import ALPHA, SCATTER_P, ChangePoints, Step, change_points, differences
from ambfit.studies.campaign.window import (
    PARAMS,
    CampaignError,
    Window,
    by_experiment,
    check_time,
    identify,
    independent,
    windows,
)

__all__ = ["ALPHA", "PARAMS", "SCATTER_P", "Campaign", "CampaignError", "ChangePoints", "Drift", "PaperOrigins",
           "Series", "Step", "Window", "analyse", "by_experiment", "change_points", "check_time", "differences",
           "drift", "identify", "independent", "paper_origins", "windows"]
