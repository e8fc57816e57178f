"""Why a least-squares fit did not converge, in words: how the solver stopped, and what dragged it.

Levenberg-Marquardt (:mod:`ambfit.estimation.lm`) stops a round on its step budget or on optimistix's Cauchy
test, which is relative: on residuals of thousands of standard deviations and a trust region shrunk by rejected
steps, both the step and the relative change of the residuals are small far from any minimum, and the solver
reports ``successful`` at a point whose EDM says it is not the minimum.  One reading the law cannot explain (a
coil current written as 0, a load of the wrong sign) drags plain least squares there, typically out of the
physical region, where a pole gap closes and the force law has a pole.  :func:`not_converged` says which of
these happened, with the reading furthest off, so the message names the cause rather than the solver's label.
"""

from __future__ import annotations

import numpy as np

from ambfit.physics.bearing import AXES


def _solver_stop(optimistix: str, num_steps: int, max_steps: int) -> str:
    if optimistix == "successful":
        return (f"least squares stalled after {num_steps} steps: its steps became too small to make progress "
                "(the solver's relative stopping test passed) at a point that is not the minimum")
    if "maximum number of steps" in optimistix:
        return f"least squares did not converge within {max_steps} steps per round"
    return "least squares failed: " + optimistix.split("<", 1)[-1].rstrip(">")


def _unphysical(values: dict, nominal: float) -> str:
    """The estimates outside the physical region (a gap that is not positive, an origin beyond its gap)."""
    out = []
    for ax in AXES:
        g, x0 = values.get(f"g_{ax}0"), values.get(f"{ax}0")
        if g is None or x0 is None or not (np.isfinite(g) and np.isfinite(x0)):
            continue
        if g <= 0 or abs(x0) >= g or g > 10 * nominal:
            out.append(f"g_{ax}0 = {g * 1e6:.4g} µm, {ax}0 = {x0 * 1e6:.4g} µm")
    return "; ".join(out)


def not_converged(res, edm_max: float) -> str:
    """The cause of a fit's failure to converge (``res``: a :class:`~ambfit.estimation.results.FitResult`), with
    the estimates that left the physical region and the reading furthest off, and what to do."""
    text = _solver_stop(res.optimistix, res.num_steps, res.thresholds.max_steps)
    text += f" (EDM {res.edm:.2g}, limit {edm_max:g})"
    away = _unphysical(dict(zip(res.names, res.values)), res.bearing.nominal_gap)
    if away:
        text += f"; the estimate left the physical region ({away}: a pole gap closed)"
    z = np.abs(np.asarray(res.residuals, dtype=float))
    if not away and z.size and np.isfinite(z).any():        # (out of the physical region every residual is off)
        j = int(np.nanargmax(np.where(np.isfinite(z), z, -np.inf)))
        row = int(res.rows[j]) if res.rows is not None else j + 1
        text += f"; the reading furthest off is row {row} ({z[j]:.3g} σ)"
    return (text + ". A reading the law cannot explain drags plain least squares there: ambfit check names readings "
            "the bearing cannot produce (a coil current written as 0, a unit mistake); or give a better start")
