"""The engine for repeated work (ambfit.engine) and the mixed-design batch (ambfit.estimation.fit.fit_many).

In this process, on a real ``distributed.LocalCluster`` of two worker processes, and the same numbers from both: the
seeds are per item, so neither the number of workers nor the chunk size may change a result.  The mixed batch must
give each data set the fit it gets alone, and its padding must not be able to move an estimate.
"""

import functools
import importlib.util
import math
import os
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pandas as pd
import pytest

from ambfit import engine
from ambfit.estimation import batches, core, fit
from ambfit.physics.bearing import PAPER_BEARING
from ambfit.rig import protocol as P
from ambfit.rig import virtual as rig

CENTER = (-33.3e-6, 11.3e-6)          # the paper rig's effective origin: pairs centred on it, as the paper runs them
OTHER_BEARING = PAPER_BEARING.with_(name="smaller bearing", pole_angle=math.radians(20.0), nominal_gap=500e-6)
OTHER_RIG = rig.RigSpec(bearing=OTHER_BEARING, g0=(510e-6, 495e-6), x0=(8e-6, -5e-6))

# Agreement of a batch estimate with the single fit: both stop once the estimated distance to the minimum is below
# core.EDM_MAX (each parameter within ~1e-3 standard errors of the optimum); near the optimum Levenberg-Marquardt's
# trust-region test accepts or rejects steps on round-off, so a start that differs in the 16th digit (the batch's
# vectorised Eq. 7 seed vs closed_form.identify) ends up to ~4e-9 relative away (measured: most parameters agree
# exactly, the largest difference on these data sets is 4e-9 of a 33 µm origin).
RTOL = 1e-8


def _mixed_datasets():
    """Data sets of different designs, lengths, axes, load groups, noise columns and bearings, and their bearings.

    Chosen to share few padded shapes (each is a compilation): every set pads to 32 rows, one bucket per bearing
    and number of loads (three unknown loads on two axes: six, padded to eight); the four-position design has no
    Eq. 7 pairs (fit's own start).
    """
    unknown = {f"u{j}": P.Load(4.0 + j, 3.0 - j, known=False) for j in range(3)}
    three_loads = P.concat(*(P.perturbation((1.3, 1.6), (25e-6,), center=CENTER, load=f"u{j}",
                                            loads={f"u{j}": unknown[f"u{j}"]}, experiment=f"L{j}") for j in range(3)))
    two_biases = P.perturbation((1.2, 1.5), (30e-6,), center=CENTER, iterations=3)
    sims = [
        rig.simulate(rig.PAPER_RIG, P.paper_table2(iterations=3, center=CENTER), seed=1).data,
        rig.simulate(rig.PAPER_RIG, two_biases, noise=rig.Noise(1.0e-3, 0.2e-6), seed=2).data,
        rig.simulate(rig.PAPER_RIG, three_loads, seed=3).data,
        rig.simulate(rig.PAPER_RIG, P.perturbation((1.4, 1.6), (15e-6, 30e-6), center=CENTER, iterations=3),
                     seed=5).data.query("axis == 'v'").reset_index(drop=True),
        rig.simulate(rig.PAPER_RIG, P.paper_table2(iterations=5, center=CENTER), seed=6).data.query("axis == 'v'")
        .reset_index(drop=True),
        rig.simulate(rig.PAPER_RIG, two_biases, seed=7).data.drop(columns=["i_top_std_A", "i_bottom_std_A"]),
        rig.simulate(OTHER_RIG, P.perturbation((1.0, 1.3), (20e-6,), center=(-8e-6, 5e-6), iterations=3),
                     seed=8).data,
    ]
    return sims, [PAPER_BEARING] * 6 + [OTHER_BEARING]


@pytest.fixture(scope="module")
def mixed():
    return _mixed_datasets()


def _assert_same_fit(a, b, rtol=RTOL):
    assert a.names == b.names
    np.testing.assert_allclose(a.values, b.values, rtol=rtol)
    np.testing.assert_allclose(a.std, b.std, rtol=10 * rtol)
    assert abs(a.chi2 - b.chi2) <= 1e-6 * b.chi2
    assert (a.converged, a.well_conditioned, a.adequate, a.dof, len(a.outliers)) == \
        (b.converged, b.well_conditioned, b.adequate, b.dof, len(b.outliers))


# --- the mixed-design batch ------------------------------------------------------------------------------------

def test_mixed_designs_in_one_batch_equal_their_single_fits(mixed):
    data, bearings = mixed
    assert len({len(d) for d in data}) == 2 and len(set(bearings)) == 2
    many = fit.fit_many(data, bearing=bearings, loss="linear")
    for d, b, res in zip(data, bearings, many):
        _assert_same_fit(res, fit.fit(d, bearing=b, loss="linear", throw=False))
    # the one-axis set estimates only its axis; three unknown loads on two axes are six nuisance parameters
    assert "g_w0" not in many[4].names and sum(n.startswith("load[") for n in many[2].names) == 6
    assert many[5].noise_estimated and not many[0].noise_estimated
    assert "g_w0" not in many[3].names


def test_fit_many_with_the_outlier_test_equals_fit(mixed):
    data, bearings = mixed
    bad = data[0].copy()
    bad.loc[5, "i_top_A"] += 0.05              # one reading ~60 σ off: fit names it and leaves it out
    many = fit.fit_many([bad, data[1]])
    alone = fit.fit(bad, throw=False)
    assert [o.row for o in many[0].outliers] == [o.row for o in alone.outliers] == [6]
    _assert_same_fit(many[0], alone)
    _assert_same_fit(many[1], fit.fit(data[1], throw=False))


def test_fit_many_reports_what_fit_raises(mixed):
    data, _ = mixed
    out = fit.fit_many(data[2:3], require_k=True)          # unknown loads only: k cannot be calibrated
    with pytest.raises(core.FitError) as single:
        fit.fit(data[2], require_k=True)
    assert isinstance(out[0], core.FitError) and str(out[0]) == str(single.value)
    with pytest.raises(ValueError, match="loss must be one of"):
        fit.fit_many(data[:1], loss="l1")
    # a robust loss reweights each data set in rounds of its own, after the joint solve
    _assert_same_fit(fit.fit_many(data[:2], loss="huber")[1], fit.fit(data[1], loss="huber", throw=False))


def test_padded_rows_and_loads_cannot_change_a_result(mixed, monkeypatch):
    data, bearings = mixed
    reference = fit.fit_many(data[2:3], loss="linear")                 # alone: its own shape, no padding
    # two data sets are padded and vmapped: pad far more than the buckets do, three padded rows per real row,
    # three more padded loads
    monkeypatch.setattr(batches, "row_bucket", lambda n: 4 * n)
    monkeypatch.setattr(batches, "load_bucket", lambda m: m + 3)
    padded = fit.fit_many([data[2], data[2]], loss="linear")[:1]
    for a, b in zip(padded, reference):
        _assert_same_fit(a, b)


def test_an_effects_entries_follow_the_padded_loads(mixed, monkeypatch):
    """With an effect fitted, a batch's theta holds the head, each data set's own loads, the padded loads and then
    the effect's entries: a data set padded in rows and loads fits as alone, bias correction included."""
    from ambfit.physics.effects import CurrentOffset

    data, _ = mixed
    reference = fit.fit_many(data[2:3], (CurrentOffset(),), loss="linear")[0]
    monkeypatch.setattr(batches, "row_bucket", lambda n: 2 * n)
    monkeypatch.setattr(batches, "load_bucket", lambda m: m + 3)
    padded = fit.fit_many([data[2], data[2]], (CurrentOffset(),), loss="linear")[0]
    assert reference.model != "ideal" and "skipped" not in reference.bias_correction
    assert padded.names == reference.names and padded.dof == reference.dof
    # in standard errors (the bias sums of a padded batch and of a fit alone differ at the round-off of their
    # differences: 2e-8 of an offset here, where the plain solves agree to 1e-8 relative)
    assert np.max(np.abs(padded.values - reference.values) / reference.std) < 1e-6
    subtracted = [np.array([r.bias_correction[n]["subtracted"] for n in r.names]) for r in (padded, reference)]
    assert np.max(np.abs(subtracted[0] - subtracted[1]) / reference.std) < 1e-6


def test_padded_rows_have_zero_residual_and_zero_jacobian(mixed):
    data, _ = mixed
    prob, _ = core.build_problem(data[2])
    theta = fit.fit(data[2], loss="linear").theta
    n, p = len(data[2]), len(theta)
    stacked = batches.pad([prob], n + 20)
    one = jax.tree.map(lambda a: a[0], stacked)                    # the padded problem of a batch of one
    padded_theta = np.concatenate([theta, np.zeros(3)])            # three loads no row points at
    r = np.asarray(core.residuals(padded_theta, one))
    j = np.asarray(core.jacobian(padded_theta, one))
    assert np.all(r[n:] == 0.0) and np.all(j[n:] == 0.0)           # padded rows
    assert np.all(j[:, p:] == 0.0)                                 # padded loads
    np.testing.assert_allclose(r[:n], np.asarray(core.residuals(theta, prob)), rtol=1e-12, atol=1e-12)


def test_row_buckets_bound_the_padding():
    assert [batches.row_bucket(n) for n in (1, 16, 17, 24, 32, 33, 80, 480)] == [16, 16, 32, 32, 32, 64, 128, 512]
    assert all(n <= batches.row_bucket(n) < 2 * n for n in range(17, 2000))
    assert [batches.load_bucket(m) for m in (0, 1, 2, 3, 5)] == [0, 1, 2, 4, 8]


# --- the engine in this process --------------------------------------------------------------------------------

def _noise_of(items, seeds):
    """A chunk function: one normal draw per item from its own seed."""
    return [(x, float(np.random.default_rng(s).normal())) for x, s in zip(items, seeds)]


def test_in_process_results_do_not_depend_on_the_chunk_size():
    ref = engine.Engine().map_batches(_noise_of, range(11), seed=7, chunk_size=11)
    for size in (1, 3, 4):
        assert engine.Engine().map_batches(_noise_of, range(11), seed=7, chunk_size=size) == ref
    assert [x for x, _ in ref] == list(range(11))
    calls = []
    engine.Engine().map_batches(_noise_of, range(11), seed=7, chunk_size=4, progress=lambda *a: calls.append(a))
    assert calls == [("items", 0, 11), ("items", 4, 11), ("items", 8, 11), ("items", 11, 11)]


def test_bad_arguments_and_a_chunk_function_that_loses_items():
    with pytest.raises(ValueError, match="not both"):
        engine.Engine(workers=2, scheduler="tcp://localhost:8786")
    with pytest.raises(ValueError, match="positive integer"):
        engine.Engine(workers=0)
    with pytest.raises(engine.EngineError, match="one result per item"):
        engine.Engine().map_batches(lambda items: items[:-1], range(4), chunk_size=2)


def test_the_default_runs_without_dask():
    # a fresh interpreter in which dask cannot be imported: the in-process engine, SBC's and the batch's code paths
    code = textwrap.dedent("""
        import sys
        sys.modules["dask"] = sys.modules["distributed"] = None
        from ambfit import engine
        assert engine.Engine().map(abs, [-1, 2]) == [1, 2]
        try:
            engine.Engine(workers=2).open()
        except engine.EngineError as exc:
            print(exc)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "install ambfit[dask]" in out.stdout


# --- a real cluster of two worker processes --------------------------------------------------------------------

needs_dask = pytest.mark.skipif(importlib.util.find_spec("distributed") is None,
                                reason="dask[distributed] is not installed (pip install 'ambfit[dask]'): the "
                                       "multi-process engine is not tested")


@pytest.fixture(scope="module")
def cluster():
    """Two worker processes, started once; a test makes them its studies' engine with ``with cluster:``."""
    eng = engine.Engine(workers=2).open()
    yield eng
    eng.close()


def _where(items):
    import jax
    import jax.numpy as jnp

    return [(os.getpid(), str(jnp.zeros(1).dtype), bool(jax.config.jax_enable_x64),
             os.environ.get("MALLOC_TRIM_THRESHOLD_"), os.environ.get("OMP_NUM_THREADS")) for _ in items]


@needs_dask
@pytest.mark.slow          # two worker processes
def test_workers_are_separate_float64_processes(cluster):
    assert cluster.kind == "local" and cluster.n_workers == 2
    seen = cluster.map_batches(_where, range(8), chunk_size=1)
    pids = {pid for pid, *_ in seen}
    assert os.getpid() not in pids and len(pids) == 2
    assert all(dtype == "float64" and x64 for _, dtype, x64, _, _ in seen)
    # Dask's other worker settings stay; its malloc trim threshold (a tenth of the CPU of batch fits) does not
    assert all(trim is None and omp == "1" for *_, trim, omp in seen)


DESIGNS = (P.paper_table2(iterations=2, center=CENTER),               # three designs of one length: one compilation
           P.perturbation((1.2, 1.5), (30e-6,), center=CENTER, iterations=2),
           P.perturbation((1.3, 1.6), (15e-6,), center=CENTER, iterations=2))


def _simulate_and_fit(items, seeds):
    """A Monte Carlo chunk: simulate each item's design with its seed, fit the chunk as one mixed batch."""
    data = [rig.simulate(rig.PAPER_RIG, DESIGNS[i % len(DESIGNS)], seed=np.random.default_rng(s)).data
            for i, s in zip(items, seeds)]
    return [np.concatenate([r.values[:4], r.std[:4]]) for r in fit.fit_many(data, loss="linear")]


@needs_dask
@pytest.mark.slow          # two worker processes
def test_same_numbers_in_process_and_on_two_workers_in_any_chunks(cluster):
    ref = engine.Engine().map_batches(_simulate_and_fit, range(9), seed=3, chunk_size=5)
    for size in (2, 4):
        got = cluster.map_batches(_simulate_and_fit, range(9), seed=3, chunk_size=size)
        np.testing.assert_allclose(np.array(got), np.array(ref), rtol=RTOL)
    # the same workers through their scheduler's address (as a dask-jobqueue cluster is used)
    with engine.Engine(scheduler=cluster.client.scheduler.address) as remote:
        assert remote.kind == "cluster" and remote.n_workers == 2
        got = remote.map_batches(_simulate_and_fit, range(9), seed=3, chunk_size=3)
    np.testing.assert_allclose(np.array(got), np.array(ref), rtol=RTOL)
    assert cluster.client.status == "running"          # the remote engine disconnected; the cluster runs on


@needs_dask
@pytest.mark.slow          # two worker processes
def test_sbc_and_paper_tables_are_identical_on_two_workers(cluster):
    from ambfit.studies import paper, sbc

    kw = dict(n_draws=9, n_steps=60, seed=11)
    here = sbc.run(2, **kw)
    with cluster:                                     # the studies' engine inside the block (engine.using)
        there = sbc.run(2, chunk_size=1, **kw)
    np.testing.assert_array_equal(here.ranks, there.ranks)
    for p in here.coverage:
        np.testing.assert_array_equal(here.coverage[p], there.coverage[p])
    a = paper.reproduce(replicates=2, seed=5, least_squares=False, iterations=3)
    with cluster:
        b = paper.reproduce(replicates=2, seed=5, least_squares=False, iterations=3, chunk_size=1)
    np.testing.assert_array_equal(a.replicates, b.replicates)
    pd.testing.assert_frame_equal(a.comparison(), b.comparison())
    pd.testing.assert_frame_equal(a.spread(), b.spread())


@needs_dask
def test_an_unreachable_scheduler_is_named():
    with pytest.raises(engine.EngineError, match="cannot reach the Dask scheduler at 'tcp://127.0.0.1:9'"):
        engine.Engine(scheduler="tcp://127.0.0.1:9", timeout=1).open()


@needs_dask
@pytest.mark.slow          # two worker processes
def test_a_task_error_reaches_the_caller(cluster):
    with pytest.raises(ZeroDivisionError):
        cluster.map(functools.partial(divmod, 1), [1, 0, 2], chunk_size=1)
