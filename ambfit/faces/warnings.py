"""The warnings a result carries, in words: one source for the command line (``warning:`` lines) and the report's
summary box, so that the page says whatever the terminal says."""

from __future__ import annotations


def fit_warnings(res) -> list[str]:
    """A least-squares fit's failed health checks (not converged, not identifiable, does not fit its data, ...),
    each with its likely cause and fix.  A missing k is a property of the design (its notes say it) and
    plausibility is judged against the bearing (:func:`plausibility_warnings`)."""
    return [text for check, ok, text in res.checks() if ok is False and check not in ("k_identified", "plausible")]


def plausibility_warnings(res, bearing) -> list[str]:
    """What the bearing description rules out in a fit's estimates (``identify`` exits 3 on them)."""
    from ambfit.estimation import plausibility

    return [f"implausible: {f}" for f in plausibility.check_result(dict(zip(res.names, res.values)), bearing)]


def posterior_warnings(post, record: dict | None = None) -> list[str]:
    """A posterior that has not converged (too short for its autocorrelation time, R-hat beyond its bound, NUTS'
    divergent transitions) or that disagrees with the least-squares fit it started from.  ``record``: its
    ``to_json()`` when the caller has it."""
    rec = record if record is not None else post.to_json()
    chains = "ensembles" if post.sampler == "emcee" else "chains"
    out = []
    if post.too_short:
        out.append(f"the posterior is not converged: {post.message}")
    high = [k for k, p in rec["params"].items() if not p["r_hat"] < rec["rhat_max"]]
    if high:
        out.append(f"R-hat across the {chains} above {rec['rhat_max']:g} for {', '.join(high)}: the {chains} have "
                   "not found the same posterior (run longer, or look for several modes in the pair plot)")
    if post.divergent:
        out.append(f"{post.divergent} divergent transition(s) of NUTS after its warm-up: where they are the sampler "
                   "could not follow the posterior, and the draws there are not to be trusted (compare with "
                   "--sampler emcee)")
    if rec["least_squares_agreement"]["disagrees"]:
        out.append(rec["least_squares_agreement"]["text"])
    return out
