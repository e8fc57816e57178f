"""The contract's held-out score (DATA-CONTRACT.md section 3) against numbers computed by hand.

``excess = sqrt(max(mean(z^2) - 1, 0))`` is the model error beyond the noise floor in noise units;
``shrink = 1 - excess_after / excess_before`` the fraction of it an effect removes.
"""

import math
import types
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from ambfit import diagnosis as D
from ambfit import rig
from ambfit.diagnosis.heldout import BIAS_RANGES
from ambfit.physics import effects as E
from ambfit.rig import protocol as P

# excess and shrink are a mean, a square root and a ratio: 1e-14 relative is round-off; a formula change
# (e.g. squaring the ratio) moves the values by 0.1 or more.
REL = 1e-14


def test_excess_by_hand():
    # mean(z^2) = 4 -> sqrt(3) = 1.7320508075688772
    assert D.excess([2.0, -2.0, 2.0, -2.0]) == pytest.approx(1.7320508075688772, rel=REL)
    # mean(z^2) = (9 + 0) / 2 = 4.5 -> sqrt(3.5) = 1.8708286933869707
    assert D.excess(np.array([3.0, 0.0])) == pytest.approx(1.8708286933869707, rel=REL)
    # exactly on the floor, and below it (mean(z^2) = (0.25 + 0.25 + 1) / 3 = 0.5): no excess, not NaN
    assert D.excess([1.0, -1.0, 1.0]) == 0.0
    assert D.excess([0.5, -0.5, 1.0]) == 0.0


def test_shrink_by_hand():
    before = D.excess([3.0, -3.0])          # sqrt(9 - 1) = sqrt(8)
    after = D.excess([1.5, -1.5])           # sqrt(2.25 - 1) = sqrt(1.25)
    assert before == pytest.approx(math.sqrt(8.0), rel=REL) and after == pytest.approx(math.sqrt(1.25), rel=REL)
    # 1 - sqrt(1.25) / sqrt(8) = 1 - sqrt(0.15625) = 0.6047152924789526 (python math);
    # the squared ratio would give 1 - 1.25/8 = 0.84375
    assert D.shrink(before, after) == pytest.approx(0.6047152924789526, rel=REL)
    # residuals pushed below the floor: all of the excess removed
    assert D.shrink(before, D.excess([0.9, -0.9])) == 1.0
    # nothing to remove, and a model that makes it worse (1 - sqrt(8)/sqrt(3) = -0.6329931618554521)
    assert D.shrink(0.0, 1.0) == 0.0
    assert D.shrink(math.sqrt(3.0), math.sqrt(8.0)) == pytest.approx(-0.6329931618554521, rel=REL)


def test_candidate_reports_the_contract_shrink():
    c = D.Candidate("saturation", heldout_z=np.array([1.5, -1.5, 1.5, -1.5]), before=math.sqrt(8.0), fit=None)
    assert c.after == pytest.approx(math.sqrt(1.25), rel=REL)
    assert c.shrink == pytest.approx(0.6047152924789526, rel=REL)
    assert c.score == pytest.approx(2.25, rel=REL)       # mean z^2


def test_heldout_residuals_refit_only_loads_no_training_row_saw():
    # Groups (load_id|axis): a|v has training and test rows; b|v is held out entirely with an unknown load
    # (its one nuisance number is refitted on the test rows: the mean is removed); c|v is held out with a
    # known load (nothing to refit).
    df = pd.DataFrame({"axis": ["v"] * 7, "load_id": ["a", "a", "a", "b", "b", "c", "c"],
                       "load_N": [np.nan, np.nan, np.nan, np.nan, np.nan, 5.0, 5.0]})
    z = np.array([0.3, 1.0, -2.0, 4.0, 2.0, 3.0, 1.0])
    test = np.array([False, True, True, True, True, True, True])
    out = D.heldout_residuals(types.SimpleNamespace(residuals=z, fitted_rows=~test), df, test)
    # b: 4 and 2 minus their mean 3 -> 1, -1
    np.testing.assert_array_equal(out, [1.0, -2.0, 1.0, -1.0, 3.0, 1.0])
    assert z[3] == 4.0                                    # the fit's residuals are not modified
    # a's one training row left out of the fit as an outlier: no row the fit used saw a's load, refitted too
    # (1 and -2 minus their mean -0.5 -> 1.5, -1.5)
    out = D.heldout_residuals(types.SimpleNamespace(residuals=z, fitted_rows=np.zeros(7, bool)), df, test)
    np.testing.assert_array_equal(out, [1.5, -1.5, 1.0, -1.0, 3.0, 1.0])


def test_folds_follow_the_operating_regions():
    df = pd.DataFrame({"axis": ["v"] * 6, "bias_A": [1.0, 1.4, 1.8, 1.0, 1.4, 1.8],
                       "load_id": ["m0", "m0", "m1", "m1", "m2", "m2"], "iteration": [1, 1, 1, 2, 2, 2]})
    name, tests = D.folds(df)
    assert name == "leave-one-load-out" and [t.tolist() for t in tests] == [
        [True, True, False, False, False, False], [False, False, True, True, False, False],
        [False, False, False, False, True, True]]
    name, tests = D.folds(df.drop(columns="load_id"))
    assert name == "leave-one-bias-out" and len(tests) == 3 and tests[0].tolist() == [True, False, False] * 2
    name, tests = D.folds(df.drop(columns="load_id").assign(bias_A=[1.4, 1.6] * 3))
    assert name == "alternate iterations" and tests[1].tolist() == [True, True, True, False, False, False]
    # many biases: neighbouring ones are held out together, in BIAS_RANGES ranges of about equal count
    many = pd.DataFrame({"axis": "v", "bias_A": np.repeat(np.linspace(0.8, 2.0, 20), 2)[::-1],
                         "iteration": 1})
    name, tests = D.folds(many)
    assert name == f"leave-one-bias-range-out ({BIAS_RANGES} ranges of 20 biases)" and len(tests) == BIAS_RANGES
    assert np.all(np.sum(tests, axis=0) == 1)                   # every reading held out once
    held = [np.unique(many["bias_A"][t]) for t in tests]
    assert all(len(h) in (2, 3) for h in held)                      # 20 biases in 8 ranges
    assert all(a.max() < b.min() for a, b in zip(held, held[1:]))   # contiguous, in order


def test_diagnosis_record_follows_the_formula_on_a_saturating_rig():
    # Three biases at ±20 and ±40 µm on a rig that saturates (b_sat 1.2 T): leave-one-bias-out folds; the
    # record's shrink is 1 - after / before of its own held-out excesses.  (Whether the removed part suffices
    # for a verdict is the diagnosis' judgement, tested in test_gap.py: extrapolating to a held-out 1.8 A
    # bias, saturation removes about a fifth of the excess here.)
    proto = P.perturbation((1.0, 1.4, 1.8), (20e-6, 40e-6), center=(-33.3e-6, 11.3e-6))
    data = rig.simulate(rig.PAPER_RIG, proto, (E.Saturation(b_sat=1.2, sharpness=5.0),), seed=5).data
    d = D.diagnose(data, candidates=[E.Saturation()], pairs=False)
    assert d.folds == "leave-one-bias-out"
    top = d.ranking[0]
    # the contract's formula written out here, not the library's excess(): sqrt(max(mean(z^2) - 1, 0)); 1e-12:
    # another order of summation is round-off, a formula change moves it by 0.1 or more
    def by_hand(z):
        return math.sqrt(max(float(np.mean(np.square(np.asarray(z, float)))) - 1.0, 0.0))

    assert d.heldout_excess_before == pytest.approx(by_hand(d.ideal.heldout_z), rel=1e-12)
    assert top.after == pytest.approx(by_hand(top.heldout_z), rel=1e-12)
    rec = d.to_json()
    r0 = rec["ranking"][0]
    assert r0["shrink"] == pytest.approx(1.0 - r0["heldout_excess_after"] / r0["heldout_excess_before"], rel=REL)
    assert rec["verdict"] != "none" and rec["shrink"] == pytest.approx(r0["shrink"], rel=REL)
    assert rec["heldout_excess_before"] > 3.0 and 0.0 < rec["shrink"] < 1.0   # structured before, partly removed


def test_two_threads_give_the_one_thread_diagnosis():
    # The fits run two at a time (threads=2, the default); each is the same computation as one after another,
    # and the results come back in the candidates' order: the same records.  Up to round-off: with two threads
    # BLAS runs one thread per fit, which sums the discrepancy's matrix products in another order (1e-14
    # relative measured; a fit swapped with another candidate's differs in the first digits).
    import json

    proto = P.perturbation((1.0, 1.4, 1.8), (20e-6, 40e-6), center=(-33.3e-6, 11.3e-6))
    data = rig.simulate(rig.PAPER_RIG, proto, (E.Saturation(b_sat=1.2, sharpness=5.0),), seed=5).data
    cands = [E.Saturation(), E.Fringing(), E.CurrentOffset()]
    one, two = (json.loads(json.dumps(D.diagnose(data, candidates=cands, threads=t).to_json(), default=float))
                for t in (1, 2))

    def same(a, b, path="record"):
        assert type(a) is type(b), path
        if isinstance(a, dict):
            assert a.keys() == b.keys(), path
            for k in a:
                same(a[k], b[k], f"{path}/{k}")
        elif isinstance(a, list):
            assert len(a) == len(b), path
            for j, (x, y) in enumerate(zip(a, b)):
                same(x, y, f"{path}[{j}]")
        elif isinstance(a, float):
            assert a == pytest.approx(b, rel=1e-9, abs=1e-300), path
        else:
            assert a == b, path

    same(one, two)
    assert [r["effect"] for r in one["ranking"]] == [r["effect"] for r in two["ranking"]]
    with pytest.raises(ValueError, match="threads"):
        D.diagnose(data, candidates=cands, threads=0)


def test_recent_drops_the_least_recently_used():
    from ambfit._recent import Recent

    r = Recent(2)
    r.put("a", 1)
    r.put("b", 2)
    assert r.get("a") == 1          # "a" used: "b" is now the least recent
    r.put("c", 3)
    assert r.get("b") is None and r.get("a") == 1 and r.get("c") == 3 and len(r) == 2


def test_ideal_fit_stalled_near_its_minimum_is_the_diagnosis_reference(monkeypatch):
    # a law far from the readings can stall a few 1e-5 of χ² short of the estimate's EDM limit (1e-6); the
    # diagnosis compares χ² in noise units and keeps it; a stall further off than BASELINE_EDM still stops it
    import dataclasses

    import ambfit
    from ambfit.diagnosis import attribution

    df = pd.read_csv(Path(__file__).resolve().parents[1] / "data" / "paper_table2.csv")
    res = ambfit.fit(df)
    stalled = dataclasses.replace(res, edm=9.3e-5)
    assert not stalled.converged and stalled.well_conditioned
    monkeypatch.setattr(attribution, "fit", lambda *a, **k: stalled)
    assert attribution._baseline(df, res.bearing, {}) is stalled
    far = dataclasses.replace(res, edm=2 * attribution.BASELINE_EDM)
    monkeypatch.setattr(attribution, "fit", lambda *a, **k: far)
    with pytest.raises(ambfit.FitError, match="EDM 0.02"):
        attribution._baseline(df, res.bearing, {})
