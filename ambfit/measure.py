"""Force measurement from identified parameters: the paper's stated end goal.

Given a least-squares fit (with known loads, so that ``k`` is identified), the
force Eq. 4 predicts for any currents and position, with a standard error that
propagates the parameters' covariance (delta method) and, optionally, the
measurement noise of the inputs.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ambfit.fit import FitError, FitResult
from ambfit.model import ALPHA_DEFAULT, AXES, ideal_force


def force(result: FitResult, axis: str, i_top, i_bottom, x, *, sigma_i: float = 0.0, sigma_x: float = 0.0,
          alpha: float = ALPHA_DEFAULT) -> tuple[np.ndarray, np.ndarray]:
    """Bearing force [N] and its standard error for given currents [A] and position [m] on one axis.

    The paper's end goal.  The error propagates the parameters' covariance (delta
    method) and, if given, the measurement noise of the currents and position.
    Needs ``k`` of that axis, i.e. a fit with known loads.
    """
    if axis not in AXES:
        raise ValueError(f"axis must be one of {AXES}, got {axis!r}")
    names = (f"g_{axis}0", f"{axis}0", f"k_{axis}")
    if names[2] not in result.names:
        raise FitError(f"the force on axis {axis} needs k_{axis}, which this fit could not identify "
                       "(no known load on that axis)")
    idx = [result.names.index(n) for n in names]
    p = result.values[idx]
    cov = result.cov[np.ix_(idx, idx)]
    it, ib, xx = (jnp.asarray(np.broadcast_to(v, np.broadcast(i_top, i_bottom, x).shape), dtype=float)
                  for v in (i_top, i_bottom, x))

    def f(q, it, ib, xx):
        return ideal_force(q[0], q[1], q[2], it, ib, xx, alpha)

    val = f(jnp.asarray(p), it, ib, xx)
    jp = jax.vmap(jax.grad(f), in_axes=(None, 0, 0, 0))(jnp.asarray(p), it.ravel(), ib.ravel(), xx.ravel())
    var = jnp.einsum("ni,ij,nj->n", jp, jnp.asarray(cov), jp).reshape(val.shape)
    if sigma_i or sigma_x:
        d = jax.vmap(jax.grad(lambda a, b, c: f(jnp.asarray(p), a, b, c), argnums=(0, 1, 2)))(
            it.ravel(), ib.ravel(), xx.ravel())
        var = var + ((d[0] * sigma_i) ** 2 + (d[1] * sigma_i) ** 2 + (d[2] * sigma_x) ** 2).reshape(val.shape)
    return np.asarray(val), np.sqrt(np.asarray(var))
