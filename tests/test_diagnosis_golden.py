"""The diagnosis record held against references (issue 30): a change that is meant to leave the diagnosis alone
(a refactor, a faster route) must leave every key, string, flag and number of ``Diagnosis.to_json()`` as it was.

The cases cover the ways a verdict is reached: the bundled data (``none``, the protocol's blind spot), a library
law, a pair, laws of families the library does not write (a coupling through the other axis' currents named by its
signature, an exponential drift in time that its signature's settling curves reach (the case is named for the
verdict it had before they were there), a non-linear position sensor too weak to single out), iron reluctance that
saturation explains alike (``undecided``, with the protocol that would separate them), and the FEM development data
(the magnetic circuit, its pieces as families). Inputs are stored as they were simulated, so only the diagnosis is
compared. Keys must come in the same order, lists must have the same shapes, and strings, flags and integers must be
equal. Numbers must agree to a millionth of themselves (:data:`RTOL`) or, when that is a rounding's, to 1e-13 in SI
units and 1e-9 for numbers without a unit (log Bayes factors, shrinks, relative gains); a covariance's entries to a
millionth of their parameters' standard deviations, any other matrix's to a millionth of their row's scale. Why not
closer: the references were made on one machine, and another processor's vector instructions round the last bits
differently, which the flat directions of a fit amplify. Measured between an Intel machine and an AMD EPYC one,
every verdict, string and flag the same: a sensor gain error the data do not constrain (2e-8, zero within its
standard error) moved 4e-4 of itself (1e-11), log Bayes factors of zero moved 2e-10 nats, covariances of 1e-30
changed sign, a projection's row of 1e-22 entries moved by its own size, and the largest relative move of a number
that is not a rounding's zero was 1.2e-7 (a saturation sharpness).

When a change is *meant* to change the diagnosis, regenerate the references and say so in the commit:

    .venv/bin/python tests/test_diagnosis_golden.py --regenerate [CASE ...]
"""

import gzip
import json
import math
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
REFS = HERE / "data" / "diagnosis"
SHARED_FEM = HERE.parents[1] / "shared" / "fem"
STAMP = ("schema", "kind", "ambfit_version")

CASES = {
    "paper_table2": (HERE.parent / "data" / "paper_table2.csv", None),
    "law": (REFS / "rig_saturation.csv.gz", None),
    "pair": (REFS / "hid_saturation_offset.csv.gz", None),
    "signature": (REFS / "hid_coupling_currents.csv.gz", None),
    "short_of_the_floor": (REFS / "hid_drift_exponential.csv.gz", None),
    "weak": (REFS / "hid_position_nonlinear.csv.gz", None),
    "undecided": (REFS / "rig_iron_reluctance.csv.gz", None),
    "fem_dev": (SHARED_FEM / "fem_dev.csv", SHARED_FEM / "fem_dev.toml"),
}


def diagnosis_of(case: str, tmp: Path) -> dict:
    import ambfit

    data, bearing = CASES[case]
    if not data.exists():
        pytest.skip(f"{data} is not here")
    if data.suffix == ".gz":
        plain = tmp / data.stem
        plain.write_bytes(gzip.decompress(data.read_bytes()))
        data = plain
    kw = {"bearing": ambfit.Bearing.from_toml(bearing)} if bearing is not None else {}
    return ambfit.diagnose(ambfit.read_csv(data), **kw).to_json()


RTOL = 1e-6
"""Numbers agree to this share of themselves; a matrix's entries to this share of their row's scale."""
ATOL = 1e-13
"""...or to this, absolutely: numbers in SI units (a gap of 5e-4 m, a variance of 1e-14 m^2) stay tested."""
ATOL_PURE = 1e-9
"""...or to this for the numbers without a unit whose value is a rounding's zero: log Bayes factors [nats], shrinks,
an unconstrained relative sensor gain, a fit's distance from its minimum."""
PURE = ("log_bayes", "shrink", "gain_error", "edm")
REFIT_EDM_RTOL = 1e-3
"""The EDM of a circuit family's refit (a family record: ``piece``, ``edm``) is where the refit stopped: once its χ²
rise is settled (an EDM below a hundredth of the significance threshold) or decided, well short of the optimum that
:data:`ambfit.estimation.core.EDM_MAX` asks of a fit.  Reordered floating-point operations move where it stops: two
changes that only reorder the compiled program's operations moved the FEM case's iron refit EDM (0.088) by 3.5e-5 and
2.4e-5 relative while every other number of the diagnosis moved by 7e-8 at most.  Its χ² rise and bounds stay at
:data:`RTOL`."""


def _close(got: float, want: float, path: str) -> bool:
    if math.isnan(got) or math.isnan(want):
        return math.isnan(got) and math.isnan(want)
    atol = ATOL_PURE if any(p in path for p in PURE) else ATOL
    return math.isclose(got, want, rel_tol=RTOL, abs_tol=atol)


def _is_matrix(value) -> bool:
    """Whether ``value`` is a rectangular list of rows of floats (a covariance, a projection)."""
    return (isinstance(value, list) and len(value) > 1 and all(isinstance(r, list) and r for r in value)
            and len({len(r) for r in value}) == 1 and all(isinstance(x, float) for r in value for x in r))


ROUNDING = 1e-10
"""A matrix row whose entries are all below this share of the matrix' largest is a rounding's zero."""


def _matrix_differences(got, want, path: str) -> list[str]:
    """A matrix's entries to :data:`RTOL` of their scale: a covariance's ``sqrt(c_ii c_jj)`` (each parameter in its
    own unit), any other matrix's row's largest entry (a projection: one parameter's unit per row; a row of
    rounding's zeros (:data:`ROUNDING`) counts at that level)."""
    covariance = path.endswith("covariance") and len(want) == len(want[0])
    top = max((abs(x) for r in want for x in r if math.isfinite(x)), default=0.0)
    for i, (gr, wr) in enumerate(zip(got, want)):
        if not isinstance(gr, list) or len(gr) != len(wr) or not all(isinstance(x, float) for x in gr):
            return [f"{path}[{i}]: {gr!r:.80} != {wr!r:.80}"]
        row = max(max((abs(x) for x in wr if math.isfinite(x)), default=0.0), ROUNDING * top)
        for j, (a, b) in enumerate(zip(gr, wr)):
            scale = math.sqrt(abs(want[i][i] * want[j][j])) if covariance else row
            if not ((math.isnan(a) and math.isnan(b)) or a == b or abs(a - b) <= RTOL * scale):
                return [f"{path}[{i}][{j}]: {a!r} != {b!r}"]
    return []


def differences(got, want, path="") -> list[str]:
    """Where ``got`` differs from ``want``: key order, types, shapes, strings and flags exactly, numbers to a
    millionth (:data:`RTOL`, a matrix's entries of their scale)."""
    if isinstance(want, dict):
        if not isinstance(got, dict) or list(got) != list(want):
            return [f"{path}: keys {list(got) if isinstance(got, dict) else type(got).__name__} != {list(want)}"]
        if "piece" in want and isinstance(want.get("edm"), float):
            edm, rest = got["edm"], {k: v for k, v in want.items() if k != "edm"}
            near = isinstance(edm, float) and math.isclose(edm, want["edm"], rel_tol=REFIT_EDM_RTOL)
            return ([] if near else [f"{path}.edm: {edm!r} != {want['edm']!r}"]) + differences(
                {k: v for k, v in got.items() if k != "edm"}, rest, path)
        return [d for k in want for d in differences(got[k], want[k], f"{path}.{k}")]
    if isinstance(want, list):
        if not isinstance(got, list) or len(got) != len(want):
            return [f"{path}: {got!r:.80} != {want!r:.80}"]
        if _is_matrix(want):
            return _matrix_differences(got, want, path)
        return [d for i, (g, w) in enumerate(zip(got, want)) for d in differences(g, w, f"{path}[{i}]")]
    if isinstance(want, float) and isinstance(got, float):
        return [] if _close(got, want, path) else [f"{path}: {got!r} != {want!r}"]
    return [] if type(got) is type(want) and got == want else [f"{path}: {got!r:.80} != {want!r:.80}"]


@pytest.mark.parametrize("case", list(CASES))
def test_the_diagnosis_is_what_it_was(case, tmp_path):
    want = json.loads(gzip.decompress((REFS / f"{case}.json.gz").read_bytes()))
    got = json.loads(json.dumps(diagnosis_of(case, tmp_path)))             # as the command line writes it
    for key in STAMP:
        got.pop(key), want.pop(key)
    diff = differences(got, want)
    assert not diff, f"{len(diff)} difference(s), first: " + "; ".join(diff[:5])


def test_a_family_refits_edm_is_compared_to_its_own_tolerance():
    family = {"piece": "iron", "delta_chi2": 404.9, "converged": True, "edm": 0.0883}
    assert not differences(family | {"edm": 0.0883 * (1 + 1e-4)}, family)
    assert differences(family | {"edm": 0.0883 * (1 + 1e-2)}, family)
    assert differences(family | {"edm": 0.0883 * (1 + 1e-4), "delta_chi2": 404.9 * (1 + 1e-5)}, family)
    fit = {"chi2": 717.1, "edm": 0.0883}                 # any other EDM: a fit's, at RTOL
    assert differences(fit | {"edm": 0.0883 * (1 + 1e-4)}, fit)


def test_the_comparison_sees_a_changed_number_a_reordered_key_and_a_changed_word():
    ref = {"a": 1.0, "b": {"c": [1, "x", True]}}
    assert not differences(json.loads(json.dumps(ref)), ref)
    assert differences({"a": 1.0 + 1e-5, "b": {"c": [1, "x", True]}}, ref)
    assert not differences({"a": 1.0 + 1e-7, "b": {"c": [1, "x", True]}}, ref)
    # a parameter vector of mixed units: each number on its own (a gap of 5e-4 m beside a permeability of 2500)
    assert differences({"values": [1e-3, 2500.0]}, {"values": [5e-4, 2500.0]})
    assert differences({"g": 5e-4 * (1 + 1e-5)}, {"g": 5e-4}) and differences({"s": 2e-12}, {"s": 1e-12})
    assert not differences({"log_bayes": 2e-10}, {"log_bayes": -1e-10})       # a rounding's zero, in nats
    # a covariance: each entry to its parameters' standard deviations, a variance of 1e-20 m^2 beside one of 1e6
    cov = {"covariance": [[1e-20, 1e-30], [1e-30, 1e6]]}
    assert not differences({"covariance": [[1e-20, -1e-30], [-1e-30, 1e6]]}, cov)   # a rounding's sign
    assert differences({"covariance": [[1.01e-20, 1e-30], [1e-30, 1e6]]}, cov)
    assert differences({"covariance": [[1e-20, 1e-8], [1e-8, 1e6]]}, cov)           # a correlation of 0.1
    # any other matrix row by row (a projection: one unit per row), a row of rounding's zeros at that level
    proj = {"projection": [[1e-3, 2e-3], [1e-7, 3e-7], [1e-22, -2e-22]]}
    assert differences({"projection": [[1e-3, 2e-3], [1.1e-7, 3e-7], [1e-22, -2e-22]]}, proj)
    assert not differences({"projection": [[1e-3, 2e-3], [1e-7, 3e-7], [3e-22, 2e-22]]}, proj)
    # shapes count: the same numbers nested otherwise are different
    assert differences({"m": [[1.0, 2.0], [3.0, 4.0]]}, {"m": [[1.0], [2.0, 3.0, 4.0]]})
    assert differences({"m": [1.0, [2.0, 3.0]]}, {"m": [[1.0, 2.0], 3.0]})
    assert differences({"b": {"c": [1, "x", True]}, "a": 1.0}, ref)
    assert differences({"a": 1.0, "b": {"c": [1, "y", True]}}, ref)
    assert differences({"a": 1.0, "b": {"c": [1, "x", 1]}}, ref)


if __name__ == "__main__" and "--regenerate" in sys.argv:
    import tempfile

    named = [a for a in sys.argv[1:] if a in CASES]          # (default: every case)
    with tempfile.TemporaryDirectory() as tmp:
        for name in named or CASES:
            (REFS / f"{name}.json.gz").write_bytes(gzip.compress(
                (json.dumps(diagnosis_of(name, Path(tmp)), indent=2) + "\n").encode(), mtime=0))
            print("wrote", REFS / f"{name}.json.gz")
