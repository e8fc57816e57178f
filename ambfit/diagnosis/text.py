"""What a diagnosis says, in sentences and table rows: every word a face shows of a
:class:`~ambfit.diagnosis.results.Diagnosis`, written from its record in one place.

:func:`summary` is ``str(diagnosis)``; the command line prints :func:`floor`, the rows of :func:`where_rows` and
:func:`ranking_rows`, :func:`verdict` and :func:`flagged_parameters`; the report shows :func:`headline` in its
summary box, :func:`findings` and :func:`blind_spot`.
"""

from __future__ import annotations

import html as _html

import numpy as np

from ambfit.estimation.design import MIN_BIASES, bias_settings
from ambfit.estimation.units import GEOMETRY


def floor(dg) -> str:
    """The noise floor and the ideal law's held-out excess."""
    nf = dg.noise_floor
    return (f"noise floor ({nf.source}): the ideal law's mean z² in sample {nf.mean_z2:.2f} (expected "
            f"{nf.expected_mean_z2:.2f}, (n - p) / n, were it right and the noise as stated); held-out excess "
            f"{dg.heldout_excess_before:.2f} noise units; folds: {dg.folds}")


def ranking_rows(dg) -> list[dict]:
    """The ranking as ``{column: text}`` rows (best first)."""
    return [{"effect": r.effect, "held-out excess after": f"{r.heldout_excess_after:.2f}",
             "shrink": f"{r.shrink:.3f}", "in-sample mean z²": f"{r.insample_mean_z2:.2f}",
             "fit": "converged" if r.converged else "not converged"}
            for r in dg.to_dataframe().itertuples()]


def where_rows(dg, n: int = 8) -> list[dict]:
    """The largest structured regions as ``{column: text}`` rows."""
    return [{"region": w.describe(), "rows": str(w.rows), "z": f"{w.z:.1f}"} for w in dg.where.regions[:n]]


def headline(dg) -> str:
    """The verdict in one line with its grade: what it names, how it was found and what it leaves."""
    if dg.verdict == "none":
        from ambfit.diagnosis.noise import NoiseEstimate

        est = getattr(dg, "noise_estimate", None)
        return "verdict: none (the ideal law's held-out residuals sit on the noise floor)" + _unlike_stated(dg) + (
            f"; the floor's level came from the readings themselves ({'incomplete' if est.gaps else 'no'} current "
            "std columns): an effect that varies between neighbouring readings like noise (a history the operating "
            "point does not fix) would hide in it; std columns, or --current-noise-ma and --position-noise-um, "
            "would show it" if isinstance(est, NoiseEstimate) else "")
    return _headline(dg) + _unlike_stated(dg)


def _unlike_stated(dg) -> str:
    """The readings scattering clearly unlike their stated noise, said on the verdict's own line."""
    sc = getattr(dg, "scatter", None)
    if sc is None or not sc.off:
        return ""
    return (f" (but the readings scatter {sc.ratio:.2f} times their stated noise between neighbours: check the "
            + ("declared level" if sc.declared else "std columns") + ", or declare the noise with "
            "--current-noise-ma and --position-noise-um; see below)")


def _headline(dg) -> str:
    g = dg.grade
    if dg.verdict == "undecided":
        return (f"verdict: undecided between {', '.join(dg.decision.candidates)} (best first): these data cannot "
                "tell them apart")
    if dg.verdict == "unexplained":
        return "verdict: unexplained: no model reaches the noise floor held out" + (
            f" (the closest, {g.model}, leaves {g.remainder:.2f} noise units)" if g is not None else "")
    text = f"verdict: {dg.verdict}"
    if g is not None:
        how = {"law": "the library's law", "pair": "a pair of laws", "signature": "its law widened by its signature",
               "widened_pair": "a pair with one law widened by its signature"}
        text += (f" ({how.get(g.by, g.by)} {g.model}: removes {g.removes:.3f} of the held-out excess, "
                 + ("at the noise floor)" if g.at_floor else f"leaves {g.remainder:.2f} noise units)"))
    return text


def verdict(dg) -> str:
    """The verdict with what it rests on: confounded models, the circuit's pieces, the force check, the findings,
    the protocol's blind spot, the best pair."""
    text = headline(dg)
    if dg.verdict == "none":
        text += f"; these data cannot exclude: {', '.join(dg.confounded_with) or 'nothing'}"
    elif dg.verdict not in ("undecided", "unexplained"):
        text += f"; confounded with: {', '.join(dg.confounded_with) or 'none'}; shrink {dg.shrink:.3f}"
    failed = [c.effect for c in dg.ranking if not c.fit.converged]
    if failed:
        text += (f"\nnot converged within the candidate fits' step budget (scored as they stand): "
                 f"{', '.join(failed)}")
    if dg.families is not None:
        text += ("\nthe magnetic circuit of the whole bearing explains it; what each piece contributes (χ² rise "
                 "when it is switched off): " + ", ".join(
                     f"{f.piece} ({f.family}) {f.delta_chi2:.0f}" + family_note(f) for f in dg.families))
    if dg.families is not None and dg.verdict_fit is not None:
        vf = dg.verdict_fit
        shown = [n for n in GEOMETRY if n in vf.names]
        text += ("\nthe circuit's gap and origin [µm]: " + ", ".join(
            f"{n} {vf.value(n) * 1e6:.2f} ± {vf.error(n) * 1e6:.2f}" for n in shown)
            + f" (χ²/dof {vf.reduced_chi2:.2f}; the ideal law's are compared with the drawing below)")
    fc = dg.force_check
    if fc is not None and fc.error is not None:
        text += f"\nforce check not possible: {fc.error}"
    elif fc is not None:
        text += (f"\nforce check (each of {fc.ideal.n_loads} known loads left out and predicted): ideal law "
                 f"{100 * fc.ideal.rms_rel:.2f} % RMS ({100 * fc.ideal.max_rel:.2f} % worst)")
        for check, what in ((fc.verdict, ""), (fc.best, " (the model that removes most of the excess)")):
            if check is not None and check.error is None:
                text += (f", {check.model}{what} {100 * check.rms_rel:.2f} % RMS "
                         f"({100 * check.max_rel:.2f} % worst)")
        if fc.discrepancy is not None:
            text += (f", {fc.discrepancy.model} {100 * fc.discrepancy.rms_rel:.2f} % RMS "
                     f"({100 * fc.discrepancy.max_rel:.2f} % worst)")
        if fc.ideal.noise_floor_rel is not None:
            text += f"; the readings' noise alone gives {100 * fc.ideal.noise_floor_rel:.2f} % RMS"
    text += "".join(f"\n{line}" for line in findings(dg))
    if blind := blind_spot(dg):
        text += f"\n{blind}"
    if dg.best_pair is not None:
        bp = dg.best_pair
        text += (f"\nbest pair: {bp.effect} (held-out excess {bp.heldout_excess_after:.2f}, shrink "
                 f"{bp.shrink:.3f}{', explains the data' if bp.explains else ''})")
    return text


def _listed(names) -> str:
    """``a``, ``a and b``, ``a, b and c``."""
    names = list(names)
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} and {names[-1]}"


def unjudged(dg) -> str:
    """Why the widened laws took no part in the verdict, and what data would let them."""
    listed = _listed(dg.decision.unjudged)
    op = dg.operating
    loads = op["load_N"].round(9) if "load_N" in op else None
    per_axis = (loads.groupby(op["axis"]).nunique().reindex(op["axis"].unique(), fill_value=0)
                if loads is not None else None)
    few = per_axis is None or not len(per_axis) or int(per_axis.min()) < 2
    from ambfit.estimation.basis import slow as slow_groups

    slow = any(slow_groups(s.groups) for s in getattr(dg, "signatures", None) or ())
    which = ("the widened laws whose terms follow the readings set aside"
             + (" (those of time and temperature alone are still judged)" if slow else "")
             if dg.rules.set_aside == "readings" else "every widened law set aside")
    return (f"{which}: {listed} predicted the held-out readings better than their noise (a "
            "correction learnt how the readings' noise moves the force"
            + ("; with fewer than two known loads on an axis the force's change across loads is not observed, and "
               "a correction can flatten the law there); several known loads per axis would test them" if few else
               "); a protocol with more loads or more readings per set-point would test them"))


def untested(dg) -> str:
    """Why an undecided verdict lists families whose laws do not explain the data as well as the first's."""
    first, one = dg.decision.candidates[0], len(dg.decision.untested) == 1
    return (f"{first}'s law explains the data, but {first} shares its signature with {_listed(dg.decision.untested)}, "
            "whose broader forms only the widened laws test, and those widened laws were set aside on these data: they "
            "cannot exclude " + ("it" if one else "them"))


def shared(dg) -> str:
    """Why an undecided verdict between pairs does not name the family they share."""
    common = dg.decision.shared
    seconds = [f for c in dg.decision.candidates for f in c.split("+") if f not in common]
    short = dg.decision.grade is not None and not dg.decision.grade.explains
    return (f"every candidate holds {_listed(common)}: the data want {'it' if len(common) == 1 else 'them'} and a "
            f"second effect, which they cannot single out ({_listed(list(dict.fromkeys(seconds)))})"
            + ("; none of them reaches the noise floor" if short else ""))


def findings(dg) -> list[str]:
    """What an undecided verdict cannot tell and what would; the grade, law and discrepancy findings (part of
    :func:`verdict`; the report shows them)."""
    out = []
    if dg.verdict == "undecided":
        out.append(untested(dg) if dg.decision.untested else
                   f"{', '.join(dg.decision.candidates)} explain the data alike: these data cannot tell them apart")
        if dg.decision.shared:
            out.append(shared(dg))
        sep = dg.separation
        if sep is not None:
            out.append(f"to tell them apart, run {sep.protocol}: expected log Bayes factor {sep.expected_log_bayes:.1f} "
                       f"for the weakest pair (these data: {sep.on_these_data:.1f})"
                       + ("" if sep.separates else "; even that would not separate them clearly"))
            if (current := sep.current_note()) is not None:
                out.append(current)
            drift = any("thermal_drift" in c.split("+") for c in dg.decision.candidates)
            if drift and sep.time_tied is not None and sep.time_tied > dg.rules.time_tied_r2:
                out.append(f"the readings' time runs with the sweep (the set-points, biases and loads explain "
                           f"{100 * sep.time_tied:.0f} % of it): a drift cannot be told from an effect of the "
                           "operating point; shuffle the order of the set-points and biases")
    if getattr(dg, "scatter", None) is not None and dg.scatter.off:
        out.append(dg.scatter.describe())
    if dg.decision.unjudged:
        out.append(unjudged(dg))
    if dg.left_out:
        rows = ", ".join(map(str, dg.left_out[:10])) + (f" and {len(dg.left_out) - 10} more" if len(dg.left_out) > 10
                                                        else "")
        share = len(dg.left_out) / max(len(dg.baseline.residuals), 1)
        out.append(f"{len(dg.left_out)} reading(s) ({100 * share:.1f} %) that no model at the noise floor fits (data "
                   f"row(s) {rows}: every model at the floor named them outliers) are left out of every held-out "
                   "score: a sensor's gross errors, or an effect that no library law holds, confined to them; check "
                   "the sensors there")
    if dg.grade is not None:
        g = dg.grade
        out.append(f"{g.model} removes {g.removes:.3f} of the held-out excess and leaves {g.remainder:.2f} "
                   f"noise units (mean z² {g.remainder_mean_z2:.2f}; the floor reaches {g.floor_mean_z2:.2f}): "
                   + ("at the noise floor" if g.at_floor else "short of the floor: part of the structure is left"))
    if dg.law is not None:
        lw = dg.law
        signature = "+".join(lw.groups)
        if lw.widens is None:
            whose, library, widening = "its", f"{lw.family} law", "widened by that signature"
            named = f": the family is {lw.family}, its law differs from the library's"
        else:               # (a widened pair: the library's pair, then its family's law widened beside the other's)
            whose, library, widening = "the pair's", f"pair {lw.law.effect}", \
                f"with its {lw.family} law widened by that signature"
            named = (f": the families are {dg.verdict}; {lw.family}'s law differs from the library's, beside "
                     f"{lw.second}'s library law")
        named = named if dg.verdict == "+".join(lw.families) else ""
        out.append(f"{lw.family}'s signature ({signature} terms) in {whose} residuals: log Bayes factor "
                   f"{lw.log_bayes_max:.1f} ({'clear' if dg.judge.clear(lw) else 'not clear'}); the library's "
                   f"{library} shrinks the held-out excess by {lw.law.shrink:.3f}, {widening} by {lw.shrink:.3f}"
                   + named)
    if dg.ceiling is not None:
        dc = dg.ceiling
        text = ("discrepancy (a smooth correction in flux density, gap, other axis and approach direction, "
                "orthogonal to the fitted parameters) on the ideal law: it removes "
                f"{dc.ideal.insample_shrink:.3f} of the excess in sample (the ceiling of what any such effect "
                f"explains), {dc.ideal.shrink:.3f} held out")
        if dc.verdict is not None:
            text += f"; added to {dc.verdict.model}: {dc.verdict.shrink:.3f} held out"
        if dg.verdict == "none":
            text += " (the ideal law sits on the floor: these are shares of its noise, not of an effect)"
        elif dc.ideal.shrink < 0 or (dc.verdict is not None and dc.verdict.shrink < 0):
            text += (" (a negative share: with the correction the held-out readings are predicted worse than "
                     "without it, so what it learns in sample is noise, not a missing effect)")
        out.append(text)
    return out


def flagged_parameters(dg) -> list[str]:
    """Parameters against the drawing as sentences: flagged ones, and gaps that differ from the drawn number but
    stay inside the drawing's tolerance (effective values, not flags)."""
    out = []
    for e in dg.parameter_gap:
        if not e.get("differs", e["flagged"]):
            continue
        # plausible explanations first; an implausible one says why (e.g. beyond the calibration tolerance)
        could = sorted(e.get("could_be", []), key=lambda c: c.get("plausible") is False)
        why = "; ".join(f"{c['effect']} ({c['needs']}"
                        + (f"; implausible: {c.get('note', 'beyond its physical range')})"
                           if c.get("plausible") is False else ")") for c in could)
        text = f"{e['parameter']}: identified {e['identified']:.4g} vs nominal {e['nominal']:.4g} ({e['z']:+.1f} sd)"
        if "tolerance" in e and e["flagged"]:
            text += f", beyond the drawing's ±{e['tolerance']:.3g} µm by {e['z_beyond_tolerance']:.1f} sd (flagged)"
        elif "tolerance" in e:
            text += (f", inside the drawing's ±{e['tolerance']:.3g} µm (machining and iron reluctance): an "
                     "effective value, not flagged")
        out.append(f"{text} - could be {why}")
    return out


def blind_spot(dg) -> str | None:
    """What a ``none`` verdict cannot say: with fewer than three bias settings on an axis the force law's bend with
    flux density is not seen, so effects that bend it would be read as effective gap, origin and k."""
    if dg.verdict != "none" or dg.operating is None or "bias_A" not in dg.operating:
        return None
    op = dg.operating
    biases = bias_settings(op)
    if all(len(b) >= MIN_BIASES for b in biases.values() if len(b)):
        return None
    bending = [e for e in ("saturation", "iron_reluctance", "leakage") if e in dg.confounded_with]
    if not bending:
        return None
    b = np.concatenate([op["b_top_T"].to_numpy(float), op["b_bottom_T"].to_numpy(float)])
    shown = ", ".join(f"{ax}: {'/'.join(f'{x:g}' for x in v)} A" for ax, v in biases.items() if len(v))
    return (f"this protocol cannot see {', '.join(bending)}: its biases ({shown}; flux density "
            f"{np.nanmin(b):.2f}-{np.nanmax(b):.2f} T) are too few and too close for the force law's bend with "
            "flux density to show, so any such effect is absorbed into the identified gap, origin and k "
            "(values of this protocol, not of the bearing as drawn); to see it, run a bias sweep of three or more "
            "biases spread towards the coil limit (ambfit simulate --preset rich sweeps four, from a third to "
            "over half of the bearing's limit)")


def summary(dg) -> str:
    """The whole diagnosis as text: floor, structured regions, ranking, verdict, flagged parameters."""
    lines = [floor(dg)]
    lines += [f"  where: {r.describe()} ({r.rows} rows, z {r.z:.1f})" for r in dg.where.regions[:5]]
    lines += [f"  {c.effect:<32} excess after {c.after:.2f}, shrink {c.shrink:.3f}" for c in dg.ranking[:6]]
    lines.append(verdict(dg))
    lines += flagged_parameters(dg)
    return "\n".join(lines)


def html(dg) -> str:
    """The verdict and the ranking as HTML (a notebook's view)."""
    rows = "".join(f"<tr><td>{_html.escape(c.effect)}</td><td>{c.after:.2f}</td><td>{c.shrink:.3f}</td></tr>"
                   for c in dg.ranking)
    return (f"<b>{_html.escape(verdict(dg))}</b><table><tr><th>effect</th><th>held-out excess after</th>"
            f"<th>shrink</th></tr>{rows}</table>")


def family_note(f) -> str:
    """What a circuit piece's χ² rise means: significant or not, or undecided with the range it may take."""
    lo, hi = f.delta_chi2_bounds
    if not f.decided:
        return f" (undecided: between {lo:.0f} and {hi:.0f}, its refit not settled)"
    return ("" if f.significant else " (not significant)") + ("" if f.converged else
                                                             f" (refit not settled: {lo:.0f} to {hi:.0f})")
