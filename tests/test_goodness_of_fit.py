"""χ² goodness of fit of a least-squares result: degrees of freedom and p-value."""

import numpy as np
import pytest
from scipy.stats import chi2, kstest

from ambfit import rig
from ambfit.estimation import fit
from ambfit.rig import protocol


def test_p_value_is_the_chi2_tail_with_rows_minus_free_parameters():
    # dof = fitted readings - estimated parameters (gap, origin, k per axis; no nuisance loads here), and the
    # p-value is scipy's chi2.sf(χ², dof); with dof = readings the p-value of a good fit is inflated towards 1
    spec = rig.PAPER_RIG
    proto = protocol.paper_table2(center=spec.centre)
    pvals = []
    for seed in range(12):
        res = fit.fit(rig.simulate(spec, proto, seed=seed).data, loss="linear")
        assert res.n_fit_rows == 80 and len(res.names) == 6
        assert res.dof == 80 - 6
        assert res.p_value == pytest.approx(chi2.sf(res.chi2, 74), rel=1e-9)
        pvals.append(res.p_value)
    # clean data: p-values uniform (KS test; 12 fits, a false alarm at 1 % is acceptable for a fixed seed set)
    assert kstest(pvals, "uniform").pvalue > 0.01
    assert np.mean(pvals) == pytest.approx(0.5, abs=0.25)
