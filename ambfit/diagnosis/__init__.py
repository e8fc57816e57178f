"""Sim-to-real diagnosis: where the model fails, which effect explains it, the parameter-level gap.

:mod:`ambfit.diagnosis.residuals` (noise floor, structured regions),
:mod:`ambfit.diagnosis.heldout` (cross-validation folds, held-out excess and shrink),
:mod:`ambfit.diagnosis.attribution` (the candidates' held-out ranking and the verdict),
:mod:`ambfit.diagnosis.results` (the :class:`Diagnosis` record),
:mod:`ambfit.diagnosis.circuit_families` (what each piece of the magnetic circuit contributes),
:mod:`ambfit.diagnosis.discrepancy` (a family's own signature, the discrepancy's ceiling),
:mod:`ambfit.diagnosis.threads` (the fits run a few at a time) and
:mod:`ambfit.diagnosis.parameter_gap` (identified parameters against the bearing).
"""

from ambfit.diagnosis.attribution import diagnose
from ambfit.diagnosis.heldout import Candidate, excess, folds, heldout_residuals, shrink
from ambfit.diagnosis.parameter_gap import parameter_gap
from ambfit.diagnosis.residuals import NoiseFloor, Region, Where, noise_floor, operating_variables, where
from ambfit.diagnosis.results import Diagnosis

__all__ = ["Candidate", "Diagnosis", "NoiseFloor", "Region", "Where", "diagnose", "excess", "folds",
           "heldout_residuals", "noise_floor", "operating_variables", "parameter_gap", "shrink", "where"]
