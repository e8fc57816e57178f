"""Random smooth functions for the law zoo (:mod:`ambfit.rig.zoo`): the *structure* of a zoo law is drawn, not
only its magnitude.

A :class:`Shape` is a sum of a few terms drawn from four broad classes on ``u >= 0``, each zero at ``u = 0``:
powers ``u^n`` (polynomials), logistic steps ``sigma((u - c) / s) - sigma(-c / s)`` (mixtures of sigmoids),
knees ``s (softplus((u - c) / s) - softplus(-c / s))`` (a ramp that starts near ``c``: a monotone spline with
one smooth joint, or a lagged start) and settling curves ``1 - exp(-u / tau)`` (a first-order lag).  With
positive weights it is monotone increasing (a knee in flux density, a fringe area growing with the gap); with
signed weights it is any smooth function (a drift that rises and turns back).  Each law scales one to the
magnitude it needs (:mod:`ambfit.rig.zoo_laws`).
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ambfit._arrays import numpy_unless_traced
from ambfit.physics.stages import Effect

KINDS = ("power", "step", "knee", "settle")
SLOTS = 2
"""Terms of each kind a shape can hold (fixed, so that every shape has the same array shapes under ``jit``)."""


class Shape(eqx.Module):
    """``f(u) = sum_j w_j basis_j(u)`` over the terms of :data:`KINDS` (rows), :data:`SLOTS` of each (columns).

    ``w`` holds the weights (0 for a term not drawn), ``a`` each term's exponent ``n``, centre ``c``, centre
    ``c`` or time constant ``tau`` (in units of ``u``), ``s`` the widths of steps and knees.
    """

    w: jnp.ndarray
    a: jnp.ndarray
    s: jnp.ndarray

    def __call__(self, u):
        xp = numerics(u, self.w)
        u = xp.abs(xp.asarray(u, dtype=float))[..., None]
        n, c_step, c_knee, tau = self.a
        s_step, s_knee = self.s[1], self.s[2]

        def softplus(z):
            return xp.logaddexp(0.0, z)

        def sigmoid(z):
            return xp.exp(-softplus(-z))

        power = u**n
        step = sigmoid((u - c_step) / s_step) - sigmoid(-c_step / s_step)
        knee = s_knee * (softplus((u - c_knee) / s_knee) - softplus(-c_knee / s_knee))
        settle = 1.0 - xp.exp(-u / tau)
        return xp.sum(self.w[0] * power + self.w[1] * step + self.w[2] * knee + self.w[3] * settle, axis=-1)

    def slope(self, u, du: float = 1e-4):
        """``df/du`` by a central difference (draw-time checks only)."""
        return (self(u + du) - self(u - du)) / (2.0 * du)

    def describe(self) -> dict:
        """The drawn terms only: ``{"power": [[w, n], ...], "step": [[w, c, s], ...], ...}``."""
        w, a, s = (np.asarray(x) for x in (self.w, self.a, self.s))
        out = {}
        for k, kind in enumerate(KINDS):
            terms = [[float(w[k, j]), float(a[k, j])] + ([float(s[k, j])] if kind in ("step", "knee") else [])
                     for j in range(SLOTS) if w[k, j] != 0.0]
            if terms:
                out[kind] = terms
        return out


def numerics(*arrays):
    """numpy unless an argument is being traced by JAX: draws evaluate laws on numpy grids, and the rig senses
    whole protocols outside ``jit``, where op by op jax.numpy would compile each operation for each new length."""
    return numpy_unless_traced(*arrays)


def random_shape(rng: np.random.Generator, *, kinds=KINDS, terms=(1, 3), power=(1.0, 3.0), centre=(0.2, 1.2),
                 width=(0.03, 0.3), tau=(0.1, 1.0), signed=False, span=(0.0, 1.0)) -> Shape:
    """A :class:`Shape` of ``terms`` (a range) terms drawn from ``kinds``, normalised over ``span`` of ``u``.

    Exponents, centres, widths and time constants are drawn uniformly from their ranges (in units of ``u``).
    Weights are drawn log-uniformly over a decade (random signs with ``signed``).  The result is scaled so that
    ``f(span[1]) = 1`` (monotone) or ``max |f| = 1`` over ``span`` (``signed``).
    """
    w, a, s = np.zeros((4, SLOTS)), np.ones((4, SLOTS)), np.ones((4, SLOTS))
    slots = [(KINDS.index(k), j) for k in kinds for j in range(SLOTS)]
    count = int(rng.integers(terms[0], terms[1] + 1))
    for idx in rng.choice(len(slots), size=min(count, len(slots)), replace=False):
        k, j = slots[idx]
        w[k, j] = 10.0 ** rng.uniform(-1.0, 0.0) * (rng.choice([-1.0, 1.0]) if signed else 1.0)
        a[k, j] = rng.uniform(*(power, centre, centre, tau)[k])
        s[k, j] = rng.uniform(*width)
    shape = Shape(w, a, s)
    grid = np.linspace(*span, 201)
    values = np.asarray(shape(grid))
    scale = np.max(np.abs(values)) if signed else values[-1]
    if not np.isfinite(scale) or abs(scale) < 1e-12:
        return random_shape(rng, kinds=kinds, terms=terms, power=power, centre=centre, width=width, tau=tau,
                            signed=signed, span=span)
    return Shape(w / scale, a, s)


def log_uniform(rng: np.random.Generator, lo: float, hi: float, size=None):
    """Magnitudes spread evenly over decades between ``lo`` and ``hi``."""
    return np.exp(rng.uniform(np.log(lo), np.log(hi), size))


def signed(rng: np.random.Generator, lo: float, hi: float, size=None):
    """Log-uniform magnitudes between ``lo`` and ``hi`` with random signs."""
    return log_uniform(rng, lo, hi, size) * rng.choice([-1.0, 1.0], size)


class ZooLaw(Effect):
    """A zoo law: an :class:`~ambfit.physics.stages.Effect` whose structure and magnitude :meth:`draw` draws.

    ``family`` is the contract family (section 3) the law belongs to, ``""`` for a law of no family.
    """

    family: ClassVar[str] = ""

    @classmethod
    def draw(cls, rng: np.random.Generator, duration_s: float) -> ZooLaw:
        """A law of this class with random structure and magnitude; ``duration_s`` [s] is the run's length (the
        time scale of laws in time)."""
        return jax.tree_util.tree_map(jnp.asarray, cls._draw(rng, duration_s))

    @classmethod
    def _draw(cls, rng: np.random.Generator, duration_s: float) -> ZooLaw:
        """:meth:`draw` with numpy parameters (draw-time checks evaluate the law without compiling anything)."""
        raise NotImplementedError

    def describe(self) -> dict:
        """Parameters as plain lists (SI units), a :class:`Shape` as its drawn terms."""
        return {f.name: (v.describe() if isinstance(v, Shape) else np.asarray(v).tolist())
                for f in dataclasses.fields(self) for v in (getattr(self, f.name),)}
