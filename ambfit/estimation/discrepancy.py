"""A model-discrepancy term: what no physical parameter of the model can express (Kennedy and O'Hagan 2001).

The force is the physical model plus a smooth correction,
``F = F_model(theta) + delta(readings)``.  ``delta`` is a finite basis with a Gaussian prior on its
coefficients, i.e. a degenerate Gaussian process (Rasmussen and Williams 2006, section 2.1), built from what
shapes a horseshoe's force (:mod:`ambfit.estimation.basis`): by default its flux density and gap, the other
axis, and the direction from which each coil current was approached; a family's signature groups on request.

**Kept from swallowing gap, origin and k** (Plumlee 2017, "Bayesian calibration of computer models using
orthogonal discrepancy", doi:10.1080/01621459.2016.1211016): the basis is projected onto the orthogonal
complement of the model's Jacobian columns (every fitted parameter: gap, origin, k, loads, effect parameters)
in the fit's weighted metric.  The physical parameters therefore stay the physical law's best fit; the
correction carries only what the law cannot express.  What an unconstrained correction would have done to
them is reported (:attr:`Discrepancy.unconstrained_shift`): in the joint linear problem it moves the
parameters by ``-A c`` (``A`` the projection coefficients, ``c`` the correction's coefficients), which is
exactly how much of the correction the parameters could have absorbed.  Fitted on other rows than the fit used
(``mask``: its outliers among them), the parameters are first refitted to those rows, linearised; the correction
(:attr:`Discrepancy.row_correction`) carries that move too.

The prior scale of the coefficients is chosen by maximising the marginal likelihood (type-II maximum
likelihood) over a grid; the coefficients' posterior gives the correction's standard error.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd

from ambfit.data import Dataset, zero_based
from ambfit.estimation.basis import GROUPS, Basis
from ambfit.estimation.core import Model, build_problem, free_mask, noise_std, row_jacobian, si_scale
from ambfit.estimation.results import FitResult

TAU_GRID = np.logspace(-7, 2, 19)
"""Prior standard deviations tried for each group's coefficients (dimensionless: a fraction of ``F_ref``)."""


@dataclasses.dataclass(frozen=True)
class Discrepancy:
    """A fitted correction: its coefficients, their posterior, and how it was kept off the physical parameters.

    Attributes
    ----------
    basis : Basis
    coef, cov : array[m], array[m, m]
        Posterior mean and covariance of the coefficients.
    projection : array[p, m]
        Regression of each basis function on the physical parameters' force sensitivities (SI units of
        the parameter per unit coefficient), for the ``names`` of the model (loads excluded).
    names : tuple of str
        Physical parameters the projection refers to.
    tau : dict
        Each group's prior sd chosen by the marginal likelihood (0: the data do not want the group).
    log_bayes : dict
        Each group's log Bayes factor: the log marginal likelihood with the group against without it (the
        other groups at their scales); above 5 the data want it strongly (Kass and Raftery 1995).
    effective_parameters : float
        ``sum(s^2 / (1 + s^2))`` over the singular values ``s`` of the prior-scaled basis: how many
        coefficients the data determine.
    row_correction, row_correction_n : array[n]
        The correction on every row of the data it was fitted on (held-out rows too), in standardized units
        and in newtons; with the parameters' refit when fitted on other rows than the fit used (:meth:`correction`
        at other readings carries the basis' part alone).
    row_noise_n : array[n]
        Each of those rows' force noise std [N] (the unit of the standardized correction).
    row_variance : array[n]
        The variance of the correction on each of those rows from its coefficients' uncertainty, in standardized
        units (what a held-out reading's prediction variance gains).
    unconstrained_shift : dict
        ``{name: (shift, shift / std)}``: how far an unconstrained correction (not projected) would move each
        physical parameter, in SI units and in the parameter's standard errors.
    """

    basis: Basis
    coef: np.ndarray
    cov: np.ndarray
    projection: np.ndarray
    names: tuple
    tau: dict
    log_bayes: dict
    effective_parameters: float
    row_correction: np.ndarray
    row_correction_n: np.ndarray
    unconstrained_shift: dict
    row_noise_n: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    row_variance: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))

    def correction(self, readings, sensitivity: np.ndarray, frame=None) -> tuple[np.ndarray, np.ndarray]:
        """The correction [N] at other readings and its standard error.

        ``sensitivity``: ``dF/d(parameter)`` [N per SI unit] of the physical model at those readings, one
        column per entry of :attr:`names` (the projection needs it); ``frame``: their table, when the basis
        follows each coil's path (its memory and fading groups).
        """
        g = self.basis.matrix(readings, frame) - np.asarray(sensitivity) @ self.projection
        return g @ self.coef, np.sqrt(np.maximum(np.sum((g @ self.cov) * g, axis=1), 0.0))

    def largest(self, n: int = 5) -> list[dict]:
        """The ``n`` basis terms that carry most of the correction (coefficient over its standard error)."""
        std = np.sqrt(np.maximum(np.diag(self.cov), 1e-300))
        order = np.argsort(-np.abs(self.coef / std))[:n]
        terms = self.basis.terms()
        return [{"group": terms[j][0], "term": terms[j][1], "coefficient": float(self.coef[j]),
                 "sigma": float(self.coef[j] / std[j])} for j in order]

    def summary(self, n_terms: int = 5) -> dict:
        """What the correction says, without its matrices: prior scales, Bayes factors, the largest terms, and
        what an unconstrained correction would have done to the parameters."""
        return {"tau": self.tau, "log_bayes": self.log_bayes, "effective_parameters": self.effective_parameters,
                "largest_terms": self.largest(n_terms),
                "unconstrained_shift": {k: {"shift": v[0], "sigma": v[1]} for k, v in self.unconstrained_shift.items()}}

    def to_json(self) -> dict:
        return {"basis": self.basis.to_json(), "terms": [t for _, t in self.basis.terms()],
                "coefficients": self.coef.tolist(), "covariance": self.cov.tolist(),
                "projection": self.projection.tolist(), "names": list(self.names),
                "orthogonal_to": "every fitted parameter (Plumlee 2017)", **self.summary()}

    @classmethod
    def from_json(cls, record: dict) -> Discrepancy:
        basis = Basis.from_json(record["basis"])
        coef = np.asarray(record["coefficients"], dtype=float)
        cov = np.asarray(record["covariance"], dtype=float)
        proj = np.asarray(record["projection"], dtype=float)
        m = len(basis.terms())
        if coef.shape != (m,) or cov.shape != (m, m) or proj.shape != (len(record["names"]), m):
            raise ValueError(f"the discrepancy has {m} basis terms but {coef.shape} coefficients, a "
                             f"{cov.shape} covariance and a {proj.shape} projection")
        return cls(basis=basis, coef=coef, cov=cov, projection=proj, names=tuple(record["names"]),
                   tau=dict(record["tau"]), log_bayes=dict(record.get("log_bayes", {})),
                   effective_parameters=float(record["effective_parameters"]), row_correction=np.zeros(0),
                   row_correction_n=np.zeros(0), unconstrained_shift={})


class _Evidence:
    """log N(y | 0, sigma^2 (I + X diag(scale^2) X^T)) for grids of ``scale`` vectors; sigma = 1 for known noise,
    else profiled.

    With ``G = X^T X`` and ``g = X^T y`` computed once, ``Xs = X diag(scale)`` and ``C = I + Xs^T Xs``:
    ``det(I + Xs Xs^T) = det C`` and ``y^T (I + Xs Xs^T)^-1 y = |y|^2 - g_s^T C^-1 g_s`` with ``g_s = Xs^T y``
    (all m x m).  :meth:`along` and :meth:`common` give a whole grid of one scale from one factorization.
    """

    def __init__(self, x, y, noise_known: bool):
        self.gram, self.g, self.yy, self.n = x.T @ x, x.T @ y, float(y @ y), len(y)
        self.noise_known = noise_known

    def _log(self, quad, logdet):
        if self.noise_known:
            return -0.5 * (quad + logdet + self.n * np.log(2 * np.pi))
        return -0.5 * (self.n * np.log(2 * np.pi * quad / self.n) + self.n + logdet)

    def common(self, grid) -> np.ndarray:
        """The log evidence with every column at each scale of ``grid`` (one eigendecomposition of ``G``)."""
        lam, vec = np.linalg.eigh(self.gram)
        c2 = (vec.T @ self.g) ** 2
        t2 = np.asarray(grid, dtype=float)[:, None] ** 2
        return self._log(self.yy - np.sum(t2 * c2 / (1.0 + t2 * lam), axis=1),
                         np.sum(np.log1p(t2 * np.maximum(lam, 0.0)), axis=1))

    def along(self, scales, cols, grid) -> np.ndarray:
        """The log evidence at ``scales`` [m] with the columns ``cols`` (bool [m]) set to each scale of ``grid``.

        With the other columns ``A`` fixed, ``C`` factors through ``C_A = I + S_A G_AA S_A``: ``det C = det C_A
        det(I + t^2 M)`` and ``g_s^T C^-1 g_s = a + t^2 w^T (I + t^2 M)^-1 w``, where ``M = G_BB - G_BA S_A
        C_A^-1 S_A G_AB``, ``w = g_B - G_BA S_A C_A^-1 S_A g_A`` and ``a = g_A^T S_A C_A^-1 S_A g_A`` (block
        elimination): one Cholesky of ``C_A`` and one eigendecomposition of ``M`` for the whole grid.
        """
        a_, b_ = ~cols, cols
        sa = np.asarray(scales, dtype=float)[a_]
        chol = np.linalg.cholesky(np.eye(len(sa)) + sa[:, None] * self.gram[np.ix_(a_, a_)] * sa[None, :])
        # h = L_A^-1 S_A [G_AB, g_A]; h^T h = [G_BA, g_A^T] S_A C_A^-1 S_A [G_AB, g_A]
        h = np.linalg.solve(chol, sa[:, None] * np.column_stack([self.gram[np.ix_(a_, b_)], self.g[a_]]))
        proj = h.T @ h
        m_ = self.gram[np.ix_(b_, b_)] - proj[:-1, :-1]
        w = self.g[b_] - proj[:-1, -1]
        a = float(proj[-1, -1])
        lam, vec = np.linalg.eigh(0.5 * (m_ + m_.T))
        lam = np.maximum(lam, 0.0)                            # PSD up to round-off
        c2 = (vec.T @ w) ** 2
        t2 = np.asarray(grid, dtype=float)[:, None] ** 2
        logdet = 2.0 * np.sum(np.log(np.diagonal(chol))) + np.sum(np.log1p(t2 * lam), axis=1)
        return self._log(self.yy - a - np.sum(t2 * c2 / (1.0 + t2 * lam), axis=1), logdet)


def _scales(x, y, group, n_groups, noise_known):
    """Each group's prior sd by coordinate ascent of the marginal likelihood over ``TAU_GRID`` and 0, and each
    group's log Bayes factor (with it against without it, the others at their scales).  Each step evaluates the
    whole grid of one group from one factorization (:meth:`_Evidence.along`).

    The marginal likelihood of several groups has several maxima (two groups that carry the same structure: either
    takes it).  The ascent starts from every group at one common scale; a group that alone reaches a higher
    marginal likelihood than that ascent's maximum starts an ascent of its own, and the highest maximum is kept."""
    evidence = _Evidence(x, y, noise_known)
    grid = np.concatenate([[0.0], TAU_GRID])

    def ascend(t):
        value = -np.inf
        for _ in range(2):
            for g in range(n_groups):
                vals = evidence.along(t[group], group == g, grid)
                j = int(np.argmax(vals))
                t[g], value = grid[j], vals[j]
        return t, value

    tau, best = ascend(np.full(n_groups, TAU_GRID[int(np.argmax(evidence.common(TAU_GRID)))]))
    for g in range(n_groups if n_groups > 1 else 0):
        alone = evidence.along(np.zeros(len(group)), group == g, TAU_GRID)
        if np.max(alone) > best:
            t, value = ascend(np.where(np.arange(n_groups) == g, TAU_GRID[int(np.argmax(alone))], 0.0))
            if value > best:
                tau, best = t, value
    without = np.array([evidence.along(tau[group], group == g, [0.0])[0] for g in range(n_groups)])
    return tau, best - without


def seen_rows(fit: FitResult, rows: np.ndarray) -> np.ndarray:
    """Of ``rows`` (bool), those with a finite residual under ``fit``, its outliers included: the rows a correction
    of a fit made without them learns from (where a law other than the fit's departs from it most, the fit sees
    outliers; the correction is what would explain them)."""
    return rows & np.isfinite(np.asarray(fit.residuals)[:len(rows)])


def _refit(jac: np.ndarray, z: np.ndarray, sw: np.ndarray, result: FitResult) -> np.ndarray:
    """The step of the (scaled) parameters that minimises ``|sw (z + jac step)|^2`` plus the effect parameters'
    priors ``|q + step|^2`` (``q ~ N(0, 1)``, the fit's own: :func:`ambfit.estimation.core.with_priors`)."""
    names = list(result.names)[:jac.shape[1]]
    effect = np.array(["." in name for name in names])
    q = np.asarray(result.theta, dtype=float)[:jac.shape[1]][effect]
    a = np.vstack([sw[:, None] * jac, np.eye(jac.shape[1])[effect]])
    return np.linalg.lstsq(a, -np.concatenate([sw * z, q]), rcond=None)[0]


def fit_discrepancy(result: FitResult, data: Dataset | pd.DataFrame, *, sigma_i: float | None = None,
                    sigma_x: float | None = None, mask=None, groups=GROUPS) -> Discrepancy:
    """The discrepancy of ``result``'s model on ``data`` (the rows the fit used, or ``mask``'s rows).

    ``sigma_i``, ``sigma_x`` must be those the fit was given; ``mask`` (1 fitted, 0 held out): the rows to fit
    the correction on, by default those the fit used (its weights); ``groups`` the basis groups to use
    (:data:`GROUPS`).  On the fit's own rows its parameters are not changed: see the module docstring for why they
    need not be; on others they are refitted, linearised, and the refit is part of :attr:`Discrepancy.row_correction`.
    """
    df = zero_based(data.frame if isinstance(data, Dataset) else data)
    prob, meta = build_problem(df, sigma_i=sigma_i, sigma_x=sigma_x)
    basis = Basis.of(result.bearing, groups, prob.readings)
    model = Model.of(result.effects, result.bearing)
    theta = np.asarray(result.theta, dtype=float)
    n = len(df)
    free = free_mask(prob, meta, model)
    rows = result.jacobian_rows
    # measured with the fit's solve, every row at weight 1: the same matrix
    jac = rows if rows is not None and rows.shape == (n, int(free.sum())) else row_jacobian(theta, prob, meta, model)
    s = result.row_noise
    if s is None or np.shape(s) != (n,):
        s = np.asarray(noise_std(theta, prob, model))
    own = result.row_weights[:n]
    w = own if mask is None else np.asarray(mask, dtype=float) ** 2
    sw = np.sqrt(w)[:, None]
    z = np.asarray(result.residuals)[:n]
    refit = np.zeros(n)
    if not np.allclose(w, own):
        # other rows or weights than the fit's: its parameters refitted to them, linearised, first (with the effect
        # parameters' priors, as the fit had them; at the fit's own they are at their minimum); what the
        # correction adds is orthogonal to them there too
        z = np.where(w > 0, z, 0.0)
        refit = jac @ _refit(jac, z, sw[:, 0], result)
        z = z + refit
    b = basis.matrix(prob.readings, df) / s[:, None]
    # the basis' regression on the parameters' columns (weighted), and what is left: orthogonal to them
    a = np.linalg.lstsq(sw * jac, sw * b, rcond=None)[0]
    b_perp = b - jac @ a
    used = w > 0
    x, y = (sw * b_perp)[used], -(np.sqrt(w) * z)[used]
    noise_known = not result.noise_estimated
    group = basis.group_index()
    tau_g, bayes = _scales(x, y, group, len(basis.groups), noise_known)
    tau = tau_g[group]
    xs = x * tau
    inner = np.linalg.inv(np.eye(xs.shape[1]) + xs.T @ xs)     # posterior covariance of coef / tau
    coef = tau * (inner @ xs.T @ y)
    neff = float(xs.shape[1] - np.trace(inner))               # sum s^2 / (1 + s^2)
    sigma2 = 1.0
    if not noise_known:
        resid = y - x @ coef
        sigma2 = float(resid @ resid) / max(len(y) - neff, 1.0)
    cov = sigma2 * inner * np.outer(tau, tau)
    row = b_perp @ coef + refit
    scale, _ = si_scale(prob, model)
    names = list(result.names)
    phys = [j for j, nm in enumerate(names) if not nm.startswith("load[")]
    a_si = a * scale[free][:, None]
    shift = -(a_si @ coef)
    unconstrained = {names[j]: (float(shift[j]), float(shift[j] / result.std[j]) if result.std[j] > 0 else np.inf)
                     for j in phys}
    return Discrepancy(basis=basis, coef=coef, cov=cov, projection=a_si[phys], names=tuple(names[j] for j in phys),
                       tau=dict(zip(basis.groups, map(float, tau_g))), log_bayes=dict(zip(basis.groups, map(float, bayes))),
                       effective_parameters=neff, row_correction=row, row_correction_n=row * s,
                       unconstrained_shift=unconstrained, row_noise_n=s,
                       row_variance=np.maximum(np.sum((b_perp @ cov) * b_perp, axis=1), 0.0))
