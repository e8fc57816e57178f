"""The paper's effective-origin search on the rig."""

import numpy as np
import pytest

from ambfit import rig
from ambfit.studies import origin


def test_noise_free_search_converges_in_one_move():
    res = origin.search(rig.PAPER_RIG, noise=rig.NOISE_FREE, iterations=3, run_all=False, tolerance=1e-9)
    assert res.converged and res.converged_at == 2
    np.testing.assert_allclose(res.centers[1], [-33.3e-6, 11.3e-6], atol=1e-12)
    np.testing.assert_allclose(res.g0, [[775e-6, 763e-6]] * 2, rtol=1e-9)


def test_noisy_search_settles_on_the_effective_origin():
    res = origin.search(rig.PAPER_RIG, iterations=10, seed=11)
    assert res.n_iterations == 10 and len(res.data) == 10 * 8
    # after the first move the centres scatter around -x0 by about the per-iteration origin error (~1 µm)
    c = res.centers[1:]
    np.testing.assert_allclose(c.mean(axis=0), [-33.3e-6, 11.3e-6], atol=2e-6)
    assert np.all(c.std(axis=0) < 3e-6)
    assert sorted(res.data.iteration.unique()) == list(range(1, 11))
    assert np.all(np.diff(res.data.time_s.to_numpy()) >= 0)


def test_search_from_a_random_start():
    res = origin.search(rig.PAPER_RIG, start=(30e-6, 30e-6), noise=rig.NOISE_FREE, iterations=2)
    assert res.centers[0].tolist() == [30e-6, 30e-6]
    np.testing.assert_allclose(res.offsets[0], [63.3e-6, 18.7e-6], rtol=1e-9)
    js = res.to_json()
    assert js["iterations"][1]["v_center_um"] == pytest.approx(-33.3)
