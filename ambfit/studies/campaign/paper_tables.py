"""The seed paper's Tables 1 and 2 read as a campaign over iterations: drift inside Table 2, moves between
Table 1's experiments."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ambfit.studies.campaign.series import Series, drift
from ambfit.studies.campaign.steps import ALPHA, differences
from ambfit.studies.campaign.window import PARAMS


@dataclasses.dataclass(frozen=True)
class PaperOrigins:
    """The paper's Tables 1 and 2 read as a campaign over iterations (:func:`paper_origins`).

    Attributes
    ----------
    drifts : dict
        Parameter -> :class:`Drift` inside Table 2 [m per iteration].
    moves : dict
        Parameter -> :func:`differences` between Table 1's consecutive experiments, noise only (no drift).
    changes : dict
        Parameter -> :func:`differences` between Table 1's consecutive experiments, Table 2's drift (with its
        error) removed.
    first : int
        The first Table 2 iteration used (iteration 1 ran before the rotor was re-centred).
    iterations : int
        Iterations per experiment (Table 2's rows): each Table 1 row is their mean.
    sd : dict
        Parameter -> per-iteration sd of Table 2's iterations ``first``..``iterations`` [m]: each iteration's error,
        and over ``sqrt(iterations)`` each Table 1 row's.
    source : int
        Table 1's row whose iterations Table 2 lists.
    """

    drifts: dict
    moves: dict
    changes: dict
    first: int
    iterations: int
    sd: dict
    source: int


def paper_origins(*, first: int = 2, source: int = 2, alpha: float = ALPHA) -> PaperOrigins:
    """Drift inside the paper's Table 2 and change points between Table 1's experiments.

    The paper gives estimates, not readings, and no times, so the clock is the iteration: Table 1's three
    experiments are taken to have run one after another, 10 iterations each (experiment ``e`` at iterations
    ``10 (e - 1) + 1 .. 10 e``, its mean at their centre), Table 2 being the iterations of experiment
    ``source``.  Errors: each iteration's is the per-iteration sd of Table 2's iterations ``first``..10, each
    Table 1 row's that over ``sqrt(10)`` (the three experiments are assumed as noisy as Table 2's).  Each
    boundary is tested by :func:`differences` twice: against noise alone (did the origin move?) and with Table
    2's drift removed, its error included (did it move more than Table 2's drift explains?).  Three experiments
    cannot separate a drift from a jump on their own.
    """
    from ambfit.studies import paper

    t2, t1 = paper.load_table(2), paper.load_table(1)
    n = len(t2)
    it = t2["iteration"].to_numpy(float)
    keep = it >= first
    sel = t1["source_row"].astype(int).to_numpy()
    centre = (sel - 1) * n + 0.5 * (n + 1)
    drifts, moves, changes, sd = {}, {}, {}, {}
    for name in PARAMS:
        y = t2[f"{name}_um"].to_numpy(float)[keep] * 1e-6
        sd[name] = float(np.std(y, ddof=1))
        inside = Series(name, (source - 1) * n + it[keep], y, np.full(len(y), sd[name]),
                        labels=tuple(f"iteration {int(k)}" for k in it[keep]), time_unit="iteration",
                        seconds_per_unit=None)
        drifts[name] = drift(inside)
        between = Series(name, centre, t1[f"{name}_um"].to_numpy(float) * 1e-6,
                         np.full(len(t1), sd[name] / math.sqrt(n)), labels=tuple(str(r) for r in sel),
                         groups=tuple(str(r) for r in sel), time_unit="iteration", seconds_per_unit=None)
        moves[name] = differences(between, alpha=alpha)
        changes[name] = differences(between, drift=drifts[name], alpha=alpha)
    return PaperOrigins(drifts, moves, changes, first, n, sd, source)
