"""How a diagnosis turns held-out scores into a verdict: the rules, and one pure function that applies them.

Every model is scored by its held-out standardized residuals ``z`` (each fold's readings predicted by a fit that
did not see them): ``score = mean(z^2)``, 1 at the noise floor for a model whose parameters are known exactly, and
``mean(1 + h)`` for one that is right but estimated (``h``: what its parameters' uncertainty adds to each
prediction's variance, :func:`ambfit.diagnosis.heldout.predictive_variance`).  With ``n`` held-out readings the
score's standard error is ``sqrt(2 / n)`` (a mean of ``n`` squared standard normals), scaled by its level.  A model

- is *at the floor* when its score is within ``Rules.floor_se`` of those standard errors of its floor (and not
  below the noise's: held-out residuals far *smaller* than their predictive variance, on the readings a model
  predicts confidently, are no model of the force, it predicts the readings' own noise);
- *explains* the data when it is at the floor where the ideal law is not;
- is *clearly better* than another when, reading by reading, its predictions are better by more than
  ``Rules.margin_se`` standard errors of their paired difference (minus twice the log predictive density,
  ``z^2 / (1 + h) + log(1 + h)``: a flexible model pays for the width of its predictions; the two models' scores
  share the readings' noise, so their difference is known far better than either score).

:func:`decide` applies them to scored models (:class:`~ambfit.diagnosis.heldout.Candidate` laws and pairs,
:class:`~ambfit.diagnosis.signatures.Signature` widened laws), simplest first, so that flexibility is paid for:
a library law that explains the data is preferred to a pair, and a pair to a family's law widened by its
signature (tens of free terms).  The first of these tiers that explains the data gives the model a verdict would
name; its family is named only when that model is clearly better than every other family's best model, of any
tier, that rivals it; otherwise the verdict is ``undecided`` and lists them (``candidates``, best first).  A more
flexible model rivals the simplest explanation only when it explains the data and is *ahead* of it (better by
``Rules.ahead_se`` standard errors, short of clearly; ``Rules.occam`` says which models this spares).  Families
sharing a signature are told apart by their own laws, or not at all.  When nothing explains the data the verdict
is ``unexplained``, with the model that removes most reported (``best``), unless one removes nearly all of the
excess and beats every other family's model: it is named, graded short of the floor.  A clear widened law *below*
the floor has learnt how the readings' noise moves the force (one load per axis lets a
correction flatten the law): then no widened law whose terms follow the readings is judged by its held-out score
(``Verdict.unjudged``; ``Rules.set_aside``).
:func:`needs_pairs` and :func:`needs_signatures` say, from the same rules,
whether the scores so far call for more candidates.  Nothing here fits: every function is pure, and unit tests
drive it with hand-made scores.
"""

from __future__ import annotations

import dataclasses

import numpy as np

OCCAM = ("all", "siblings", "none")
"""Which more flexible models need to be ahead of the simplest explanation to rival it (:attr:`Rules.occam`)."""

SET_ASIDE = ("readings", "all")
"""Which widened laws a widened law below the floor sets aside (:attr:`Rules.set_aside`)."""


@dataclasses.dataclass(frozen=True)
class Rules:
    """Every threshold of a verdict, in one place (:func:`ambfit.diagnose` takes them as ``rules``).

    Attributes
    ----------
    floor_tolerance : float
        The ideal law is on the floor (verdict ``none``) when its held-out excess [noise units] is below this and
        no region is structured (or when its score is at the floor).
    floor_se : float
        At the floor: a score within this many standard errors of 1.
    margin_se : float
        Clearly better: a paired difference of squared held-out residuals beyond this many of its standard
        errors.  Models not clearly apart are indistinguishable (``undecided``, ``confounded_with``).  The
        standard error treats the readings' differences as independent, which readings held out in blocks and
        predicted by shared fits are not, so it is too small; the margin allows for that.  On the law zoo's stored
        scores at 4 (at 3 in brackets): seeds 3131, 7373 and 8484 (712 draws, studied) wrong claims 4.9 % (6.3 %),
        right 39.9 % (39.7 %); seeds 9191 and 4242 (300 draws each, kept unseen for this rule) wrong claims 5.3 %
        (6.7 %) and 4.0 % (4.7 %), right 40.0 % (40.7 %) and 47.7 % (49.7 %), the right verdicts given up all
        ``undecided`` with the truth; the own rig's top-1 0.90 at both, 0.81 at 5 (``reports/gap/rules.md``).
    graded_shrink : float
        When nothing reaches the floor, a model that removes at least this share of the ideal law's held-out
        excess, leaves less than ``graded_remainder``, and predicts clearly better than every other family's, is
        still named (its ``grade`` says what it leaves); one that does not is ``unexplained``.
    graded_remainder : float
        The most a model named short of the floor may leave [noise units of held-out excess]: a family that removes
        most of a large excess but leaves more than a noise unit has a second effect beside it, which naming it
        alone would hide (the FEM development bearing's circuit leaves 0.63 and is named; on the law zoo's pairs a
        widened hysteresis law that left 1.05 beside a current offset, and a widened leakage law that left 1.49
        beside saturation and a current offset, were named alone at 2).
    confident_var : float
        A held-out prediction is confident when its variance is at most this many noise variances (its parameters'
        uncertainty adds at most as much as the noise): the readings on which :meth:`Judge.below_floor` looks for a
        model that predicts their noise (a law zoo case, seed 7373 draw 276: a saturation law widened by its shape
        group with a mean square of 0.93 held out and 0.07 relative to its variance, over a median variance of
        1.1).
    spread_max : float
        A model's floor counts the width its parameters' uncertainty adds to its held-out predictions up to this
        share of the noise variance: a model whose predictions are wider still (a flexible correction extrapolated
        beyond the readings it was fitted on) is not tested by them, and does not explain them by being vague
        (laws and widened laws that fit widen them by 0.01-0.13 on the law zoo's cases; a widened drift law
        extrapolated in time by 12).
    log_bayes_clear : float
        A signature is clearly in a law's residuals when the marginal likelihood wants one of its discrepancy
        groups by more than this (log Bayes factor on every reading the law's fit gives a residual, its outliers
        among them: the rows the widened law's folds learn from; above 5 is 'very strong' on Kass and Raftery's
        1995 scale; on the FEM bearing, with no hysteresis, the ceiling's correction of everything the magnetic
        circuit leaves wants its direction group by 3.3); a widened law whose signature is not clear is no
        candidate.
    structure_alpha : float
        False-alarm probability of the search for structured regions (:func:`ambfit.diagnosis.residuals.where`).
    circuit_dchi2 : float
        A piece of the magnetic circuit counts in the verdict when switching it off raises χ² by more than this
        many of χ²'s standard deviations ``sqrt(2 dof)`` (:func:`ambfit.diagnosis.circuit_families.circuit_families`).
    separate_log_bayes : float
        A protocol separates two candidates when its expected log Bayes factor is above this ('strong' and more on
        Kass and Raftery's scale is above 3; 5 leaves room for the linearisation) (:mod:`ambfit.diagnosis.separation`).
    time_tied_r2 : float
        The readings' time runs with the sweep when the set-points, biases and loads explain more than this share
        of its variance.
    ahead_se : float
        Ahead: a paired difference of held-out deviances beyond this many of its standard errors, at most
        ``margin_se`` (when two models predict alike, one is ahead of the other with probability ``P(Z < -ahead_se)``,
        about one in six at 1).  With :attr:`occam` "all" and ``margin_se`` 3: on the law zoo's first 100 draws (those
        studied while the rules were made) 1 turns 2 of 7 wrong claims and 2 right verdicts into undecided ones, 3 of
        them holding the truth; 0 turns the same 2 wrong claims and 4 right verdicts, 1.5 only 1 wrong claim; on 20
        cases of the rig's own laws none of them changes a verdict.
    occam : {"all", "siblings", "none"}
        Which more flexible models (a pair against a law, a widened law against either) that are not clearly better
        rival a simpler one that explains the data only when they explain them too and are ahead of it (where the
        simpler predicts about as well, it wins: the Occam factor a held-out score alone barely charges).  ``"all"``
        (the default, also True): every more flexible model.  ``"siblings"``: only a widened law on a signature of the
        simpler model's own families (the flux families share one, the current channels another), which can carry the
        simpler law's own shape; any other model not clearly worse is a rival (other physics that predicts as well).
        ``"none"`` (also False): no model, a family is named only when its best model beats every other family's best
        model clearly.  With ``margin_se`` 3, on the law zoo's study seed 7373 (300 draws, scored with the signatures
        of that study) "all" names a wrong family in 5.7 % of the draws and is right in 40.3 %, "siblings" 4.3 % and
        35.7 %, "none" 2.0 % and 33.3 % (the rest mostly ``undecided`` with the truth among the candidates: 13 %,
        20 %, 24 %).  On the rig's own laws (``benchmarks/gap_attribution.py``, 3 sets per effect) "all" names the
        right family in 0.90 of the structured cases, "siblings" in 0.76 (current offsets undecided against hysteresis
        widened by its memory plays, which a protocol that seldom reverses a coil's current leaves saturated: a
        constant offset), and "none" leaves even the library's own saturation law undecided against fringing widened
        by the flux families' signature.  The held-out scores cannot tell a library law that is right from another
        family's widened law that mimics it: which to prefer is a prior, and this one is the user's.
    untested_siblings : bool
        When the widened laws are set aside (:attr:`Verdict.unjudged`), a family named by its law alone, at the floor,
        is ``undecided`` with the families that share its signature (the flux families; the current channels): its law
        beats their library laws, not their broader forms, which only the widened laws test (a gain error in one
        coil's channel is an offset at one bias; a permeability that falls with flux density is a saturation).  On the
        law zoo's stored scores (seeds 3131, 7373 and 8484, 712 draws; ``margin_se`` 3) it turns wrong claims into
        ``undecided`` with the truth among the candidates about as often as right verdicts (``reports/gap/rules.md``).
    name_shared : bool
        When the models that explain the data alike are pairs sharing a family (pairs are tried when no single law
        explains the data: they want that family and a second effect they cannot single out), name that family (True),
        or leave the verdict ``undecided`` between the pairs, which share it (:attr:`Verdict.shared`; the default).
        Named, the verdict claims a family whose law alone did not explain the data, and misses the second effect when
        there is one: on the law zoo's stored scores (seeds 3131, 7373 and 8484, 712 draws; ``margin_se`` 3) naming it
        is right in 5 draws where the truth is that family alone, and a wrong claim in 7 (a pair named by one of its
        families, or a flux family named for another); undecided, all 12 list the truth among the candidates
        (``reports/gap/rules.md``).
    set_aside : {"readings", "all"}
        Which widened laws take no part in the verdict when a clear one predicts the held-out readings better than
        their noise (:func:`decide`).  ``"readings"`` (the default): those whose signature's terms follow the
        readings from one reading to the next (flux density and gap, the currents, the positions, the other axis,
        the currents' paths), which share the freedom to learn the readings' noise; a law widened by slow terms
        alone (:data:`ambfit.estimation.basis.SLOW_GROUPS`: time and temperature) is still judged.  ``"all"``: every
        widened law.  On the law zoo's stored scores (seeds 3131, 9191 and 4242, 900 draws) "readings" turns 5
        ``unexplained`` drifts into right verdicts and 1 into a wrong claim (a drift named beside a current offset no
        library law of the pair found); everything else alike (``reports/gap/rules.md``).
    sibling_rivals : bool
        With :attr:`occam` "all" or "siblings": a law widened by the flux families' shared ``shape`` signature, of
        another flux family than the library law that explains the data, rivals that law when it explains the data
        too and is not clearly worse, ahead of it or not (the law beats its sibling's library law, not its broader
        forms, which the widened law stands for; the current channels' signature is left to Occam, since it holds an
        offset per coil: an offset's law is one of its forms).  On the law zoo's stored scores (seeds 3131 and 9191,
        384 draws; ``benchmarks/zoo_replay.py``) it turns 3 wrong claims (a position gain named fringing, an iron
        reluctance named leakage, a saturation beside a current gain named alone) and 4 right verdicts (saturation,
        against leakage, iron reluctance or fringing widened) into ``undecided``: right 45.1 → 44.0 %, wrong claims
        4.4 → 3.6 %.  Off by default: on the rig's own laws (``benchmarks/gap_attribution.py``, 3 sets per effect)
        a flux family's library law, exact there, is mimicked by a sibling's widened law, and 4 of 9 (3 saturations,
        an iron reluctance) turn ``undecided``: top-1 0.90 → 0.71 (``reports/gap/rules.md``).
    minimal_explains : bool
        A model naming fewer families than the simplest that explains the data (a law against a pair, say) takes
        its place only when it explains them too: one short of the floor leaves both, ``undecided`` with the family
        they share (:attr:`Verdict.shared`).  False (the default): the fewer families are named, graded short of the
        floor, whether they explain or not.  On the law zoo's stored scores (seeds 3131 and 9191, 384 draws) one
        right verdict (a hysteresis whose widened law fell short beside pairs that explain) and one wrong claim (a
        cross coupling named beside an iron reluctance) turn ``undecided``; on the rig's own laws
        (``benchmarks/gap_attribution.py``, 3 sets per effect) a leakage law short of the floor turns ``undecided``
        among leakage and every second family beside it (top-1 0.90 → 0.86): when any second law reaches the floor
        beside it, the pairs' freedom is what reaches it, not a second effect.
    widened_pairs : bool
        Score each pair with one of its laws widened by its family's signature (a law other than the library's
        beside a second effect) when pairs were scored and no law, pair or widened law that takes part in the
        decision explains the data (:func:`needs_widened_pairs`).  Off by default: on the law zoo's study seed 3131
        (300 draws) it names 2 pairs right that were ``unexplained``, and makes 5 wrong claims: 4 pairs named by one
        family whose widened law alone, short of the floor, is not clearly worse than the widened pair
        (:attr:`minimal_explains` makes them ``undecided``, and 3 singles named short of the floor with them), and a
        mechanical spring (no family) named ``leakage+current_offset``: right 45.7 → 46.0 %, wrong claims 5.0 →
        6.7 %.
    pairs : bool
        Try pairs of effects when no single one explains the data.
    pair_verdict : bool
        Let a pair be the verdict (with False the best pair is only reported).
    """

    floor_tolerance: float = 1.0
    floor_se: float = 3.0
    margin_se: float = 4.0
    ahead_se: float = 1.0
    graded_shrink: float = 0.9
    graded_remainder: float = 1.0
    spread_max: float = 1.0
    confident_var: float = 2.0
    log_bayes_clear: float = 10.0
    structure_alpha: float = 0.01
    circuit_dchi2: float = 3.0
    separate_log_bayes: float = 5.0
    time_tied_r2: float = 0.9
    occam: str = "all"
    untested_siblings: bool = True
    name_shared: bool = False
    set_aside: str = "readings"
    sibling_rivals: bool = False
    minimal_explains: bool = False
    widened_pairs: bool = False
    pairs: bool = True
    pair_verdict: bool = True

    def __post_init__(self):
        if isinstance(self.occam, bool):
            object.__setattr__(self, "occam", "all" if self.occam else "none")
        if self.occam not in OCCAM:
            raise ValueError(f"occam must be one of {OCCAM} (or True / False for 'all' / 'none'), got {self.occam!r}")
        if self.set_aside not in SET_ASIDE:
            raise ValueError(f"set_aside must be one of {SET_ASIDE}, got {self.set_aside!r}")
        if not 0.0 <= self.ahead_se <= self.margin_se:
            raise ValueError(f"ahead_se ({self.ahead_se}) must lie between 0 and margin_se ({self.margin_se}): "
                             "ahead is short of clearly better")


@dataclasses.dataclass(frozen=True)
class Judge:
    """The :class:`Rules` applied to ``n`` held-out readings whose ideal law scores ``ideal_score``."""

    n: int
    ideal_score: float
    rules: Rules = Rules()

    def se(self, score: float = 1.0) -> float:
        """Standard error of a held-out score at ``score`` (at least that at the floor)."""
        return float(np.sqrt(2.0 / max(self.n, 1)) * max(score, 1.0))

    @property
    def floor(self) -> float:
        """The largest score at the floor of a model whose parameters are known exactly."""
        return 1.0 + self.rules.floor_se * self.se()

    def floor_of(self, model) -> float:
        """The largest score at ``model``'s floor: its held-out residuals' expected mean square when it is right
        (the noise and its parameters' uncertainty, ``mean(1 + h)``, ``h`` counted up to ``Rules.spread_max``),
        plus ``floor_se`` standard errors."""
        var = getattr(model, "heldout_var", None)
        level = 1.0 if var is None else 1.0 + min(float(np.mean(var)) - 1.0, self.rules.spread_max)
        return level + self.rules.floor_se * self.se(level)

    @property
    def below(self) -> float:
        """The smallest score at the floor: a model below it predicts the readings' own noise."""
        return 1.0 - self.rules.floor_se * self.se()

    def at_floor(self, model) -> bool:
        return model.score <= self.floor_of(model) and not self.below_floor(model)

    def below_floor(self, model) -> bool:
        """Whether ``model`` predicts the held-out readings better than their noise allows: its score is below
        :attr:`below`, or, on the readings it predicts confidently (variance at most ``Rules.confident_var``
        noise variances), its residuals' mean square relative to that variance is below the floor's lower limit for so
        many readings (a model exact on most readings, while a few far off carry its mean square up to the floor,
        predicts their noise too)."""
        if model.score < self.below:
            return True
        z2 = np.asarray(model.heldout_z) ** 2
        var = getattr(model, "heldout_var", None)
        var = np.ones_like(z2) if var is None else np.asarray(var)
        sure = var <= self.rules.confident_var
        n = int(np.sum(sure))
        return n > 1 and float(np.mean(z2[sure] / var[sure])) < 1.0 - self.rules.floor_se * np.sqrt(2.0 / n)

    def explains(self, model) -> bool:
        return self.at_floor(model) and self.ideal_score > self.floor

    def clearly_better(self, a, b) -> bool:
        """Whether ``a`` predicts the held-out readings clearly better than ``b``, reading by reading (paired
        differences of ``z^2 + log(1 + h)``, minus twice the log predictive density: a flexible model pays for
        the width of its predictions)."""
        mean, se = self._paired(a, b)
        return mean < -self.rules.margin_se * se

    def _paired(self, a, b) -> tuple[float, float]:
        """Mean and standard error of the paired differences of ``a``'s and ``b``'s held-out deviances."""
        da, db = np.asarray(a.heldout_deviance), np.asarray(b.heldout_deviance)
        if da.shape != (self.n,) or db.shape != (self.n,):
            raise ValueError(f"paired scores need {self.n} held-out readings each, got {da.shape} and {db.shape}")
        d = da - db
        return float(np.mean(d)), (float(np.std(d, ddof=1) / np.sqrt(self.n)) if self.n > 1 else np.inf)

    def ahead(self, a, b) -> bool:
        """Whether ``a`` predicts the held-out readings better than ``b`` by at least ``Rules.ahead_se`` standard
        errors of the paired differences (short of clearly better, ``margin_se``, or not)."""
        mean, se = self._paired(a, b)
        return mean < -self.rules.ahead_se * se

    def apart(self, a, b) -> bool:
        """Whether either of two models is clearly better than the other."""
        return self.clearly_better(a, b) or self.clearly_better(b, a)

    def close(self, a, ref: float) -> bool:
        """Whether ``a``'s score cannot be told from ``ref`` (unpaired: within ``margin_se`` standard errors)."""
        return abs(a.score - ref) < self.rules.margin_se * self.se(ref)

    def clear(self, signature) -> bool:
        """Whether the data clearly want ``signature``'s discrepancy groups (its ``log_bayes``, on the rows its folds
        learn from)."""
        return signature.log_bayes_max > self.rules.log_bayes_clear

    def grade(self, model) -> Grade:
        """What ``model`` removes and what it leaves."""
        return Grade(model=model.label, families=tuple(model.families), by=model.kind, removes=model.shrink,
                     remainder=model.after, remainder_mean_z2=model.score, floor_mean_z2=self.floor_of(model),
                     at_floor=self.at_floor(model), explains=self.explains(model))


@dataclasses.dataclass(frozen=True)
class Grade:
    """What a verdict's model removes and what it leaves: noise units, at the floor or not, explaining or not.

    ``by`` is how the model was found: a library ``law``, a ``pair`` of laws, a law widened by its family's
    ``signature``, or a pair with one law so widened (``widened_pair``)."""

    model: str
    families: tuple
    by: str
    removes: float
    remainder: float
    remainder_mean_z2: float
    floor_mean_z2: float
    at_floor: bool
    explains: bool

    def to_json(self) -> dict:
        return {"model": self.model, "families": list(self.families), "by": self.by, "removes": self.removes,
                "remainder": self.remainder, "remainder_mean_z2": self.remainder_mean_z2,
                "floor_mean_z2": self.floor_mean_z2, "at_floor": self.at_floor, "explains": self.explains}


KINDS = ("none", "named", "undecided", "unexplained")


@dataclasses.dataclass(frozen=True)
class Verdict:
    """What the data say.

    Attributes
    ----------
    kind : {"none", "named", "undecided", "unexplained"}
        ``none``: the ideal law's held-out residuals sit on the noise floor.  ``named``: one model's families
        (explaining the data, or graded when nothing does).  ``undecided``: several models explain the data and
        these data cannot tell them apart (``candidates``), or one family's law explains them and the families
        sharing its signature cannot be tested (``untested``).  ``unexplained``: nothing removes enough.
    model : Candidate or Signature or None
        The named model.
    families : tuple of str
        The families it names, in the order of their contribution.
    confounded_with : tuple of str
        Models (``+``-joined families) whose held-out score cannot be told from the verdict's.
    grade : Grade or None
        What the named model removes and leaves.
    shrink : float
        Held-out shrink of the verdict (of the best single law when ``unexplained``; 0 for ``none``).
    best : Candidate or Signature or None
        The model that removes most of the excess when it is not the verdict's law (a widened law, or the best
        law when nothing is named): its force check is reported as ``best``.
    candidates : tuple of str
        ``undecided``: the models that explain the data, best first (with :attr:`untested`: the family whose law
        does, then those).
    unjudged : tuple of str
        Widened laws that predicted the held-out readings better than their noise: the held-out test cannot judge
        a flexible law whose terms follow the readings on these data, so none of those took part in the decision
        (:func:`decide`).
    untested : tuple of str
        ``undecided`` by :attr:`Rules.untested_siblings`: the candidates after the first, families sharing its
        signature whose broader forms these data could not test.
    shared : tuple of str
        ``undecided`` between pairs that share a family (:attr:`Rules.name_shared`): that family, which every
        candidate holds.
    """

    kind: str
    model: object = None
    families: tuple = ()
    confounded_with: tuple = ()
    grade: Grade | None = None
    shrink: float = 0.0
    best: object = None
    candidates: tuple = ()
    unjudged: tuple = ()
    untested: tuple = ()
    shared: tuple = ()

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {self.kind!r}")

    @property
    def name(self) -> str:
        """The contract's ``verdict``: ``none``, ``undecided``, ``unexplained`` or the ``+``-joined families."""
        return "+".join(self.families) if self.kind == "named" else self.kind

    @property
    def law(self):
        """The named model's library law (a widened law's own; None when nothing is named)."""
        return getattr(self.model, "law", self.model)

    def with_families(self, families) -> Verdict:
        """The same verdict naming ``families`` (a magnetic circuit's significant pieces)."""
        families = tuple(families) or self.families
        grade = None if self.grade is None else dataclasses.replace(self.grade, families=families)
        return dataclasses.replace(self, families=families, grade=grade)


def on_floor(rules: Rules, ideal, structured: bool) -> bool:
    """Whether the ideal law's held-out residuals sit on the noise floor: its score is at the floor, or its excess
    is below ``floor_tolerance`` with no structured region."""
    judge = Judge(len(ideal.heldout_z), ideal.score, rules)
    return ideal.score <= judge.floor or (ideal.after < rules.floor_tolerance and not structured)


def needs_pairs(rules: Rules, ideal, singles: list, structured: bool) -> bool:
    """Whether pairs of effects are to be scored: no single law explains the data."""
    if on_floor(rules, ideal, structured) or not singles or not rules.pairs:
        return False
    judge = Judge(len(ideal.heldout_z), ideal.score, rules)
    return not any(judge.explains(c) for c in singles)


def needs_widened_pairs(rules: Rules, ideal, models: list) -> bool:
    """Whether pairs with one law widened by its signature are to be scored: the pairs were scored (no single law
    explains the data) and no law, pair or widened law that takes part in the decision explains them."""
    if not (rules.widened_pairs and any(c.kind == "pair" for c in models)):
        return False
    judge = Judge(len(ideal.heldout_z), ideal.score, rules)
    taking_part, _ = _judged(judge, models)               # (the widened laws decide would set aside do not count)
    return not any(
        judge.explains(c) and (c.kind not in WIDENED or judge.clear(c)) for c in taking_part)


def needs_signatures(rules: Rules, ideal, structured: bool) -> bool:
    """Whether the families' laws widened by their signatures are to be scored: whenever the ideal law is off the
    floor.  A law that explains the data must still be told from another family whose law differs from the
    library's (the flux families share one signature); the widened laws pay for their flexibility in the paired
    comparison, so an exact law beats them when it is right."""
    return not on_floor(rules, ideal, structured)


TIERS = ("law", "pair", "signature", "widened_pair")
"""Models by flexibility: a library law, a pair of them, a family's law widened by its signature, a pair with one
of its laws so widened."""

WIDENED = ("signature", "widened_pair")
"""The kinds of model widened by a signature."""


def decide(rules: Rules, ideal, candidates: list, *, structured: bool = False) -> Verdict:
    """The verdict from scored models.

    Parameters
    ----------
    rules : Rules
        The thresholds.
    ideal : Candidate
        The ideal law's held-out score.
    candidates : list
        Scored models: library laws and pairs (``kind`` ``"law"`` / ``"pair"``), widened laws (``kind``
        ``"signature"``) and widened pairs (``"widened_pair"``, used with :attr:`Rules.widened_pairs`), their
        held-out residuals on the same readings as the ideal law's, in the order they were scored (ties keep it).
    structured : bool
        Whether the ideal law's residuals have structured regions (:func:`ambfit.diagnosis.residuals.where`).

    A widened law whose terms follow the readings, whose signature is clear and which is below the floor
    (:meth:`Judge.below_floor`) sets aside every such widened law (:attr:`Rules.set_aside`; with ``"all"`` any
    widened law below the floor sets aside every one): the verdict is decided by the laws, the pairs and
    the laws widened by slow terms alone (nothing explaining, ``unexplained``; a little above the floor with no model
    clearly better, ``none``; one family's law, ``undecided`` with its signature's other families,
    :attr:`Rules.untested_siblings`) and lists those below the floor in ``unjudged``.
    """
    judge = Judge(len(ideal.heldout_z), ideal.score, rules)
    # a clear widened law below the floor predicts the readings' noise: its correction has learnt how the noise of
    # a reading moves the force, which readings at one load per axis allow (the force's slope across loads is not
    # observed, so a correction can flatten the law there).  The other widened laws whose terms follow the readings
    # share that freedom: their held-out scores do not test them, and none is used.  Slow terms (time, temperature)
    # are alike for readings close in time and cannot follow a reading's noise (below the floor, such a law is only
    # no candidate)
    if not rules.widened_pairs:
        candidates = [c for c in candidates if c.kind != "widened_pair"]
    candidates, unjudged = _judged(judge, candidates)
    verdict = _decide(judge, ideal, candidates, structured)
    if unjudged and rules.untested_siblings:
        verdict = _with_untested_siblings(verdict, candidates)
    return dataclasses.replace(verdict, unjudged=unjudged)


def _judged(judge: Judge, candidates: list) -> tuple[list, tuple]:
    """``candidates`` less the widened laws set aside (:func:`decide`), and the labels of those below the floor."""
    rules = judge.rules
    unjudged = tuple(c.label for c in candidates if c.kind in WIDENED and judge.clear(c) and judge.below_floor(c)
                     and not _slow(rules, c))
    if unjudged:
        candidates = [c for c in candidates if c.kind not in WIDENED or _slow(rules, c)]
    return candidates, unjudged


def _slow(rules: Rules, signature) -> bool:
    """Whether ``signature``'s terms are slow ones alone, judged when those that follow the readings are set aside."""
    from ambfit.estimation.basis import slow

    return rules.set_aside == "readings" and slow(signature.groups)


def _with_untested_siblings(verdict: Verdict, laws: list) -> Verdict:
    """A family named by its law explaining the data while the widened laws are set aside, as ``undecided`` with
    the families that share its signature (``untested``): its law beats their library laws, but not their broader
    forms, which these data cannot test (a gain error in one coil's channel is an offset at one bias; a permeability
    falling with flux density is a saturation)."""
    from ambfit.estimation.basis import FAMILY_GROUPS

    if verdict.kind != "named" or len(verdict.families) != 1 or getattr(verdict.model, "kind", None) != "law" or \
            verdict.grade is None or not verdict.grade.explains:
        return verdict          # (a family cut from several pairs, Rules.name_shared, or graded short of the floor)
    (family,) = verdict.families
    siblings = [f for f, groups in FAMILY_GROUPS.items() if f != family and groups == FAMILY_GROUPS.get(family)]
    if not siblings:
        return verdict
    score = {f: min((c.score for c in laws if tuple(c.families) == (f,)), default=np.inf) for f in siblings}
    siblings = sorted(siblings, key=lambda f: score[f])
    return dataclasses.replace(verdict, kind="undecided", families=(), candidates=(family, *siblings),
                               untested=tuple(siblings), confounded_with=())


def _decide(judge: Judge, ideal, candidates: list, structured: bool) -> Verdict:
    """:func:`decide` on the models that take part."""
    rules = judge.rules
    usable = [c for c in candidates if not judge.below_floor(c) and (c.kind not in WIDENED or judge.clear(c))
              and (c.kind != "pair" or rules.pair_verdict)]
    usable.sort(key=lambda c: c.score)
    # on the floor; or a little above it, with no model predicting the held-out readings clearly better
    if on_floor(rules, ideal, structured) or (
            ideal.after < rules.floor_tolerance and not any(judge.clearly_better(c, ideal) for c in usable)):
        laws = sorted((c for c in candidates if c.kind in ("law", "pair")), key=lambda c: c.score)
        return Verdict("none", confounded_with=tuple(c.label for c in laws if judge.close(c, ideal.score)))
    explaining = [c for c in usable if judge.explains(c)]
    for kind in TIERS:
        tier = [c for c in explaining if c.kind == kind]
        if tier:
            return _named_or_undecided(judge, tier[0], usable)
    # short of the floor: a model that removes nearly all of the excess, if it beats every other family's
    close = [c for c in usable if c.shrink >= rules.graded_shrink and c.after < rules.graded_remainder]
    if close:
        return _named_or_undecided(judge, close[0], usable)
    best = usable[0] if usable else None
    return Verdict("unexplained", shrink=best.shrink if best is not None else 0.0, best=best,
                   grade=judge.grade(best) if best is not None else None)


def _named_or_undecided(judge: Judge, top, usable: list) -> Verdict:
    """``top`` (the best model of the simplest tier that explains the data) against every other family's best
    model, of any tier (a flexible model must be beaten, not ignored), whether that reaches the floor or not.

    The rivals are those ``top`` is not clearly better than (a more flexible one that ``Rules.occam`` names, only
    when it explains the data and is ahead of ``top`` by ``Rules.ahead_se`` standard errors).  A model naming
    another's families and more adds nothing these data single out: of ``top`` and its rivals only the minimal
    ones count.  One left: it is named.  Else ``undecided`` among them, best first; families they all share (pairs
    with one family in common: the data want it and a second effect they cannot single out) are
    :attr:`Verdict.shared`, or with ``Rules.name_shared`` named (the second effect left in ``confounded_with``).
    Families whose laws are widened by one signature cannot be told apart by it: they are rivals whatever their own
    laws do."""
    best_of = {}
    for c in usable:                              # each family set's best model
        best_of.setdefault(frozenset(c.families), c)
    # a model (of any tier) that predicts clearly better than the simplest explanation replaces it
    better = [c for c in best_of.values() if judge.explains(c) and judge.clearly_better(c, top)]
    while better:
        top = min(better, key=lambda c: float(np.mean(c.heldout_deviance)))
        better = [c for c in best_of.values() if judge.explains(c) and judge.clearly_better(c, top)]
    best_of.pop(frozenset(top.families), None)
    rivals = [c for c in best_of.values() if not judge.clearly_better(top, c) and not (
        _occam(judge.rules, top, c) and not judge.clearly_better(c, top)
        and not (judge.explains(c) and (judge.ahead(c, top) or _sibling(judge.rules, top, c))))]
    if top.kind in WIDENED:
        # any family's widened law on the same signature, its best model or not (its own law may score lower)
        held = {frozenset(top.families)} | {frozenset(r.families) for r in rivals}
        for c in usable:
            if (c.kind == top.kind and c.groups == top.groups and judge.explains(c)
                    and frozenset(c.families) not in held):
                rivals.append(c)
                held.add(frozenset(c.families))
    group = [top, *sorted(rivals, key=lambda c: c.score)]
    sets = [frozenset(c.families) for c in group]
    # a model naming fewer families takes a rival's place only when it explains the data as well (when ``top``
    # does): one that falls short leaves both, the data wanting the extra family or not
    fewer = [fams for c, fams in zip(group, sets) if judge.explains(c) or not judge.explains(top)
             or not judge.rules.minimal_explains]
    minimal = [c for c, fams in zip(group, sets) if not any(other < fams for other in fewer)]
    core = frozenset.intersection(*sets)
    extra = tuple(dict.fromkeys("+".join(c.families) for c in group if frozenset(c.families) != core))
    if len(minimal) == 1 or (core and judge.rules.name_shared):
        named = minimal[0] if len(minimal) == 1 else top
        families = tuple(f for f in named.families if len(minimal) == 1 or f in core)
        confounded = [n for n in dict.fromkeys(list(extra) + _confounded(judge, named, usable))
                      if n != "+".join(families)]
        return Verdict("named", model=named, families=families, confounded_with=tuple(confounded),
                       grade=judge.grade(named), shrink=named.shrink, best=named if named.kind in WIDENED else None)
    return Verdict("undecided", model=top, grade=judge.grade(top), shrink=top.shrink,
                   best=top if top.kind in WIDENED else None,
                   candidates=tuple("+".join(c.families) for c in minimal),
                   shared=tuple(f for f in top.families if f in core))


def _occam(rules: Rules, top, other) -> bool:
    """Whether ``other``, more flexible than ``top``, rivals it only when it explains the data and is ahead of it
    (``Rules.occam``): with ``"siblings"``, when it is a widened law on a signature of ``top``'s families.  (With
    :attr:`Rules.sibling_rivals` a flux sibling's widened law that explains rivals it, ahead or not:
    :func:`_sibling`.)"""
    if TIERS.index(other.kind) <= TIERS.index(top.kind) or rules.occam == "none":
        return False
    if rules.occam == "all":
        return True
    from ambfit.estimation.basis import FAMILY_GROUPS

    return other.kind in WIDENED and other.groups in {FAMILY_GROUPS.get(f) for f in top.families}


def _sibling(rules: Rules, top, other) -> bool:
    """Whether ``other`` is another flux family's law widened by the flux families' shared signature, ``top`` one
    flux family's library law (:attr:`Rules.sibling_rivals`: then it rivals ``top`` when it explains the data, ahead
    of it or not)."""
    from ambfit.estimation.basis import FAMILY_GROUPS

    flux = FAMILY_GROUPS["saturation"]
    return (rules.sibling_rivals and top.kind == "law" and other.kind == "signature" and other.groups == flux
            and FAMILY_GROUPS.get(top.effect) == flux and not set(other.families) & set(top.families))


def _confounded(judge: Judge, model, others: list) -> list[str]:
    """The models of ``others`` (any tier) that explain the data too and are not clearly worse than ``model``:
    what a user should know these data do not exclude.  Not ``model``'s own families."""
    own = "+".join(model.families)
    names = ["+".join(o.families) for o in others
             if judge.explains(o) and not judge.clearly_better(model, o)]
    return [n for n in dict.fromkeys(names) if n != own]
