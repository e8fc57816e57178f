"""The paper's iterative search for the effective origin, run against the virtual rig.

"The current-position MPM is first applied at this initial location to determine
the corresponding position in effective coordinates (v_e, w_e) ... The effective
coordinates are used as an error signal to estimate a more correct rotor
position. The rotor is moved to new location according to the error estimate."
(seed paper, section "Current-Position Perturbation Algorithm").

Each iteration runs one symmetric perturbation (two biases at ``c ± d``) centred on
the current set-point ``c``, solves Eq. 5-7, and takes the effective offset
``e = c + x0_hat`` (where the set-point sits relative to the estimated effective
origin ``-x0_hat``) as the error signal: the next centre is ``c - e``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import pandas as pd

from ambfit.estimation import closed_form
from ambfit.physics.bearing import AXES
from ambfit.physics.effects import Effect
from ambfit.rig.protocol import perturbation
from ambfit.rig.virtual import Noise, RigSpec, RigState, simulate


@dataclasses.dataclass(frozen=True)
class OriginSearch:
    """Trajectory of the effective-origin search (SI units).

    Attributes
    ----------
    centers : array[n, 2]
        Set-point centre ``(v, w)`` [m] of each iteration.
    g0, x0 : array[n, 2]
        Closed-form gap and origin estimates [m] of each iteration.
    offsets : array[n, 2]
        Effective offset ``centre + x0`` [m] of each iteration (the error signal).
    converged : bool
        Whether the effective offset fell within ``tolerance`` on both axes.
    converged_at : int or None
        First iteration (from 1) at which it did.
    data : pandas.DataFrame
        Every reading of the search, contract format (one experiment, one
        iteration per search step).
    """

    centers: np.ndarray
    g0: np.ndarray
    x0: np.ndarray
    offsets: np.ndarray
    converged: bool
    converged_at: int | None
    tolerance: float
    data: pd.DataFrame
    truth: dict

    @property
    def n_iterations(self) -> int:
        return len(self.centers)

    @property
    def title(self) -> str:
        state = f"converged at iteration {self.converged_at}" if self.converged else "not converged"
        return f"effective-origin search ({state})"

    def display_rows(self) -> list[dict]:
        """One ``{column: text}`` row per iteration: set-point centre, effective offset and gap per axis [µm]."""
        rows = []
        for j in range(self.n_iterations):
            row = {"it": str(j + 1)}
            for a, ax in enumerate(AXES):
                row |= {f"{ax} centre [µm]": f"{self.centers[j, a] * 1e6:.2f}",
                        f"{ax} offset [µm]": f"{self.offsets[j, a] * 1e6:.2f}", f"g_{ax}0 [µm]": f"{self.g0[j, a] * 1e6:.2f}"}
            rows.append(row)
        return rows

    def to_json(self) -> dict:
        """Trajectory in µm for the command line's JSON output."""
        out = {"converged": self.converged, "converged_at": self.converged_at, "tolerance_um": self.tolerance * 1e6, "iterations": []}
        for j in range(self.n_iterations):
            row = {"iteration": j + 1}
            for a, ax in enumerate(AXES):
                row[f"{ax}_center_um"] = self.centers[j, a] * 1e6
                row[f"g_{ax}0_um"] = self.g0[j, a] * 1e6
                row[f"{ax}0_um"] = self.x0[j, a] * 1e6
                row[f"{ax}_offset_um"] = self.offsets[j, a] * 1e6
            out["iterations"].append(row)
        return out


def search(
    spec: RigSpec, *, biases=(1.4, 1.6), offset: float = 20e-6, start=(0.0, 0.0), tolerance: float = 1e-6,
    iterations: int = 10, run_all: bool = True, effects: Sequence[Effect] = (), noise: Noise = Noise(),
    seed: int = 0, experiment: str = "origin_search", load: str = "rotor", loads: dict | None = None,
    state: RigState | None = None, progress=None,
) -> OriginSearch:
    """Run the effective-origin search on the rig.

    Parameters
    ----------
    spec : RigSpec
    biases : pair of float
        The two bias settings [A].
    offset : float
        Half-distance ``d`` [m] of the symmetric position pair ``c ± d``.
    start : pair of float
        Initial set-point centre [m] (the paper starts at the back-up bearing centre, 0).
    tolerance : float
        The search has converged when both effective offsets are below this [m].
    iterations : int
        Largest number of iterations.
    run_all : bool
        Keep iterating to ``iterations`` after convergence (the paper's tables
        report 10 iterations); otherwise stop at convergence.
    effects, noise, seed, state :
        Passed to :func:`ambfit.rig.simulate`.
    load, loads :
        The static load of every step, a key of ``loads`` (default: the rig's rotor, ``spec.loads``).
    progress : callable, optional
        Called as ``progress("origin search", done, iterations)`` after each iteration
        (:mod:`ambfit.faces.cli.progress`).
    """
    rng = np.random.default_rng(seed)
    center = np.asarray(start, dtype=float)
    centers, g0s, x0s, offs, frames = [], [], [], [], []
    converged_at = None
    truth = None
    for it in range(1, iterations + 1):
        proto = perturbation(biases, (offset,), center=tuple(center), iterations=1, first_iteration=it,
                             experiment=experiment, load=load, loads=spec.loads if loads is None else loads)
        sim = simulate(spec, proto, effects, noise, seed=rng, state=state)
        state, truth = sim.state, sim.truth
        frame = sim.data
        try:
            est = closed_form.identify(frame)   # one iteration: no mean to compare with least squares
        except closed_form.ClosedFormError as exc:
            raise closed_form.ClosedFormError(
                f"origin search iteration {it} (centre {center[0] * 1e6:.2f}, {center[1] * 1e6:.2f} µm): {exc}"
            ) from None
        g = np.array([est.estimates[("all", ax)].g0 for ax in AXES])
        x = np.array([est.estimates[("all", ax)].x0 for ax in AXES])
        e = center + x
        centers.append(center.copy())
        g0s.append(g)
        x0s.append(x)
        offs.append(e)
        frames.append(frame)
        if progress is not None:
            progress("origin search", it, iterations)
        if converged_at is None and np.all(np.abs(e) < tolerance):
            converged_at = it
            if not run_all:
                break
        center = center - e
    return OriginSearch(
        centers=np.array(centers), g0=np.array(g0s), x0=np.array(x0s), offsets=np.array(offs),
        converged=converged_at is not None, converged_at=converged_at, tolerance=tolerance, data=pd.concat(frames, ignore_index=True), truth=truth or {},
    )
