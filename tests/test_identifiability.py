"""An effect the data cannot see is reported as not identifiable, not as a solver that ran out of steps."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import ambfit
from ambfit import rig
from ambfit.estimation import conditioning, fit, identification
from ambfit.estimation.core import FitError
from ambfit.physics import effects as E
from ambfit.rig import protocol

TABLE2 = Path(__file__).resolve().parents[1] / "data" / "paper_table2.csv"


@pytest.fixture(scope="module")
def table2():
    return ambfit.read_csv(TABLE2)


def test_two_close_biases_do_not_determine_saturation(table2):
    # the paper's protocol (1.4/1.6 A): each saturation parameter keeps more than half its prior's variance; a
    # bias sweep (rich preset, 1.0-1.6 A up and down) of a saturating rig determines them to a thousandth
    shares = conditioning.effect_identification(table2, (E.Saturation(),))
    assert set(shares) == {f"saturation.{f}[{ax}]" for f in ("b_sat", "sharpness") for ax in "vw"}
    assert min(shares.values()) > 0.5 > identification.MAX_PRIOR_SHARE
    sweep = rig.simulate(rig.PAPER_RIG, protocol.rich(), [E.Saturation(b_sat=np.asarray(1.2))], seed=1).data
    assert max(conditioning.effect_identification(sweep, (E.Saturation(),)).values()) < 0.01


def test_a_non_converged_fit_of_an_unseen_effect_says_not_identifiable(table2):
    res = fit.fit(table2, (E.Saturation(),), throw=False)
    assert not res.converged and res.well_conditioned     # the weak priors keep the Jacobian well conditioned
    res = dataclasses.replace(res, effect_identification=conditioning.effect_identification(table2,
                                                                                            (E.Saturation(),)))
    with pytest.raises(FitError) as err:
        res.raise_for_health()
    text = str(err.value)
    assert text.startswith("not identifiable: saturation.b_sat[v]") and "not determined by these data" in text
    assert "bias sweep" in text and "--preset rich" in text and "did not converge" not in text
    assert any(h.startswith("not identifiable") for h in res.health())


def test_fit_of_saturation_on_table2_says_not_identifiable(table2):
    with pytest.raises(FitError, match="not identifiable: saturation"):
        ambfit.fit(table2, effects=(ambfit.Saturation(),))
