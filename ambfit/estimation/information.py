"""Fisher information and the Cramér-Rao bound for any perturbation design.

For the effective-variance likelihood of :mod:`ambfit.estimation.fit` (Gaussian reading
noise, the equilibrium constraint linearised around the true readings) the
Fisher information of the scaled parameters is ``I = J^T J`` with ``J`` the
Jacobian of the standardized residuals at the truth, evaluated on noise-free
readings.  ``inv(I)`` is the Cramér-Rao bound: no unbiased estimator using the
same data can have a smaller covariance.  It is the yardstick for every
estimator here (closed form, least squares, posterior).

A design is anything :func:`ambfit.rig.simulate` can run: the information is
computed from the rig's noise-free readings of it, with the declared noise.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pandas as pd

from ambfit.estimation.core import Model, build_problem, free_mask, free_names, jacobian, param_scale, to_theta
from ambfit.physics.bearing import PAPER_BEARING, Bearing
from ambfit.physics.model import BearingParams, evaluate


@dataclasses.dataclass(frozen=True)
class Information:
    """Fisher information of a design and what follows from it (SI units).

    Attributes
    ----------
    names : list[str]
    matrix : array[p, p]
        Fisher information of the parameters in SI units.
    crlb : array[p, p]
        Its inverse, the Cramér-Rao bound on the covariance.
    condition : float
        Condition number of the column-scaled Jacobian (as the fit reports it).
    weakest : dict
        The least-informed direction: ``{name: component}`` of the smallest
        eigenvector of the correlation-scaled information.
    """

    names: list
    matrix: np.ndarray
    crlb: np.ndarray
    condition: float
    weakest: dict

    def std(self, name: str) -> float:
        """Square root of the bound for one parameter (its smallest possible standard error)."""
        j = self.names.index(name)
        return float(np.sqrt(self.crlb[j, j]))

    def table(self) -> pd.DataFrame:
        return pd.DataFrame({"param": self.names, "crlb_std": [self.std(n) for n in self.names]})


def fisher(data: pd.DataFrame, params: BearingParams, loads: dict | None = None, *, sigma_i: float | None = None,
           sigma_x: float | None = None, bearing: Bearing = PAPER_BEARING) -> Information:
    """Fisher information of the readings ``data`` (noise-free, contract table) at ``params``.

    ``loads`` maps the design's nuisance load groups (``"<load_id>|<axis>"``) to
    their true values [N]; groups not given are set to the mean force the model
    predicts for them (exact for noise-free data).
    """
    prob, meta = build_problem(data, sigma_i=sigma_i, sigma_x=sigma_x)
    model = Model.of((), bearing)
    f = np.asarray(evaluate(params, prob.readings, bearing=bearing)[0])
    gidx = np.asarray(prob.gidx)
    lv = np.array([(loads or {}).get(g, np.mean(f[gidx == j])) for j, g in enumerate(meta.load_groups)])
    theta = jnp.asarray(to_theta(np.asarray(params.g0), np.asarray(params.x0), np.asarray(params.k), lv))
    free = free_mask(prob, meta)
    j = np.asarray(jacobian(theta, prob, model))[:, free]
    names = free_names(meta, free)
    scale = param_scale(prob.n_loads)[free]
    info_s = j.T @ j
    norms = np.sqrt(np.diag(info_s))
    corr_info = info_s / np.outer(norms, norms)
    w, v = np.linalg.eigh(corr_info)
    cond = float(np.sqrt(w[-1] / w[0])) if w[0] > 0 else np.inf
    # A singular information matrix leaves some combinations unbounded: their parameters get an
    # infinite bound, not the pseudo-inverse's misleading finite number.
    null = w < 1e-12 * w[-1]
    crlb_s = np.linalg.pinv(info_s)
    if null.any():
        loaded = np.any(np.abs(v[:, null]) > 1e-6, axis=1)
        crlb_s[loaded, :] = np.inf
        crlb_s[:, loaded] = np.inf
    weakest = {n: float(c) for n, c in zip(names, v[:, 0])}
    return Information(names=names, matrix=info_s / np.outer(scale, scale), crlb=crlb_s * np.outer(scale, scale),
                       condition=cond, weakest=weakest)


def design_information(spec, protocol, noise, *, loads: dict | None = None) -> Information:
    """Fisher information of running ``protocol`` on rig ``spec`` with sensor ``noise`` (a :class:`ambfit.rig.Noise`)."""
    from ambfit import rig

    sim = rig.simulate(spec, protocol, noise=rig.NOISE_FREE)
    return fisher(sim.data, spec.params(), loads, sigma_i=noise.current, sigma_x=noise.position, bearing=spec.bearing)
