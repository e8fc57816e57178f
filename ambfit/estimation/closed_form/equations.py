"""Eq. 5-7 for one iteration of one axis: the ratio ``P`` at each position (Eq. 6) and the linear system in gap
and origin (Eq. 7), on arrays of any shape (:func:`eq6`, :func:`eq7`) and for one iteration with its checks
(:func:`solve`).  See :mod:`ambfit.estimation.closed_form` for the equations."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ambfit.estimation.profile import profile
from ambfit.physics.bearing import PAPER_BEARING, Bearing
from ambfit.physics.model import ideal_force

POSITION_TOLERANCE = 2e-6
"""Readings whose own-axis positions differ by less than this [m] count as one position."""

MAX_CONDITION = 1e10
"""Systems with a larger condition number are reported as singular."""


MIN_STEP_SNR = 3.0
"""Eq. 6's numerator and denominator (the change of i^2 between the two biases) must exceed this many of their
noise standard deviations; closer to zero the ratio, and the gap with it, is noise."""


class ClosedFormError(ValueError):
    """Eq. 5-7 cannot be solved for these readings; the message says why."""


@dataclasses.dataclass(frozen=True)
class Solution:
    """The closed-form solution of one iteration on one axis (SI units).

    Attributes
    ----------
    g0, x0 : float
        Effective gap and origin [m].
    k : float
        Force constant [N m^2/A^2] from the known loads, NaN when none is known.
    positions : array[p]
        Own-axis positions [m] (mean of the readings at each position).
    biases : tuple[float, float]
        The two bias settings [A].
    ratios : array[p]
        Eq. 6's ``P`` at each position.
    condition : float
        2-norm condition number of Eq. 7's matrix ``A``.
    """

    g0: float
    x0: float
    k: float
    positions: np.ndarray
    biases: tuple[float, float]
    ratios: np.ndarray
    condition: float
    g0_std_predicted: float = math.nan


def _check_step(it, ib, sigma, n_avg):
    """Eq. 6 is ill conditioned when a bias step moves i^2 by less than ``MIN_STEP_SNR`` noise std."""
    if sigma is None or not np.isfinite(sigma) or sigma <= 0:
        return
    for name, cur in (("top", it), ("bottom", ib)):
        for j in range(cur.shape[0]):
            change = abs(cur[j, 0] ** 2 - cur[j, 1] ** 2)
            noise = 2.0 * sigma * math.sqrt((cur[j, 0] ** 2 + cur[j, 1] ** 2) / n_avg)
            if change < MIN_STEP_SNR * noise:
                raise ClosedFormError(
                    f"Eq. 6 is ill conditioned: between the two biases the {name}-coil i^2 changes by {change:.3g} A^2, "
                    f"only {change / noise:.1f} times its noise ({noise:.2g} A^2 for {sigma * 1e3:.2g} mA); use a larger "
                    "bias step or average more readings")


def _predicted_std(x, it, ib, sigma, n_avg, bearing) -> float:
    """Standard deviation of one iteration's gap that current noise ``sigma`` gives (linear propagation: the gap's
    forward differences in each current, all solved at once; NaN when a moved current makes Eq. 6-7 unsolvable)."""
    if sigma is None or not np.isfinite(sigma) or sigma <= 0:
        return math.nan
    h = 1e-7
    moved = np.eye(it.size).reshape(it.size, *it.shape) * h
    still = np.zeros_like(moved)
    # the readings as they are, then each top current moved by h, then each bottom current
    g0 = _gaps(x, np.concatenate([it[None], it + moved, it + still]), np.concatenate([ib[None], ib + still, ib + moved]),
               bearing.cos_alpha)
    if not np.all(np.isfinite(g0)):
        return math.nan
    return float(np.sqrt(np.sum(np.square((g0[1:] - g0[0]) / h))) * sigma / math.sqrt(n_avg))


def _gaps(x, it, ib, c) -> np.ndarray:
    """Eq. 6-7's gap [m] of a stack of one iteration's currents ``it``, ``ib`` [..., positions, 2] at the positions
    ``x`` [m], as :func:`solve` finds it; NaN where :func:`solve` would refuse (no ratio, a singular or
    ill-conditioned Eq. 7, a non-physical solution)."""
    num = np.square(it[..., 0]) - np.square(it[..., 1])
    den = np.square(ib[..., 0]) - np.square(ib[..., 1])
    p = np.where((num == 0.0) | (den == 0.0), np.nan, eq6(it[..., 0], ib[..., 0], it[..., 1], ib[..., 1]))
    finite = np.all(np.isfinite(p), axis=-1)
    a, rhs = eq7_system(np.where(finite[..., None], p, 0.0), x, c)
    sv = np.linalg.svd(a, compute_uv=False)
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = np.where(sv[..., -1] > 0, sv[..., 0] / sv[..., -1], np.inf)
        if len(x) == 2:
            g0, x0 = eq7(p, x, c)
        else:
            sol = np.linalg.pinv(a) @ rhs[..., None]
            g0, x0 = sol[..., 0, 0], sol[..., 1, 0] / c
        u = (x0[..., None] + x) * c
        ok = finite & (cond < MAX_CONDITION) & (g0 > 0) & np.all(np.abs(u) < g0[..., None], axis=-1)
    return np.where(ok, g0, np.nan)


def position_labels(df, group=None, *, set_point_tolerance: float = POSITION_TOLERANCE) -> np.ndarray:
    """Which position each reading is at within its group (an iteration of one axis): 0 for the lowest, counting
    up, array[rows] of ints.

    A group's positions are its own-axis set-points (``v_set_um`` or ``w_set_um``, by each row's axis) when every
    row of the group has one, else its measured positions (``v_um``, ``w_um``); sorted, they start a new position
    where they step by more than ``set_point_tolerance`` or ``POSITION_TOLERANCE`` [m] respectively.  ``df``: a
    contract table; ``group``: array[rows] of group codes >= 0 (default: the table is one group).  Vectorised over
    the groups: a study's thousands of iterations are grouped in one pass.
    """
    n = len(df)
    group = np.zeros(n, dtype=int) if group is None else np.asarray(group)
    if n == 0:
        return np.zeros(0, dtype=int)
    is_w = df["axis"].to_numpy() == "w"

    def column(name):
        return df[name].to_numpy(float) if name in df else np.full(n, np.nan)

    own_set = np.where(is_w, column("w_set_um"), column("v_set_um"))
    own = np.where(is_w, column("w_um"), column("v_um"))
    by_set = (np.bincount(group, weights=np.isnan(own_set)) == 0)[group]
    pos = np.where(by_set, own_set, own) * 1e-6
    tolerance = np.where(by_set, set_point_tolerance, POSITION_TOLERANCE)
    order = np.lexsort((pos, group))
    sg, sp = group[order], pos[order]
    new = np.zeros(n, dtype=int)
    new[1:] = (sg[1:] == sg[:-1]) & (sp[1:] - sp[:-1] > tolerance[order][1:])    # a new position within the group
    count = np.cumsum(new)
    first = np.zeros(int(sg.max()) + 1, dtype=int)
    first[sg[::-1]] = np.arange(n - 1, -1, -1)        # each group's first sorted index
    labels = np.empty(n, dtype=int)
    labels[order] = count - count[first[sg]]
    return labels


def eq6(i_top_1, i_bottom_1, i_top_2, i_bottom_2):
    """Eq. 6's ratio ``P = sqrt((i_t1^2 - i_t2^2) / (i_b1^2 - i_b2^2))`` on arrays of any shape (NaN where the
    radicand is not positive and finite)."""
    num = np.square(i_top_1) - np.square(i_top_2)
    den = np.square(i_bottom_1) - np.square(i_bottom_2)
    with np.errstate(divide="ignore", invalid="ignore"):
        rad = num / den
        return np.where(np.isfinite(rad) & (rad > 0), np.sqrt(np.abs(rad)), np.nan)


def eq7_system(p, x, cos_alpha):
    """Eq. 7's rows at each position, ``A [g0, x0 c]^T = C`` with ``A = [1 - P, -(1 + P)]``, ``C = (1 + P) x c``:
    ``(A, C)``, arrays[..., positions, 2] and [..., positions] from ``p``, ``x`` [m] of shape [..., positions]."""
    p = np.asarray(p, dtype=float)
    return np.stack([1.0 - p, -(1.0 + p)], axis=-1), (1.0 + p) * np.asarray(x, dtype=float) * cos_alpha


def eq7(p, x, cos_alpha):
    """Eq. 7 at two positions (the last axis of ``p`` and ``x`` [m]) for any leading shape: ``(g0, x0)`` [m] by
    Cramer's rule, NaN where the system is singular; ``cos_alpha`` a float or an array of the leading shape.
    :func:`solve` takes more positions by least squares."""
    cos_alpha = np.asarray(cos_alpha, dtype=float)
    a, c = eq7_system(p, x, cos_alpha[..., None])
    det = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        g0 = (c[..., 0] * a[..., 1, 1] - a[..., 0, 1] * c[..., 1]) / det
        u = (a[..., 0, 0] * c[..., 1] - a[..., 1, 0] * c[..., 0]) / det
    return g0, u / cos_alpha


def ratio(i_top_1, i_bottom_1, i_top_2, i_bottom_2) -> float:
    """Eq. 6's ratio ``P = sqrt((i_t1^2 - i_t2^2) / (i_b1^2 - i_b2^2))`` at one position.

    Raises :class:`ClosedFormError` when the radicand is not positive and finite.
    """
    num = i_top_1**2 - i_top_2**2
    den = i_bottom_1**2 - i_bottom_2**2
    if den == 0.0 or num == 0.0:
        raise ClosedFormError(
            f"the two bias settings give equal {'bottom' if den == 0.0 else 'top'} currents "
            f"(i_top {i_top_1:.6g}/{i_top_2:.6g} A, i_bottom {i_bottom_1:.6g}/{i_bottom_2:.6g} A): "
            "Eq. 6 needs two different biases")
    p = float(eq6(i_top_1, i_bottom_1, i_top_2, i_bottom_2))
    if not math.isfinite(p):
        rad = num / den
        raise ClosedFormError(
            f"Eq. 6 radicand (i_t1^2 - i_t2^2)/(i_b1^2 - i_b2^2) = {num:.6g}/{den:.6g} = {rad:.6g} is not positive: "
            "top and bottom currents did not move the same way between the two biases (noise larger than the "
            "bias step, a changed load, or a clipped coil)")
    return p


def solve(positions, i_top, i_bottom, *, biases=(np.nan, np.nan), loads=None,
          bearing: Bearing = PAPER_BEARING, sigma_i: float | None = None, n_avg: int = 1,
          _propagate: bool = True) -> Solution:
    """Eq. 6-7 for one iteration of one axis.

    Parameters
    ----------
    positions : array[p]
        Own-axis rotor positions [m], ``p >= 2`` distinct values.
    i_top, i_bottom : array[p, 2]
        Coil currents [A] at each position for bias settings 1 and 2.
    biases : tuple[float, float]
        The two bias settings [A] (recorded only).
    loads : array[p, 2], optional
        Known loads [N] of the readings (NaN where unknown) to calibrate ``k``.
    bearing : Bearing
        The bearing (its pole angle).
    sigma_i : float, optional
        Current noise std [A] of one reading: iterations whose bias step is within
        ``MIN_STEP_SNR`` noise std of zero are refused, and the gap's predicted std is recorded.
    n_avg : int
        Readings averaged into each current.
    """
    x = np.asarray(positions, dtype=float)
    it = np.asarray(i_top, dtype=float).reshape(len(x), 2)
    ib = np.asarray(i_bottom, dtype=float).reshape(len(x), 2)
    if len(x) < 2:
        raise ClosedFormError(f"Eq. 7 needs two positions, got {len(x)}")
    sep = float(np.min(np.diff(np.sort(x))))
    if sep < POSITION_TOLERANCE:
        raise ClosedFormError(
            f"two positions coincide ({sep * 1e6:.3g} µm apart): Eq. 7 becomes singular; use distinct set-points")
    c = bearing.cos_alpha
    if _propagate:
        _check_step(it, ib, sigma_i, n_avg)
    p = np.array([ratio(it[j, 0], ib[j, 0], it[j, 1], ib[j, 1]) for j in range(len(x))])
    a, rhs = eq7_system(p, x, c)
    sv = np.linalg.svd(a, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    if not cond < MAX_CONDITION:
        raise ClosedFormError(f"Eq. 7's matrix is singular (condition number {cond:.3g}); the ratios P "
                              f"{p.tolist()} do not separate gap and origin")
    if len(x) == 2:
        g0, x0 = (float(v) for v in eq7(p, x, c))
    else:
        sol = np.linalg.lstsq(a, rhs, rcond=None)[0]
        g0, x0 = float(sol[0]), float(sol[1] / c)
    u = (x0 + x) * c
    if not (g0 > 0 and np.all(np.abs(u) < g0)):
        raise ClosedFormError(f"non-physical solution g0 = {g0 * 1e6:.4g} µm, x0 = {x0 * 1e6:.4g} µm: "
                              "a pole gap would be closed at the measured positions")
    k = math.nan
    if loads is not None:
        f = np.asarray(loads, dtype=float).reshape(len(x), 2)
        unit = ideal_force(g0, x0, 1.0, it, ib, x[:, None], c)
        ok = (np.isfinite(f) & (np.abs(unit) > 0)).ravel()
        # least squares through the origin, F = k * unit (one k: every reading in segment 0)
        k = float(profile(unit.ravel(), np.nan_to_num(f.ravel()), ok, np.zeros(ok.size, dtype=int), 1,
                          -np.ones(ok.size, dtype=int), 0, math.nan)[0][0])
    pred = _predicted_std(x, it, ib, sigma_i, n_avg, bearing) if _propagate else math.nan
    return Solution(g0=g0, x0=x0, k=k, positions=x, biases=tuple(float(b) for b in biases), ratios=p, condition=cond,
                    g0_std_predicted=pred)
