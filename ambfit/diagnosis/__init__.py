"""Sim-to-real diagnosis: where the model fails, which effect explains it, the parameter-level gap.

The diagnosis runs in stages (:mod:`ambfit.diagnosis.attribution` holds :func:`diagnose`, which runs them):
:mod:`ambfit.diagnosis.residuals` (noise floor, structured regions),
:mod:`ambfit.diagnosis.heldout` (cross-validation folds, held-out excess and shrink),
:mod:`ambfit.diagnosis.scoring` (score: each model's held-out fits, as typed records),
:mod:`ambfit.diagnosis.signatures` (a family's law widened by its signature),
:mod:`ambfit.diagnosis.verdict` (decide: the :class:`Rules` and the pure :func:`decide`),
:mod:`ambfit.diagnosis.checks` (check: force measurement with each model),
:mod:`ambfit.diagnosis.discrepancy` (the discrepancy's ceiling),
:mod:`ambfit.diagnosis.circuit_families` (what each piece of the magnetic circuit contributes),
:mod:`ambfit.diagnosis.results` (the :class:`Diagnosis` record and its JSON),
:mod:`ambfit.diagnosis.text` (say: its sentences),
:mod:`ambfit.diagnosis.threads` (the fits run a few at a time) and
:mod:`ambfit.diagnosis.parameter_gap` (identified parameters against the bearing).
"""

from ambfit.diagnosis.attribution import diagnose
from ambfit.diagnosis.heldout import Candidate, excess, folds, heldout_residuals, shrink
from ambfit.diagnosis.parameter_gap import parameter_gap
from ambfit.diagnosis.residuals import NoiseFloor, Region, Where, noise_floor, operating_variables, where
from ambfit.diagnosis.results import Diagnosis
from ambfit.diagnosis.verdict import Rules, Verdict, decide

__all__ = ["Candidate", "Diagnosis", "NoiseFloor", "Region", "Rules", "Verdict", "Where", "decide", "diagnose",
           "excess", "folds", "heldout_residuals", "noise_floor", "operating_variables", "parameter_gap", "shrink",
           "where"]
