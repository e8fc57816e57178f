"""Sim-to-real diagnosis: where the model fails, which effect explains it, the parameter-level gap.

:mod:`ambfit.diagnosis.residuals` (noise floor, structured regions),
:mod:`ambfit.diagnosis.attribution` (held-out ranking, verdict, shrink) and
:mod:`ambfit.diagnosis.parameter_gap` (identified parameters against the bearing).
"""

from ambfit.diagnosis.attribution import Candidate, Diagnosis, diagnose, excess, folds, heldout_residuals, shrink
from ambfit.diagnosis.parameter_gap import parameter_gap
from ambfit.diagnosis.residuals import NoiseFloor, Region, Where, noise_floor, operating_variables, where

__all__ = ["Candidate", "Diagnosis", "NoiseFloor", "Region", "Where", "diagnose", "excess", "folds",
           "heldout_residuals", "noise_floor", "operating_variables", "parameter_gap", "shrink", "where"]
