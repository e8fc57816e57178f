"""Force measurement from identified parameters: the paper's stated end goal.

Given a least-squares fit (with known loads, so that ``k`` is identified), the
force its model (Eq. 4 plus the fit's effects) predicts for any currents and position, with a standard error that
propagates the parameters' covariance (delta method) and, optionally, the
measurement noise of the inputs.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ambfit.estimation.fit import FitError, FitResult
from ambfit.physics.bearing import AXES
from ambfit.physics.model import BearingParams, Readings, evaluate


def force(result: FitResult, axis: str, i_top, i_bottom, x, *, y=0.0, sigma_i: float = 0.0,
          sigma_x: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Bearing force [N] and its standard error for given currents [A] and position [m] on one axis.

    The paper's end goal.  The error propagates the parameters' covariance (delta
    method) and, if given, the measurement noise of the currents and position.
    Needs ``k`` of that axis, i.e. a fit with known loads.  ``y`` is the other axis' position [m]
    (effects that couple the axes use it).  The error covers gap, origin and k; the effect
    parameters are held at their estimates.
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
    shape = np.broadcast(i_top, i_bottom, x, y).shape
    it, ib, xx, yy = (jnp.asarray(np.broadcast_to(v, shape), dtype=float) for v in (i_top, i_bottom, x, y))
    a = AXES.index(axis)
    others = {n: result.value(n) for n in ("g_v0", "g_w0", "v0", "w0") if n in result.names}

    def f(q, it, ib, xx, yy=0.0):
        g0 = jnp.array([others.get("g_v0", 1.0), others.get("g_w0", 1.0)]).at[a].set(q[0])
        x0 = jnp.array([others.get("v0", 0.0), others.get("w0", 0.0)]).at[a].set(q[1])
        params = BearingParams(g0, x0, jnp.full(2, q[2]))
        r = Readings.build(axis=jnp.full(jnp.shape(it), a), i_top=it, i_bottom=ib, x=xx, y=yy)
        return evaluate(params, r, result.effects, bearing=result.bearing)[0]

    val = f(jnp.asarray(p), it, ib, xx, yy)
    jp = jax.jacfwd(lambda q: f(q, it.ravel(), ib.ravel(), xx.ravel(), yy.ravel()))(jnp.asarray(p))
    var = jnp.einsum("ni,ij,nj->n", jp, jnp.asarray(cov), jp).reshape(val.shape)
    if sigma_i or sigma_x:
        q = jnp.asarray(p)
        ones = jnp.ones(it.size)
        d = [jax.jvp(lambda *z: f(q, *z, yy.ravel()), (it.ravel(), ib.ravel(), xx.ravel()),
                     tuple(ones if j == k else 0 * ones for j in range(3)))[1] for k in range(3)]
        var = var + ((d[0] * sigma_i) ** 2 + (d[1] * sigma_i) ** 2 + (d[2] * sigma_x) ** 2).reshape(val.shape)
    return np.asarray(val), np.sqrt(np.asarray(var))
