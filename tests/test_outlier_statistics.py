"""The outlier test's statistics on their own: studentized residuals and the robust scale.

Each test checks the textbook property the outlier test rests on, so that a wrong leverage or a wrong MAD
constant cannot pass unnoticed (the end-to-end robustness tests use small leverages, where neither shows).
"""

import types

import numpy as np
import pytest
from scipy.stats import norm

from ambfit.estimation import outliers, robust


def _linear_fits(rng, sets: int, held_out: int = 0):
    """Straight-line fits y = a + b x with unit noise on a design with two far-out (high-leverage) readings:
    ``(jac[sets, rows, 2], z[sets, rows], weight[sets, rows], h[rows])``; the last ``held_out`` rows are left out
    of the fit (weight 0) and their residuals are predictions."""
    # 200 readings near the centre keep the robust scale (a MAD) steady; two far out carry h of about 0.5
    x = np.concatenate([np.linspace(-1.0, 1.0, 200), [10.0, -8.0], np.linspace(-0.5, 0.5, held_out) + 9.0])
    jac = np.stack([np.ones_like(x), x], axis=1)
    w = np.ones(len(x))
    if held_out:
        w[-held_out:] = 0.0
    jw = jac[w > 0]
    cov = np.linalg.inv(jw.T @ jw)
    h = np.einsum("ni,ij,nj->n", jac, cov, jac)
    e = rng.standard_normal((sets, len(x)))
    beta = np.einsum("ij,nj,sn->si", cov, jw, e[:, w > 0])
    z = e - beta @ jac.T
    return np.broadcast_to(jac, (sets, *jac.shape)), z, np.broadcast_to(w, (sets, len(x))), h


def test_studentized_residuals_have_unit_variance_at_high_leverage():
    # Cook & Weisberg (1982) sec. 2.2: var(z_i) = 1 - h_ii for a fitted reading, 1 + h_ii for a left-out one,
    # so t_i = z_i / sqrt(1 -/+ h_ii) has unit variance whatever the leverage (here up to h = 0.6)
    rng = np.random.default_rng(0)
    jac, z, w, h = _linear_fits(rng, 4000, held_out=2)
    # known noise (unit): the robust scale is max(1, 1.4826 MAD), above 1 on about half the sets, which
    # shrinks every row's variance alike by E[1/s^2] (about 0.94 here)
    t = robust.studentized_many(jac, z, w, known_noise=True)
    high = np.nonzero((h > 0.25) & (w[0] > 0))[0]
    out = np.nonzero(w[0] == 0)[0]
    assert len(high) == 2 and len(out) == 2 and h[np.r_[high, out]].min() > 0.25   # really high leverages
    var = np.var(t, axis=0)
    low = var[:200].mean()
    assert 0.85 < low <= 1.02
    # 4000 sets: each row's variance has a standard error of sqrt(2 / 4000) = 2.2 %, hence 10 % (4.5 se)
    assert np.all(np.abs(var[high] / low - 1.0) < 0.1), var[high] / low
    assert np.all(np.abs(var[out] / low - 1.0) < 0.1), var[out] / low     # predictions: var(z) = 1 + h
    assert np.all(np.abs(np.var(z, axis=0)[high] - (1 - h[high])) < 0.05)   # the raw residuals are not


def test_robust_scale_of_gaussian_residuals_is_their_sd():
    # 1.4826 = 1 / Φ⁻¹(3/4): the MAD of N(0, σ²) is σ Φ⁻¹(3/4), so 1.4826 MAD estimates σ
    assert 1 / norm.ppf(0.75) == pytest.approx(1.4826, abs=1e-4)
    rng = np.random.default_rng(1)
    for sigma in (0.5, 2.0, 7.0):
        z = sigma * rng.standard_normal(20000)
        # 20000 draws: the MAD estimate's relative standard error is about 1.17 / sqrt(20000) = 0.8 %
        assert robust.robust_scale(z, known_noise=False) == pytest.approx(sigma, rel=0.04)
    # known noise levels: never below 1, so a noise level stated too large does not make readings outliers
    assert robust.robust_scale(0.5 * rng.standard_normal(20000), known_noise=True) == 1.0
    assert robust.robust_scale(2.0 * rng.standard_normal(20000), known_noise=True) == pytest.approx(2.0, rel=0.04)


def test_a_round_of_studentized_residuals_that_fails_fails_only_its_own_screens():
    """The screens' studentized residuals are measured stacked; one data set whose measurement fails (a Jacobian
    that is not finite) gets its own error, thrown into its screen, and the others their values, as if alone.  The
    first measurement of a study's fits leaves the failing one to its screen."""
    rng = np.random.default_rng(0)

    def asked(jac):
        return outliers.Studentize(types.SimpleNamespace(jacobian_rows=jac, residuals=rng.normal(size=6)),
                                   types.SimpleNamespace(mask=np.ones(6)), True)

    good, bad = asked(rng.normal(size=(6, 2))), asked(np.full((6, 2), np.nan))
    out = outliers._studentized_all({"good": good, "bad": bad})
    assert isinstance(out["bad"], np.linalg.LinAlgError)
    alone = robust.studentized(good.res.jacobian_rows, good.res.residuals, np.ones(6, bool), np.ones(6))
    np.testing.assert_array_equal(out["good"], alone)
    known = types.SimpleNamespace(noise_estimated=False)
    first = outliers.studentized([good.res, bad.res], [good.prob, bad.prob], [known, known])
    np.testing.assert_array_equal(first[0], alone)
    assert first[1] is None


def test_the_robust_scale_is_the_median_of_each_rows_finite_fitted_residuals():
    """Exactly ``1.4826 median |z|`` over a row's fitted finite entries, odd and even counts, as ``np.median``
    gives it (the scale sorts rather than calling ``np.nanmedian``); a row with none is 1."""
    rng = np.random.default_rng(3)
    z = 3.0 * rng.standard_normal((40, 9))
    z[rng.random(z.shape) < 0.2] = np.nan
    fitted = rng.random(z.shape) < 0.8
    fitted[0] = False                                      # no reading of its own: scale 1
    scales = robust._scales(z, fitted, known_noise=False)
    for row, use, scale in zip(z, fitted, scales):
        kept = np.abs(row[use & np.isfinite(row)])
        assert scale == (1.4826 * np.median(kept) if len(kept) else 1.0)
    assert len({int(np.sum(u & np.isfinite(r))) % 2 for r, u in zip(z, fitted)}) == 2     # odd and even counts
