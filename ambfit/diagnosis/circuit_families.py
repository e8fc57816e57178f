"""What each piece of the magnetic circuit contributes to a diagnosis, named as the contract's effect families.

When the verdict is the magnetic circuit of the whole bearing
(:class:`~ambfit.physics.effects.MagneticCircuit`), each of its pieces is switched off in turn and
the circuit refitted; the rise of χ² says which families (saturation, iron reluctance, fringing,
leakage, cross-coupling) the data need.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd

from ambfit.estimation.fit import fit
from ambfit.estimation.results import FitResult
from ambfit.physics.bearing import Bearing


@dataclasses.dataclass(frozen=True)
class CircuitFamily:
    """What one piece of the magnetic circuit contributes: the rise of χ² when it is switched off.

    Attributes
    ----------
    piece, family : str
        The circuit's piece and the contract family it stands for.
    delta_chi2 : float
        The rise of χ² as the refit stands; ``delta_chi2_bounds`` what it may still become.
    significant : bool
        Whether the rise clears the significance threshold (its lower bound does).
    converged : bool
        Whether the refit is settled (:data:`SETTLED_EDM`).
    decided : bool
        Whether the significance is (an undecided piece is not ``significant``).
    edm : float
    steps : int
        The refit's EDM and step count.
    """

    piece: str
    family: str
    delta_chi2: float
    delta_chi2_bounds: tuple
    significant: bool
    converged: bool
    decided: bool
    edm: float
    steps: int

    def to_json(self) -> dict:
        return dataclasses.asdict(self) | {"delta_chi2_bounds": list(self.delta_chi2_bounds)}

SETTLED_EDM = 0.01
"""A refit with a piece switched off is settled when its EDM (the χ² a Gauss-Newton step would still gain) is
below this fraction of the significance threshold: its χ² rise is then known far better than the verdict needs
(``EDM_MAX`` asks for 1e-3 standard errors of every parameter, which a refit whose χ² is 10^5 above the
full model's approaches only linearly)."""

EDM_MARGIN = 100.0
"""Before it is settled, a refit's χ² is taken to fall by at most this many EDMs more; a piece is decided
significant when its rise clears the threshold by that margin, and not significant as soon as its rise is below
the threshold (χ² only falls as the refit goes on).  The margin is an estimate, not a bound: far from the
minimum the Gauss-Newton EDM can understate what is left (on the FEM bearing an ideal-iron refit that stops at EDM
34 has a χ² 590, 17 EDMs, above what a run from a nearer start reaches), hence 100.  A piece neither decided
significant nor not is ``undecided`` and left out of the verdict."""


def circuit_families(data: pd.DataFrame, full: FitResult, bearing: Bearing, max_steps: int = 200, step: int = 20,
                     significance: float = 3.0, each=None, **noise) -> list[CircuitFamily]:
    """What each piece of the magnetic circuit contributes, as contract families, largest first.

    Each piece is switched off in turn and the circuit refitted to the same rows with the full model's noise
    weights held (:meth:`Problem.with_noise`: every χ² weighs the readings alike, and Levenberg-Marquardt
    minimises a fixed sum of squares); its contribution is the rise of χ².  ``saturation``: the B-H curve
    replaced by a constant permeability (what the curve's knee adds); ``iron_reluctance``: ideal iron instead of
    that constant permeability (what a finite permeability adds); ``fringing``, ``leakage``, ``cross_coupling``
    (the horseshoes' shared back iron).

    A refit runs ``step`` steps at a time (per reweighting round) until it is settled (:data:`SETTLED_EDM`) or
    its piece's significance is decided (:data:`EDM_MARGIN`), at most ``max_steps`` steps in all.  A piece is
    significant when switching it off raises χ² by more than ``significance`` of χ²'s standard deviations
    ``sqrt(2 dof)`` (:attr:`ambfit.diagnosis.verdict.Rules.circuit_dchi2`).  Returns one :class:`CircuitFamily`
    per piece, largest rise first.  ``full`` is the circuit's fit of ``data``'s rows in their order, its noise not
    held (the refits hold the noise its solve measured).  ``each(fn, items)``, if given, maps the pieces' refits
    (a diagnosis passes its thread pool; default one after another, with the same results).
    """
    from ambfit.estimation.measure import force_noise
    from ambfit.physics.effects import MagneticCircuit

    mec = next(e for e in full.effects if isinstance(e, MagneticCircuit))
    threshold = significance * np.sqrt(2.0 * max(full.dof, 1))
    names = {"saturation": "saturation", "iron": "iron_reluctance", "fringing": "fringing", "leakage": "leakage",
             "coupling": "cross_coupling"}
    # the noise the full fit's solve measured at its estimate (see the docstring), else propagated anew
    held = full.row_noise if full.row_noise is not None and len(full.row_noise) == len(data) \
        else force_noise(full, data, **noise)
    # the same rows as the full fit, none dropped by an outlier test: χ² must compare like with like
    keep = full.fitted_rows.astype(float)
    off = {p: mec.without(p) for p in MagneticCircuit.PIECES}
    refits, spent = {}, dict.fromkeys(MagneticCircuit.PIECES, 0)

    def bounds(piece) -> tuple[float, float, float]:
        """The piece's contribution from the refits as they stand, and its (lower, upper) bounds."""
        f = refits[piece]
        ref = refits.get("saturation") if piece == "iron" else None
        if ref is None:
            rise = f.chi2 - full.chi2
            return rise, rise - _margin(f, threshold), rise
        rise = f.chi2 - ref.chi2
        return rise, rise - _margin(f, threshold), rise + _margin(ref, threshold)

    def decided(piece) -> bool:
        _, lo, hi = bounds(piece)
        return lo > threshold or hi <= threshold

    def refine(piece) -> None:
        # ideal iron starts from constant-permeability iron, the nearer model (neither has the B-H curve's knee)
        f = refits.get(piece) or _idle_centred(refits.get("saturation", full) if piece == "iron" else full,
                                               off[piece], bearing)
        while spent[piece] < max_steps:
            # alpha=0: no reading is tested as an outlier (a refit without a piece misfits many; naming them
            # would cost a Cauchy-weighted refit per call and change nothing here)
            f = fit(data, [off[piece]], bearing=bearing, start_from=f, max_steps=step, throw=False, mask=keep,
                    loss="linear", alpha=0.0, held_noise=held, debias="none", **noise)
            refits[piece] = f
            spent[piece] += max(f.num_steps, 1)
            if _settled(f, threshold) or decided(piece):
                return

    def chain(pieces) -> None:
        for piece in pieces:
            refine(piece)

    # the pieces' refits are independent but for ideal iron, which starts from (and is measured against) the
    # linear-iron refit: one chain per piece, iron after saturation, run ``each`` at a time (the solves release the
    # interpreter); the refits are the same run one after another
    first = [p for p in MagneticCircuit.PIECES if p != "iron" and (p != "saturation" or bearing.b_curve)]
    chains = [("saturation", "iron") if p == "saturation" else (p,) for p in first]
    if not bearing.b_curve:
        chains.insert(0, ("iron",))        # linear iron already: nothing to switch off but the iron itself
    (each or (lambda fn, items: [fn(x) for x in items]))(chain, chains)
    if "saturation" in refits and not decided("iron") and not _settled(refits["saturation"], threshold):
        refine("saturation")               # the iron's part is measured from the linear-iron refit
    out = []
    for piece, f in ((p, refits[p]) for p in MagneticCircuit.PIECES if p in refits):     # in a fixed order
        rise, lo, hi = bounds(piece)
        out.append(CircuitFamily(piece=piece, family=names[piece], delta_chi2=rise, delta_chi2_bounds=(lo, hi),
                                 significant=bool(lo > threshold), converged=_settled(f, threshold),
                                 decided=bool(decided(piece)), edm=f.edm, steps=spent[piece]))
    return sorted(out, key=lambda r: -r.delta_chi2)


def _idle_centred(f: FitResult, mec, bearing: Bearing) -> FitResult:
    """``f`` as a start for the circuit ``mec``: the parameters its pieces that are off leave without effect at their
    prior centre, where the refit's prior would take them (from ``f``'s values it drags them there step by step)."""
    from ambfit.estimation.core import Model

    model = Model.of([mec], bearing)
    idle = set(mec.idle)
    theta = np.array(f.theta, dtype=float)
    first = len(theta) - model.n
    for j, name in enumerate(model.names()):
        if name.split(".", 1)[1].split("[")[0] in idle:
            theta[first + j] = 0.0                       # (an effect parameter's prior centre is q = 0)
    return dataclasses.replace(f, theta=theta)


def _settled(f: FitResult, threshold: float) -> bool:
    return bool(f.edm < SETTLED_EDM * threshold)


def _margin(f: FitResult, threshold: float) -> float:
    """How much further a refit's χ² may still fall: nothing once settled, else :data:`EDM_MARGIN` EDMs."""
    return 0.0 if _settled(f, threshold) else EDM_MARGIN * f.edm
