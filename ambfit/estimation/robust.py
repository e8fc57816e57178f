"""Readings that do not belong: an outlier test on studentized residuals and robust losses.

One mistyped reading (a position of 0 where 20 µm was read) moves a least-squares
gap by many standard errors and inflates χ², but leaves every other reading
fitting well.  Two safeguards, as in ``scipy.optimize.least_squares`` and Ceres:

outlier test (the default, ``loss="auto"``)
    Each reading's standardized residual ``z_i`` is studentized by its leverage,
    ``t_i = z_i / (s sqrt(1 - h_ii))`` (a reading left out: ``sqrt(1 + h_ii)``), with
    ``h`` the hat matrix of the scaled Jacobian and ``s`` a robust scale
    (``1.4826 MAD(z)``, never below 1 so that a model misfit spread over every reading
    is not taken for outliers).  A reading is an outlier when ``|t_i|`` exceeds the
    Bonferroni bound ``Φ⁻¹(1 - α / 2n)`` (Cook & Weisberg, *Residuals and Influence
    in Regression*, 1982, sec. 2.2.2): on clean data the chance of any false alarm
    in a file is at most ``α`` (1 %).  Outliers are named, left out and the fit is
    repeated until no new one appears; more than ``MAX_FRACTION`` of the readings is
    not a few bad readings but a model that does not fit, and is reported as such.
robust losses (``loss="huber"`` or ``"cauchy"``)
    Iteratively reweighted least squares: weights ``w(t) = min(1, c/|t|)`` (Huber,
    ``c = 1.345``, 95 % efficiency on Gaussian noise) or ``1 / (1 + (t/c)^2)``
    (Cauchy, ``c = 2.385``), Holland & Welsch, Commun. Stat. A6, 813 (1977).
    The weights enter as ``sqrt(w)`` on each residual (the problem's row mask).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.special import ndtri, stdtrit

ALPHA = 0.01
"""Family-wise false-alarm probability of the outlier test on one data set."""

MAX_FRACTION = 0.1
"""More outliers than this fraction of the fitted readings: the model, not the readings, is at fault."""

MAX_ROUNDS = 5
"""Refits of the outlier test (each leaves out the newly found readings) and IRLS rounds of the robust losses."""

LOSSES = ("auto", "linear", "huber", "cauchy")
TUNING = {"huber": 1.345, "cauchy": 2.385}


@dataclasses.dataclass(frozen=True)
class Outlier:
    """One reading the outlier test rejected.

    Attributes
    ----------
    row : int
        Data row, counted from 1 as in every message (the CSV line is one more).
    axis : str
    t : float
        Studentized residual (in noise units).
    reading : dict
        The row's values as read (``i_top_A``, ``i_bottom_A``, ``v_um``/``w_um``, ``load_N``).
    fits_with : dict
        For each of the row's currents and its position, the value that alone would make the
        row fit the model (the likely true reading, when one of them was mistyped).
    """

    row: int
    axis: str
    t: float
    reading: dict
    fits_with: dict

    def __str__(self) -> str:
        read = ", ".join(f"{k} {_num(v)}" for k, v in self.reading.items())
        alt = " or ".join(f"{k} = {_num(v)}" for k, v in self.fits_with.items())
        return f"row {self.row} (axis {self.axis}: {read}) is {abs(self.t):.1f} σ off the fit" + (
            f"; it would fit with {alt}" if alt else "")

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def _num(v: float) -> str:
    return f"{v:.6g}" if v is not None and np.isfinite(v) else "–"


MAD_DOF = 2.72
"""``n / MAD_DOF`` degrees of freedom carry a noise level estimated as ``1.4826 MAD`` of ``n`` residuals: its relative
variance, 1.36/n for Gaussian noise (Rousseeuw & Croux, JASA 88, 1273, 1993), is a sample sd's of n/2.72 dof."""


def threshold(n: int, alpha: float = ALPHA, estimated: bool = False) -> float:
    """Bonferroni bound on ``|t|`` for ``n`` readings: ``Φ⁻¹(1 - alpha / 2n)``; with the noise ``estimated`` from
    the same residuals, Student's t of ``n / MAD_DOF`` degrees of freedom in its place (the scale's own scatter
    would otherwise push clean readings over the normal bound: 3.8 % of clean 80-reading files, not 1 %)."""
    p = 1.0 - alpha / (2.0 * max(n, 1))
    if estimated:
        return float(stdtrit(max(n / MAD_DOF, 1.0), p))
    return float(ndtri(p))


def robust_scale(z: np.ndarray, known_noise: bool = True) -> float:
    """``1.4826 median |z|`` of standardized residuals (1 when the model and the noise are right); with known
    noise levels never below 1, so a noise level stated too large does not make readings outliers."""
    z = np.asarray(z, dtype=float)
    return float(_scales(z[None], np.ones(z.shape, bool)[None], known_noise)[0])


def _scales(z: np.ndarray, fitted: np.ndarray, known_noise: bool) -> np.ndarray:
    """:func:`robust_scale` of each row of ``z[sets, rows]`` over its ``fitted`` finite entries: array[sets]."""
    a = np.where(fitted & np.isfinite(z), np.abs(z), np.nan)
    if not a.shape[1]:
        return np.ones(len(a))
    n = np.sum(~np.isnan(a), axis=1)
    none = n == 0
    # the median of each row's finite entries: sorted, NaN last (np.nanmedian's masked-array route is slow on short
    # rows)
    a = np.sort(a, axis=1)
    lo, hi = (np.take_along_axis(a, np.maximum(i, 0)[:, None], axis=1)[:, 0] for i in ((n - 1) // 2, n // 2))
    s = 1.4826 * np.where(none, 0.0, (lo + hi) / 2)
    return np.where(none, 1.0, np.maximum(1.0, s) if known_noise else np.maximum(s, 1e-300))


def studentized(jac_rows: np.ndarray, z: np.ndarray, used: np.ndarray, weight: np.ndarray | None = None,
                known_noise: bool = True) -> np.ndarray:
    """``t_i = z_i / (s sqrt(1 -/+ h_ii))`` for every row (fitted rows ``-``, left-out rows ``+``).

    ``jac_rows`` is the unweighted Jacobian of the standardized residuals of every row (free columns only),
    ``weight`` the rows' fit weights (1, or the robust loss's; 0 for left-out rows).
    """
    w = np.asarray(used, dtype=float) if weight is None else np.asarray(weight, dtype=float)
    return studentized_many(np.asarray(jac_rows)[None], np.asarray(z)[None], w[None], known_noise)[0]


def leverage(jac_rows: np.ndarray, weight: np.ndarray, prior: np.ndarray | None = None) -> np.ndarray:
    """``h = J (J' W J + P)^+ J'`` of every row of many fits: ``jac_rows[sets, rows, params]`` (unweighted),
    ``weight[sets, rows]`` (each row's weight in the fit's sum of squares, 0 for a left-out row) and ``prior[params]``
    (the precision of priors on the parameters, none by default).  A fitted row's leverage is ``w h``; a left-out
    row's prediction variance, in its noise units, is ``h`` (Cook and Weisberg, *Residuals and Influence in
    Regression*, 1982, sec. 2.2).  Returns ``h[sets, rows]``."""
    jw = jac_rows * np.sqrt(np.asarray(weight, dtype=float))[..., None]
    info = np.einsum("bni,bnj->bij", jw, jw)
    cov = np.linalg.pinv(info if prior is None else info + np.diag(prior))
    return np.einsum("bni,bij,bnj->bn", jac_rows, cov, jac_rows)


def studentized_many(jac_rows: np.ndarray, z: np.ndarray, weight: np.ndarray, known_noise: bool = True) -> np.ndarray:
    """:func:`studentized` of many fits at once: ``jac_rows[sets, rows, params]``, ``z`` and ``weight[sets, rows]``;
    returns ``t[sets, rows]``."""
    w = np.asarray(weight, dtype=float)
    h = leverage(jac_rows, w)                                          # leverage of an unweighted row
    fitted = w > 0
    var = np.where(fitted, 1.0 - np.clip(w * h, 0.0, 0.999), 1.0 + h)
    return np.asarray(z, dtype=float) / (_scales(np.asarray(z, dtype=float), fitted, known_noise)[:, None]
                                         * np.sqrt(var))


def weights(t: np.ndarray, loss: str) -> np.ndarray:
    """IRLS weights of the robust ``loss`` for studentized residuals ``t``."""
    c = TUNING[loss]
    a = np.abs(np.asarray(t, dtype=float))
    if loss == "huber":
        return np.minimum(1.0, c / np.maximum(a, 1e-300))
    return 1.0 / (1.0 + (a / c) ** 2)


def fits_with(i_top: float, i_bottom: float, x: float, load: float, g0: float, x0: float, k: float,
              cos_alpha: float) -> dict:
    """The value of each of ``i_top``, ``i_bottom``, ``x`` that alone would make Eq. 4 give ``load``
    (SI in; contract units out: A and µm); None where no value would."""
    out = {}
    g_t, g_b = g0 - (x0 + x) * cos_alpha, g0 + (x0 + x) * cos_alpha
    f_bottom = k * i_bottom**2 / g_b**2
    f_top = k * i_top**2 / g_t**2
    if k > 0:
        rad = (load + f_bottom) / k
        out["i_top_A"] = float(np.sqrt(rad) * g_t) if rad >= 0 else None
        rad = (f_top - load) / k
        out["i_bottom_A"] = float(np.sqrt(rad) * g_b) if rad >= 0 else None
    # position: solve F(x) = load by bisection over the physical range (F increases with x)
    def force(xx):
        gt, gb = g0 - (x0 + xx) * cos_alpha, g0 + (x0 + xx) * cos_alpha
        return k * (i_top**2 / gt**2 - i_bottom**2 / gb**2)

    lo, hi = -g0 / cos_alpha - x0 + 1e-9, g0 / cos_alpha - x0 - 1e-9
    lo, hi = max(lo, -0.9 * g0 - x0), min(hi, 0.9 * g0 - x0)
    if k > 0 and force(lo) <= load <= force(hi):
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if force(mid) < load else (lo, mid)
        out["x_um"] = 0.5 * (lo + hi) * 1e6
    return {key: v for key, v in out.items() if v is not None}
