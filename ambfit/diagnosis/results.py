"""The diagnosis as a record: where the ideal model fails, the verdict, and its text, table and JSON forms."""

from __future__ import annotations

import dataclasses
import html

import numpy as np
import pandas as pd

from ambfit.diagnosis.heldout import Candidate
from ambfit.diagnosis.residuals import NoiseFloor, Where
from ambfit.estimation.results import FitResult
from ambfit.physics.bearing import AXES


@dataclasses.dataclass(frozen=True)
class Diagnosis:
    """Where the ideal model fails, which effect explains it on held-out data, how far the gap shrinks.

    Attributes
    ----------
    baseline : FitResult
        The ideal law fitted to every row.
    noise_floor, where :
        What the residuals would be if the model were right, and where they are structured.
    folds : str
        The cross-validation scheme.
    ideal : Candidate
        The ideal law's held-out score (the ``before`` of every candidate).
    ranking : list[Candidate]
        Candidates, best (lowest held-out score) first; pairs follow when no single effect explains the data.
    verdict : str
        An effect name, ``a+b`` for a pair, ``none`` or ``unexplained``.
    confounded_with : list[str]
        Candidates whose held-out score is statistically indistinguishable from the verdict's.
    shrink : float
        Held-out shrink of the verdict (or of the best single candidate when ``unexplained``).
    verdict_fit : FitResult or None
        The verdict's model fitted to every row: its residuals are the "after" of the residual map.
    operating : DataFrame
        Per-row operating variables (flux densities, positions, ...) the residuals are mapped against.
    parameter_gap : list[dict]
        Identified parameters against the bearing description.
    law : dict or None
        When the verdict's family was named by its signature: how much the library's law leaves and what the
        law widened by the signature removes (:meth:`ambfit.diagnosis.signatures.Signature.to_json`).
    grade : dict or None
        What the verdict's model removes and leaves: noise units, at the floor or not, whether it explains the
        data (:meth:`ambfit.diagnosis.verdict.Judge.grade`); None for ``none`` and ``unexplained``.
    signatures : list[dict] or None
        Every family's law widened by its signature, best first, when no law reached the floor.
    """

    baseline: FitResult
    noise_floor: NoiseFloor
    where: Where
    folds: str
    ideal: Candidate
    ranking: list
    verdict: str
    confounded_with: list
    shrink: float
    verdict_fit: FitResult | None
    operating: pd.DataFrame
    parameter_gap: list
    best_pair: dict | None = None
    families: list | None = None
    force_check: dict | None = None
    law: dict | None = None
    discrepancy: dict | None = None
    grade: dict | None = None
    signatures: list | None = None

    @property
    def residuals_before(self) -> np.ndarray:
        return self.baseline.residuals

    @property
    def residuals_after(self) -> np.ndarray | None:
        return None if self.verdict_fit is None else self.verdict_fit.residuals

    @property
    def heldout_excess_before(self) -> float:
        return self.ideal.after

    @property
    def most_structured_variable(self) -> str:
        return self.where.regions[0].variable if self.where.regions else "b_top_T"

    def to_json(self) -> dict:
        """The contract section 3 record, marked as a diagnose model file (schema, kind, ambfit version)."""
        from ambfit.estimation.model_file import stamp

        rec = {
            "baseline": "ideal", "noise_floor": self.noise_floor.to_json(), "folds": self.folds,
            "where": [r.to_json() for r in self.where.regions[:20]],
            "ranking": [c.to_json(self.ideal) for c in self.ranking], "verdict": self.verdict,
            "confounded_with": list(self.confounded_with), "shrink": self.shrink,
            "heldout_excess_before": self.heldout_excess_before,
            "parameters_baseline": {n: self.baseline.value(n) for n in self.baseline.names if not n.startswith("load[")},
            "goodness_of_fit": self.baseline.goodness_of_fit(),
            "parameter_gap": self.parameter_gap,
        }
        if blind := self.blind_spot():
            rec["blind_spot"] = blind
        if self.best_pair is not None:
            rec["best_pair"] = self.best_pair
        if self.families is not None:
            rec["verdict_model"] = "magnetic_circuit"
            rec["families"] = self.families
        if self.verdict_fit is not None and self.verdict_fit.effects:
            rec["verdict_params"] = {n: {"value": v, "std": s} for n, v, s in zip(
                self.verdict_fit.names, self.verdict_fit.values, self.verdict_fit.std) if not n.startswith("load[")}
        if self.force_check is not None:
            rec["force_check"] = self.force_check
        if self.law is not None:
            rec["law"] = self.law
        if self.grade is not None:
            rec["grade"] = self.grade
        if self.signatures is not None:
            rec["signatures"] = self.signatures
        rec["steps"] = self.steps()
        if self.discrepancy is not None:
            rec["discrepancy"] = {k: v for k, v in self.discrepancy.items() if k not in ("fit", "host", "folds")}
            if self.discrepancy.get("fit") is not None:
                rec["discrepancy"] |= self.discrepancy["fit"].summary()
        # what ambfit force needs to measure with either model
        rec["baseline_fit"] = {"model_state": self.baseline.model_state()}
        if self.verdict_fit is not None:
            rec["verdict_fit"] = {"model": self.verdict_fit.model, "model_state": self.verdict_fit.model_state()}
        if self.discrepancy is not None and self.discrepancy.get("fit") is not None:
            host = self.discrepancy["host"]
            rec["discrepancy_fit"] = {"model": f"{host.model}+discrepancy",
                                      "model_state": host.model_state() | {"discrepancy": self.discrepancy["fit"].to_json()}}
        return stamp(rec, "diagnose")

    def steps(self) -> list[dict]:
        """How the verdict was reached, each step with its held-out shrink: the first effect, then the second of
        a pair; for a family whose law differs, the library's law, then the law widened by its signature."""
        by_name = {c.effect: c for c in self.ranking}
        if self.verdict in ("none", "unexplained"):
            return []
        if self.law is not None and self.verdict == self.law["family"]:
            return [{"model": self.verdict, "shrink": self.law["library_law_shrink"]},
                    {"model": f"{self.verdict} widened by its {self.law['signature']} signature",
                     "shrink": self.law["shrink"]}]
        if self.families is not None:
            return [{"model": "magnetic_circuit", "shrink": self.shrink,
                     "families": [f["family"] for f in self.families if f["significant"]]}]
        parts = self.verdict.split("+")
        out = []
        for j in range(1, len(parts) + 1):
            c = by_name.get("+".join(parts[:j]))
            if c is not None:
                out.append({"model": c.effect, "shrink": c.shrink})
        return out

    def to_dataframe(self) -> pd.DataFrame:
        """The ranking as a table: effect, held-out excess after, shrink, in-sample mean z²."""
        return pd.DataFrame([{"effect": c.effect, "heldout_excess_after": c.after, "shrink": c.shrink,
                              "insample_mean_z2": float(np.mean(c.fit.residuals**2)), "converged": c.fit.converged}
                             for c in self.ranking])

    def ranking_rows(self) -> list[dict]:
        """The ranking as ``{column: text}`` rows (best first)."""
        return [{"effect": r.effect, "held-out excess after": f"{r.heldout_excess_after:.2f}",
                 "shrink": f"{r.shrink:.3f}", "in-sample mean z²": f"{r.insample_mean_z2:.2f}",
                 "fit": "converged" if r.converged else "not converged"}
                for r in self.to_dataframe().itertuples()]

    def where_rows(self, n: int = 8) -> list[dict]:
        """The largest structured regions as ``{column: text}`` rows."""
        return [{"region": w.describe(), "rows": str(w.rows), "z": f"{w.z:.1f}"} for w in self.where.regions[:n]]

    def floor_text(self) -> str:
        nf = self.noise_floor
        return (f"noise floor ({nf.source}): mean z² {nf.mean_z2:.2f} (expected {nf.expected_mean_z2:.2f}); "
                f"held-out excess {self.heldout_excess_before:.2f} noise units; folds: {self.folds}")

    def verdict_text(self) -> str:
        if self.verdict == "none":
            text = ("verdict: none (the ideal law's held-out residuals sit on the noise floor); these data cannot "
                    f"exclude: {', '.join(self.confounded_with) or 'nothing'}")
        else:
            text = (f"verdict: {self.verdict}; confounded with: {', '.join(self.confounded_with) or 'none'}; "
                    f"shrink {self.shrink:.3f}")
        failed = [c.effect for c in self.ranking if not c.fit.converged]
        if failed:
            text += (f"\nnot converged within the candidate fits' step budget (scored as they stand): "
                     f"{', '.join(failed)}")
        if self.families is not None:
            text += ("\nthe magnetic circuit of the whole bearing explains it; what each piece contributes (χ² rise "
                     "when it is switched off): " + ", ".join(
                         f"{f['piece']} ({f['family']}) {f['delta_chi2']:.0f}" + _family_note(f)
                         for f in self.families))
        if self.families is not None and self.verdict_fit is not None:
            vf = self.verdict_fit
            shown = [n for n in ("g_v0", "v0", "g_w0", "w0") if n in vf.names]
            text += ("\nthe circuit's gap and origin [µm]: " + ", ".join(
                f"{n} {vf.value(n) * 1e6:.2f} ± {vf.error(n) * 1e6:.2f}" for n in shown)
                + f" (χ²/dof {vf.reduced_chi2:.2f}; the ideal law's are compared with the drawing below)")
        if self.force_check is not None and "error" in self.force_check:
            text += f"\nforce check not possible: {self.force_check['error']}"
        elif self.force_check is not None:
            fc = self.force_check
            text += (f"\nforce check (each of {fc['ideal']['n_loads']} known loads left out and predicted): ideal law "
                     f"{100 * fc['ideal']['rms_rel']:.2f} % RMS ({100 * fc['ideal']['max_rel']:.2f} % worst)")
            for key, what in (("verdict", ""), ("best", " (the model that removes most of the excess)")):
                if key in fc and "error" not in fc[key]:
                    text += (f", {fc[key]['model']}{what} {100 * fc[key]['rms_rel']:.2f} % RMS "
                             f"({100 * fc[key]['max_rel']:.2f} % worst)")
            if "discrepancy" in fc:
                text += (f", {fc['discrepancy']['model']} {100 * fc['discrepancy']['rms_rel']:.2f} % RMS "
                         f"({100 * fc['discrepancy']['max_rel']:.2f} % worst)")
            floor = fc["ideal"].get("noise_floor_rel")
            if floor is not None:
                text += f"; the readings' noise alone gives {100 * floor:.2f} % RMS"
        text += "".join(f"\n{line}" for line in self.findings())
        if blind := self.blind_spot():
            text += f"\n{blind}"
        if self.best_pair is not None:
            bp = self.best_pair
            text += (f"\nbest pair: {bp['effect']} (held-out excess {bp['heldout_excess_after']:.2f}, shrink "
                     f"{bp['shrink']:.3f}{', explains the data' if bp['explains'] else ''})")
        return text

    def findings(self) -> list[str]:
        """The grade, law and discrepancy findings as sentences (part of :meth:`verdict_text`; the report shows them)."""
        out = []
        if self.grade is not None:
            g = self.grade
            out.append(f"{g['model']} removes {g['removes']:.3f} of the held-out excess and leaves {g['remainder']:.2f} "
                       f"noise units (mean z² {g['remainder_mean_z2']:.2f}; the floor reaches {g['floor_mean_z2']:.2f}): "
                       + ("at the noise floor" if g["at_floor"] else "it explains the data, not to the floor"
                          if g["explains"] else "graded: short of explaining, part of the structure is left"))
        if self.law is not None:
            lw = self.law
            named = self.verdict == lw["family"]
            out.append(f"{lw['family']}'s signature ({lw['signature']} terms) in its residuals: log Bayes factor "
                       f"{lw['log_bayes']:.1f} ({'clear' if lw['signature_clear'] else 'not clear'}); the library's "
                       f"{lw['family']} law shrinks the held-out excess by {lw['library_law_shrink']:.3f}, widened by "
                       f"that signature by {lw['shrink']:.3f}"
                       + (f": the family is {lw['family']}, its law differs from the library's" if named else ""))
        if self.discrepancy is not None:
            dc = self.discrepancy
            text = ("discrepancy (a smooth correction in flux density, gap, other axis and approach direction, "
                    "orthogonal to the fitted parameters) on the ideal law: it removes "
                    f"{dc['ideal']['insample_shrink']:.3f} of the excess in sample (the ceiling of what any such effect "
                    f"explains), {dc['ideal']['shrink']:.3f} held out")
            if "verdict" in dc:
                text += f"; added to {dc['verdict']['model']}: {dc['verdict']['shrink']:.3f} held out"
            out.append(text)
        return out

    def flagged_parameters(self) -> list[str]:
        """Parameters against the drawing as sentences: flagged ones, and gaps that differ from the drawn number
        but stay inside the drawing's tolerance (effective values, not flags)."""
        out = []
        for e in self.parameter_gap:
            if not e.get("differs", e["flagged"]):
                continue
            # plausible explanations first; an implausible one says why (e.g. beyond the calibration tolerance)
            could = sorted(e.get("could_be", []), key=lambda c: c.get("plausible") is False)
            why = "; ".join(f"{c['effect']} ({c['needs']}"
                            + (f"; implausible: {c.get('note', 'beyond its physical range')})"
                               if c.get("plausible") is False else ")") for c in could)
            text = f"{e['parameter']}: identified {e['identified']:.4g} vs nominal {e['nominal']:.4g} ({e['z']:+.1f} sd)"
            if "tolerance" in e and e["flagged"]:
                text += (f", beyond the drawing's ±{e['tolerance']:.3g} µm by {e['z_beyond_tolerance']:.1f} sd "
                         "(flagged)")
            elif "tolerance" in e:
                text += (f", inside the drawing's ±{e['tolerance']:.3g} µm (machining and iron reluctance): an "
                         "effective value, not flagged")
            out.append(f"{text} - could be {why}")
        return out

    def blind_spot(self) -> str | None:
        """What a ``none`` verdict cannot say: with fewer than three bias settings on an axis the force law's bend
        with flux density is not seen, so effects that bend it would be read as effective gap, origin and k."""
        if self.verdict != "none" or self.operating is None or "bias_A" not in self.operating:
            return None
        op = self.operating
        biases = {ax: np.unique(np.round(op.loc[op["axis"] == ax, "bias_A"].to_numpy(float), 9)) for ax in AXES}
        if all(len(b) >= 3 for b in biases.values() if len(b)):
            return None
        bending = [e for e in ("saturation", "iron_reluctance", "leakage") if e in self.confounded_with]
        if not bending:
            return None
        b = np.concatenate([op["b_top_T"].to_numpy(float), op["b_bottom_T"].to_numpy(float)])
        shown = ", ".join(f"{ax}: {'/'.join(f'{x:g}' for x in v)} A" for ax, v in biases.items() if len(v))
        return (f"this protocol cannot see {', '.join(bending)}: its biases ({shown}; flux density "
                f"{np.nanmin(b):.2f}-{np.nanmax(b):.2f} T) are too few and too close for the force law's bend with "
                "flux density to show, so any such effect is absorbed into the identified gap, origin and k "
                "(values of this protocol, not of the bearing as drawn); to see it, run a bias sweep of three or more "
                "biases up to the coil limit (ambfit simulate --preset rich is one)")

    def summary(self) -> str:
        lines = [self.floor_text()]
        lines += [f"  where: {r.describe()} ({r.rows} rows, z {r.z:.1f})" for r in self.where.regions[:5]]
        lines += [f"  {c.effect:<32} excess after {c.after:.2f}, shrink {c.shrink:.3f}" for c in self.ranking[:6]]
        lines.append(self.verdict_text())
        lines += self.flagged_parameters()
        return "\n".join(lines)

    __str__ = summary

    def __repr__(self) -> str:
        return f"Diagnosis(verdict={self.verdict!r}, shrink={self.shrink:.3f}, confounded_with={self.confounded_with})"

    def _repr_html_(self) -> str:
        rows = "".join(f"<tr><td>{html.escape(c.effect)}</td><td>{c.after:.2f}</td><td>{c.shrink:.3f}</td></tr>"
                       for c in self.ranking)
        return (f"<b>{html.escape(self.verdict_text())}</b><table><tr><th>effect</th><th>held-out excess after</th>"
                f"<th>shrink</th></tr>{rows}</table>")


def _family_note(f: dict) -> str:
    """What a circuit piece's χ² rise means: significant or not, or undecided with the range it may take."""
    lo, hi = f["delta_chi2_bounds"]
    if not f["decided"]:
        return f" (undecided: between {lo:.0f} and {hi:.0f}, its refit not settled)"
    return ("" if f["significant"] else " (not significant)") + ("" if f["converged"] else
                                                                  f" (refit not settled: {lo:.0f} to {hi:.0f})")
