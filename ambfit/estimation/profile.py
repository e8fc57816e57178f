"""The force constant and the static loads at a given gap and origin: the linear parameters profiled out.

At fixed gap and origin, Eq. 4 is linear in ``k``: each row's force is ``k u`` with ``u`` the force at
``k = 1``.  With known loads ``L``, ``k`` is the least-squares slope through the origin,
``k = sum(L u) / sum(u^2)``; a nuisance load shared by a group of rows is the mean of ``k u`` over the group.
Every start of a fit (closed form, grid, a fit of another model) and the closed form's own ``k`` take them from
:func:`profile`; NumPy only, vectorised over leading axes (origins of a grid) and over segments (axes and load
groups of many data sets at once).
"""

from __future__ import annotations

import numpy as np


def _segment_sum(values: np.ndarray, segment: np.ndarray, n: int) -> np.ndarray:
    """Sums of ``values[..., rows]`` over rows of each segment ``0..n-1`` (rows of segment -1 are left out):
    array[..., n]."""
    lead = values.shape[:-1]
    flat = values.reshape(-1, values.shape[-1])
    keep = segment >= 0
    idx = (np.arange(flat.shape[0])[:, None] * n + segment[None, keep]).ravel()
    out = np.bincount(idx, weights=flat[:, keep].ravel(), minlength=flat.shape[0] * n)
    return out.reshape(lead + (n,))


def profile(unit, load, known, k_segment, n_k: int, load_segment, n_loads: int, k_held: float | np.ndarray):
    """Best ``k`` per segment and best nuisance loads [N] at the gap and origin that gave ``unit``.

    Parameters
    ----------
    unit : array[..., rows]
        Each row's force at ``k = 1`` [N m^2/A^2 per ... : N / (N m^2/A^2)].
    load : array[rows]
        Known loads [N] (read where ``known``).
    known : array[rows] of bool
        Rows with a known load (only rows the fit uses: pass ``known & used``).
    k_segment : array[rows] of int
        The ``k`` each row belongs to, ``0..n_k-1`` (an axis of a data set); -1 for none.
    load_segment : array[rows] of int
        The nuisance load of each row, ``0..n_loads-1``; -1 for a row with a known load.
    k_held : float or array[n_k]
        ``k`` where a segment has no known load (it cancels from gap and origin).

    Returns
    -------
    k : array[..., n_k]
        Least-squares slope through the origin over the known loads, ``k_held`` without them.
    calibrated : array[n_k] of bool
        Whether a segment had known loads.
    loads : array[..., n_loads]
        Mean of ``k u`` over each load group's rows.
    """
    unit = np.asarray(unit, dtype=float)
    k_segment = np.asarray(k_segment, dtype=int)
    cal_seg = np.where(np.asarray(known, dtype=bool), k_segment, -1)
    num = _segment_sum(unit * np.where(cal_seg >= 0, np.asarray(load, dtype=float), 0.0), cal_seg, n_k)
    den = _segment_sum(unit**2, cal_seg, n_k)
    calibrated = np.bincount(cal_seg[cal_seg >= 0], minlength=n_k) > 0
    ok = calibrated & (den > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.where(ok, num / np.where(ok, den, 1.0), k_held)
    loads = np.zeros(unit.shape[:-1] + (n_loads,))
    if n_loads:
        load_segment = np.asarray(load_segment, dtype=int)
        k_row = np.take_along_axis(k, np.broadcast_to(np.maximum(k_segment, 0), unit.shape), axis=-1) \
            if k.ndim > 1 else k[np.maximum(k_segment, 0)]
        count = np.bincount(load_segment[load_segment >= 0], minlength=n_loads)
        with np.errstate(invalid="ignore", divide="ignore"):
            loads = _segment_sum(k_row * unit, load_segment, n_loads) / count
    return k, calibrated, loads
