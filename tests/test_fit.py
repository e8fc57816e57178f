"""Least squares over all readings (core only; the least-squares issue adds calibration studies)."""

import numpy as np
import pytest

from ambfit import fit
from ambfit import protocol as P
from ambfit import rig


def _truth_within(res, spec, n_se=4.0, k=True):
    truth = {"g_v0": spec.g0[0], "g_w0": spec.g0[1], "v0": spec.x0[0], "w0": spec.x0[1]}
    if k:
        truth |= {"k_v": spec.force_constant, "k_w": spec.force_constant}
    for name, t in truth.items():
        assert abs(res.value(name) - t) < n_se * res.error(name), (name, res.value(name), t, res.error(name))


@pytest.mark.parametrize("seed", [0, 1])
def test_recovers_truth_on_symmetric_design(seed):
    sim = rig.simulate(rig.PAPER_RIG, P.paper_table2(center=(-33.3e-6, 11.3e-6)), seed=seed)
    res = fit.fit(sim.data)
    assert res.converged and res.k_identified == (True, True)
    _truth_within(res, rig.PAPER_RIG)
    assert 0.5 < res.reduced_chi2 < 1.6   # 80 rows, 6 parameters: chi2/dof within its ~99 % range


def test_recovers_truth_on_non_symmetric_rich_design():
    spec = rig.PAPER_RIG.with_truth(g0=(790e-6, 745e-6), x0=(-20e-6, 14e-6))
    sim = rig.simulate(spec, P.rich(), seed=3)
    res = fit.fit(sim.data)
    _truth_within(res, spec)
    assert res.error("g_v0") < 2e-6


def test_unknown_loads_leave_k_unidentified_and_unreported():
    loads = {"u": P.Load(5.0, 4.0, known=False)}
    proto = P.perturbation((1.2, 1.4, 1.6), (20e-6, 40e-6), center=(-33.3e-6, 11.3e-6), load="u", loads=loads,
                           iterations=3)
    sim = rig.simulate(rig.PAPER_RIG, proto, seed=2)
    res = fit.fit(sim.data)
    assert res.k_identified == (False, False) and "k_v" not in res.names
    _truth_within(res, rig.PAPER_RIG, k=False)


def test_single_position_is_not_identifiable():
    loads = {"u": P.Load(5.0, 4.0, known=False)}
    one = P.grid([(10e-6, 10e-6)], [1.2, 1.4, 1.6], load="u", loads=loads)
    sim = rig.simulate(rig.PAPER_RIG, one, seed=0)
    with pytest.raises(fit.FitError, match="no redundancy"):
        fit.fit(sim.data)
    repeated = P.concat(*(P.grid([(10e-6, 10e-6)], [1.2, 1.4, 1.6], load="u", loads=loads, iteration=i)
                          for i in range(4)))
    sim = rig.simulate(rig.PAPER_RIG, repeated, seed=0)
    with pytest.raises(fit.FitError, match="does not identify"):
        fit.fit(sim.data)


def test_missing_noise_levels_are_estimated_or_declared_and_said_so():
    sim = rig.simulate(rig.PAPER_RIG, P.paper_table2(iterations=3), seed=7)
    bare = sim.data.drop(columns=["i_top_std_A", "i_bottom_std_A", "v_std_um", "w_std_um"])
    est = fit.fit(bare)
    assert "current estimated" in est.noise_source and "position noise taken as 0" in est.noise_source
    # the estimated current noise is of the order of the rig's 0.6 mA (position noise folded in)
    level = float(est.noise_source.split("estimate ")[1].split(" mA")[0])
    assert 0.3 < level < 1.5
    dec = fit.fit(bare, sigma_i=0.6e-3, sigma_x=0.1e-6)
    assert "declared" in dec.noise_source
    ref = fit.fit(sim.data)
    assert dec.value("g_v0") == pytest.approx(ref.value("g_v0"), rel=1e-9)
    assert "std columns" in ref.noise_source


def test_noise_free_data_fits_exactly():
    sim = rig.simulate(rig.PAPER_RIG, P.paper_table2(iterations=2), noise=rig.NOISE_FREE)
    res = fit.fit(sim.data, sigma_i=1e-3, sigma_x=0.1e-6)
    assert res.value("g_v0") == pytest.approx(775e-6, rel=1e-8)
    assert res.value("k_w") == pytest.approx(rig.PAPER_RIG.force_constant, rel=1e-8)
    assert np.all(np.abs(res.residuals) < 1e-6)
