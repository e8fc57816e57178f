"""The lamination's B-H curve: ``H(B)`` of every iron branch of the magnetic equivalent circuit.

A monotone cubic (Fritsch-Carlson) through the bearing description's B-H table
(:attr:`~ambfit.physics.bearing.Bearing.b_curve`, :attr:`~ambfit.physics.bearing.Bearing.h_curve`), odd
in ``B`` and linear beyond the table; a constant permeability (:data:`DEFAULT_MU_R`) when the
bearing gives no table.  SI units (T, A/m).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ambfit.physics.bearing import MU_0, Bearing

MU_R_MAX = 1e12
"""Ceiling on the iron's relative permeability: keeps the circulating flux of a ring of ideal iron
(``iron_h_scale = 0``) determined; changes forces by ~1e-10 relative."""

DEFAULT_MU_R = 4000.0
"""Relative permeability used when the bearing gives no B-H curve (unsaturated silicon iron)."""

def _pchip_slopes(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Fritsch-Carlson slopes of the monotone cubic through ``(x, y)``."""
    h = np.diff(x)
    delta = np.diff(y) / h
    d = np.zeros_like(y)
    for j in range(1, len(x) - 1):
        if delta[j - 1] * delta[j] > 0:
            w1, w2 = 2 * h[j] + h[j - 1], h[j] + 2 * h[j - 1]
            d[j] = (w1 + w2) / (w1 / delta[j - 1] + w2 / delta[j])
    d[0] = delta[0]
    d[-1] = delta[-1]
    return d


class _BH(eqx.Module):
    """``H(B)`` [A/m] of the lamination: monotone cubic through the datasheet, odd in B, linear beyond."""

    b: tuple = eqx.field(static=True)
    h: tuple = eqx.field(static=True)
    d: tuple = eqx.field(static=True)

    def __call__(self, b):
        s = jnp.where(b < 0, -1.0, 1.0)                  # odd extension with the right slope at B = 0
        b_abs = s * b
        bk, hk, dk = (np.array(a) for a in (self.b, self.h, self.d))
        # One gather of the interval's ends (b, H, H') instead of six; the interval by comparison
        # with every knot (the table is short: cheaper to compile and run than a binary search).
        table = jnp.asarray(np.stack([bk[:-1], bk[1:], hk[:-1], hk[1:], dk[:-1], dk[1:]], axis=1))
        j = jnp.clip(jnp.sum(jnp.asarray(bk) <= b_abs[..., None], axis=-1) - 1, 0, len(self.b) - 2)
        row = table[j]
        x0, x1, y0, y1, d0, d1 = (row[..., c] for c in range(6))
        hh = x1 - x0
        # 0 <= t <= 1 by the interval's choice (beyond the table the linear extension is used): no clip, whose
        # derivative at a knot (B = 0, where Newton's method starts) would be half the curve's slope
        t = (b_abs - x0) / hh
        h00, h10 = 2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t
        h01, h11 = -2 * t**3 + 3 * t**2, t**3 - t**2
        inside = h00 * y0 + h10 * hh * d0 + h01 * y1 + h11 * hh * d1
        beyond = hk[-1] + dk[-1] * (b_abs - bk[-1])
        return s * jnp.where(b_abs > bk[-1], beyond, inside)


def _iron_h(p, bh: _BH, b):
    """``H(B)`` with ``p.saturation`` blending the curve (1) with its initial slope (0)."""
    return p.saturation * bh(b) + (1.0 - p.saturation) * b * bh.d[0]


@functools.lru_cache(maxsize=32)
def bh_curve(bearing: Bearing) -> _BH:
    """The bearing's ``H(B)`` (monotone cubic through its B-H table; linear ``DEFAULT_MU_R`` without one).

    Examples
    --------
    >>> from ambfit.physics.bearing import PAPER_BEARING
    >>> h = bh_curve(PAPER_BEARING)            # no table: linear iron
    >>> round(float(h(1.0)) * MU_0 * DEFAULT_MU_R, 12)
    1.0
    """
    if len(bearing.b_curve) >= 2:
        b, h = np.asarray(bearing.b_curve, float), np.asarray(bearing.h_curve, float)
    else:
        b = np.array([0.0, 2.0])
        h = b / (MU_0 * DEFAULT_MU_R)
    return _BH(b=tuple(b.tolist()), h=tuple(h.tolist()), d=tuple(_pchip_slopes(b, h).tolist()))
