"""The parameter-level gap: identified effective parameters against the bearing as drawn.

An effective gap is not the drawn air gap: machining tolerances move the real gap, and the ideal law's effective
gap also carries the iron's reluctance (``l_iron / (2 mu_r)``: 10 µm, 1.3 %, for the paper rig's 80 mm at
``mu_r = 4000``).  A gap therefore ``differs`` from the drawing when the difference exceeds ``n_sigma`` of its
standard error (an effective value, with the effects that could explain it), and is ``flagged`` only when it lies
beyond the drawing's tolerance band ``± GAP_TOLERANCE`` by more than ``n_sigma`` standard errors: a one-sided test
whose false-alarm rate on a bearing inside its tolerance is at most ``Φ(-n_sigma)`` (0.13 % at 3 sd).  A force
constant that differs from the drawing by more than ``n_sigma`` errors is flagged, with the effects that could
explain it; each explanation gives the magnitude it would need (judged against the bearing's calibration
tolerances and iron path) and the experiment that would separate them.
"""

from __future__ import annotations

import numpy as np

from ambfit.estimation.results import FitResult
from ambfit.physics.bearing import AXES, Bearing

MODEL_GAP_TOLERANCE = 0.02
"""A model with effects accounts for the ideal law's effective gap when its own gap is within this fraction of
the drawn gap (machining tolerances of radial bearings are of the order of 1 %)."""

GAP_TOLERANCE = 0.02
"""Half-width of the band around the drawn gap that an effective gap may take on a sound bearing, as a fraction
of the drawn gap: about 1 % machining tolerance plus about 1 % iron reluctance (module docstring)."""


def parameter_gap(result: FitResult, bearing: Bearing | None = None, n_sigma: float = 3.0,
                  model_fit: FitResult | None = None, gap_tolerance: float = GAP_TOLERANCE) -> list[dict]:
    """Identified effective parameters against the nominal rig, with the effects that could explain each
    difference (and the magnitude each would need) and the experiment that would separate them.

    ``bearing`` defaults to the one the fit used.  A difference counts when it exceeds ``n_sigma``
    standard errors (``differs``); a gap is ``flagged`` when it lies more than ``n_sigma`` standard errors beyond
    ``gap_tolerance`` (relative) of the drawn gap (``z_beyond_tolerance``).  ``model_fit``: a fit of a model with effects (the diagnosis' verdict); when its own
    gap is near the drawing, the ideal law's effective gap is explained by that model's physics, and it is
    listed first.
    """
    nominal = bearing or result.bearing
    out = []
    for ax in AXES:
        name = f"g_{ax}0"
        if name not in result.names:
            continue
        g, sg = result.value(name), result.error(name)
        diff = g - nominal.nominal_gap
        tol = gap_tolerance * nominal.nominal_gap
        beyond = (abs(diff) - tol) / sg
        entry = {"parameter": f"{name}_um", "identified": g * 1e6, "std": sg * 1e6, "nominal": nominal.nominal_gap * 1e6,
                 "difference": diff * 1e6, "z": diff / sg, "differs": bool(abs(diff) > n_sigma * sg),
                 "tolerance": tol * 1e6, "z_beyond_tolerance": beyond, "flagged": bool(beyond > n_sigma)}
        if entry["differs"]:
            rel = diff / nominal.nominal_gap
            expl = []
            if model_fit is not None and model_fit.effects and name in model_fit.names:
                gm, sm = model_fit.value(name), model_fit.error(name)
                off = (gm - nominal.nominal_gap) / nominal.nominal_gap
                expl.append({"effect": model_fit.model, "needs": f"nothing more: with it the gap is {gm * 1e6:.1f} "
                             f"± {sm * 1e6:.1f} µm, {off * 100:+.1f} % from the drawing; the ideal law's "
                             f"{diff * 1e6:+.1f} µm is that model's physics read as a gap",
                             "plausible": bool(abs(off) <= MODEL_GAP_TOLERANCE),
                             "note": f"its gap is {off * 100:+.1f} % from the drawing"})
            if diff > 0:
                mu = nominal.iron_path / (2 * diff)
                expl.append({"effect": "iron_reluctance", "needs": f"relative permeability {mu:.0f} over an "
                             f"equivalent iron length of {nominal.iron_path * 1e3:.0f} mm (b_th / mu_r = "
                             f"{2 * diff * 1e6:.1f} µm)", "plausible": bool(200 < mu < 20000)})
            expl.append({"effect": "position_gain", "needs": f"sensor gain error {rel * 100:+.2f} %",
                         "plausible": bool(abs(rel) <= 3 * nominal.position_gain_tolerance),
                         "note": f"calibration tolerance {nominal.position_gain_tolerance * 100:.2f} %"})
            expl.append({"effect": "fringing", "needs": "a gap-dependent pole area; shifts the effective gap by "
                         "a few per cent of the fringe width", "plausible": True})
            entry["could_be"] = expl
            entry["separate_by"] = [
                "a known-displacement calibration of the position sensor (moves only position_gain)",
                "a wider bias range up to saturation (iron reluctance grows with flux density; a sensor gain does not)",
                "repeating at a second air gap or rotor size (fringing scales with the gap; iron path does not)"]
        out.append(entry)
    k_nom = nominal.force_constant()
    for ax in AXES:
        name = f"k_{ax}"
        if name not in result.names:
            continue
        k, sk = result.value(name), result.error(name)
        differs = bool(abs(k - k_nom) > n_sigma * sk)
        entry = {"parameter": f"{name}_Nm2_per_A2", "identified": k, "std": sk, "nominal": k_nom,
                 "ratio": k / k_nom, "z": (k - k_nom) / sk, "differs": differs, "flagged": differs}
        if entry["flagged"]:
            entry["could_be"] = ([{"effect": "leakage", "needs": f"{(1 - np.sqrt(k / k_nom)) * 100:.1f} % of "
                                   "the flux missing the gap"}] if k < k_nom else
                                 [{"effect": "fringing", "needs": f"effective pole area +{(k / k_nom - 1) * 100:.1f} %"}])
            entry["separate_by"] = ["a flux probe (Hall sensor) in one gap",
                                    "known loads at several gaps (fringing depends on the gap, leakage less)"]
        out.append(entry)
    return out
