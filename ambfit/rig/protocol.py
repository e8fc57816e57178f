"""Perturbation protocols as data: the sequence of set-points, biases and loads a rig runs.

A :class:`Protocol` is a table of *steps*.  At each step the controller holds the
rotor at ``(v_set, w_set)`` [m, sensor coordinates] with bias currents
``(bias_v, bias_w)`` [A] under the static load ``load_id``; the rig records one
reading per axis.  Builders return protocols for the paper's experiments and for
richer designs, and :func:`concat` chains them; :func:`from_dict` reads the same
description from TOML for ``ambfit simulate``.

Loads are :class:`Load` records: the force ``(F_v, F_w)`` [N] the bearing must
supply, and whether the experimenter knows it (hung masses on a known rotor
weight) or not.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence

import numpy as np

from ambfit.physics.bearing import PAPER_BEARING

G_STANDARD = 9.80665
"""Standard gravity [m/s^2]."""


@dataclasses.dataclass(frozen=True)
class Load:
    """A static load: the force the bearing supplies to the rotor along +v and +w [N].

    ``known`` says whether the experimenter knows it (written to ``load_N``).
    """

    force_v: float
    force_w: float
    known: bool = False

    @classmethod
    def gravity(cls, mass_kg: float, axis_angles_deg: tuple[float, float] = (45.0, -45.0), known: bool = True) -> Load:
        """Support of a vertical weight ``mass_kg * g`` by axes at the given angles from vertical."""
        w = mass_kg * G_STANDARD
        a = np.deg2rad(axis_angles_deg)
        return cls(float(w * np.cos(a[0])), float(w * np.cos(a[1])), known)


@dataclasses.dataclass(frozen=True)
class Protocol:
    """A sequence of steps (one reading per axis each), all arrays of equal length.

    Attributes
    ----------
    v_set, w_set : array[n]
        Commanded set-points [m], sensor coordinates.
    bias_v, bias_w : array[n]
        Commanded bias currents [A].
    load_id : array[n] of str
        Key into ``loads``.
    experiment : array[n] of str
    iteration : array[n] of int
    assembly : array[n] of int
        Key into ``assemblies``: a rotor reassembly shifts the true origin.
    loads : dict[str, Load]
    assemblies : dict[int, tuple[float, float]]
        Origin shift ``(dv0, dw0)`` [m] of each assembly relative to the rig's truth.
    dwell_s : float
        Time between readings [s].
    """

    v_set: np.ndarray
    w_set: np.ndarray
    bias_v: np.ndarray
    bias_w: np.ndarray
    load_id: np.ndarray
    experiment: np.ndarray
    iteration: np.ndarray
    assembly: np.ndarray
    loads: dict
    assemblies: dict = dataclasses.field(default_factory=lambda: {0: (0.0, 0.0)})
    dwell_s: float = 5.0

    def __post_init__(self):
        n = len(self.v_set)
        for f in ("w_set", "bias_v", "bias_w", "load_id", "experiment", "iteration", "assembly"):
            if len(getattr(self, f)) != n:
                raise ValueError(f"protocol field {f!r} has {len(getattr(self, f))} entries, expected {n}")
        missing = set(self.load_id.tolist()) - set(self.loads)
        if missing:
            raise ValueError(f"protocol refers to undefined load(s) {sorted(missing)}; defined: {sorted(self.loads)}")
        missing = set(self.assembly.tolist()) - set(self.assemblies)
        if missing:
            raise ValueError(f"protocol refers to undefined assembly {sorted(missing)}")
        if np.any(np.asarray(self.bias_v) < 0) or np.any(np.asarray(self.bias_w) < 0):
            raise ValueError("bias currents must be non-negative")

    def __len__(self) -> int:
        return len(self.v_set)

    @property
    def time(self) -> np.ndarray:
        """Time of each reading [s]."""
        return self.dwell_s * np.arange(1, len(self) + 1, dtype=float)

    def steps(self):
        """The steps as a table to run them by, in order: experiment, iteration, the load (its name, the force it
        puts on each axis [N] and whether it is known), set-points [µm, sensor coordinates], biases [A] and the
        time of the reading [s] (a DataFrame)."""
        import pandas as pd

        loads = [self.loads[k] for k in self.load_id]
        return pd.DataFrame({
            "step": np.arange(1, len(self) + 1), "experiment": self.experiment, "iteration": self.iteration,
            "load_id": self.load_id, "load_v_N": [ld.force_v for ld in loads], "load_w_N": [ld.force_w for ld in loads],
            "load_known": [ld.known for ld in loads], "v_set_um": np.asarray(self.v_set) * 1e6,
            "w_set_um": np.asarray(self.w_set) * 1e6, "bias_v_A": self.bias_v, "bias_w_A": self.bias_w,
            "time_s": self.time})


def _steps(points, biases, *, load, experiment, iteration, assembly=0):
    rows = [(v, w, bv, bw) for (v, w) in points for (bv, bw) in biases]
    a = np.asarray(rows, dtype=float).reshape(-1, 4)
    n = len(a)
    return dict(
        v_set=a[:, 0], w_set=a[:, 1], bias_v=a[:, 2], bias_w=a[:, 3],
        load_id=np.full(n, load, dtype=object), experiment=np.full(n, experiment, dtype=object),
        iteration=np.full(n, iteration, dtype=int), assembly=np.full(n, assembly, dtype=int),
    )


def _pairs(biases) -> list[tuple[float, float]]:
    out = []
    for b in biases:
        b = np.atleast_1d(np.asarray(b, dtype=float))
        out.append((float(b[0]), float(b[-1])))
    return out


def _build(parts: Sequence[dict], loads, assemblies=None, dwell_s=5.0) -> Protocol:
    cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    return Protocol(**cat, loads=dict(loads), assemblies=dict(assemblies or {0: (0.0, 0.0)}), dwell_s=dwell_s)


def rotor_loads(mass_kg: float = PAPER_BEARING.rotor_mass) -> dict[str, Load]:
    """The static load ``"rotor"``: a known rotor weight share ``mass_kg`` [kg] (a bearing description's
    ``rotor_mass``), supported by axes at ±45° from vertical."""
    return {"rotor": Load.gravity(mass_kg, known=True)}


DEFAULT_LOADS = rotor_loads()
"""The default static load: the paper rig's 1 kg rotor share, known, supported by axes at ±45° from vertical
(about 6.9 N each)."""


def perturbation(
    biases: Iterable = (1.4, 1.6), offsets: Iterable[float] = (20e-6,), *, center=(0.0, 0.0),
    iterations: int = 1, experiment: str = "E1", load: str = "rotor", loads: dict | None = None,
    assembly: int = 0, first_iteration: int = 1, dwell_s: float = 5.0,
) -> Protocol:
    """The paper's current-position perturbation (Fig. 3, Eq. 5-7).

    For each iteration, for each offset ``d`` [m], the rotor is held at
    ``center + d`` and ``center - d`` on both axes at once, and at each position
    every bias in ``biases`` [A] is applied (two biases give Eq. 6's ratios).  A bias
    may be a pair ``(b_v, b_w)``.

    Examples
    --------
    >>> p = perturbation((1.4, 1.6), (20e-6,), iterations=10)
    >>> len(p)   # 10 iterations x 2 positions x 2 biases
    40
    """
    cv, cw = center
    parts = []
    for it in range(first_iteration, first_iteration + iterations):
        pts = [(cv + s * d, cw + s * d) for d in offsets for s in (1.0, -1.0)]
        parts.append(_steps(pts, _pairs(biases), load=load, experiment=experiment, iteration=it, assembly=assembly))
    return _build(parts, loads or DEFAULT_LOADS, dwell_s=dwell_s)


def grid(
    points: Iterable[tuple[float, float]], biases: Iterable, *, experiment: str = "grid", load: str = "rotor",
    loads: dict | None = None, iteration: int = 1, assembly: int = 0, dwell_s: float = 5.0,
) -> Protocol:
    """Every bias at every ``(v_set, w_set)`` point [m]: non-symmetric designs, position-only designs."""
    return _build([_steps(list(points), _pairs(biases), load=load, experiment=experiment,
                          iteration=iteration, assembly=assembly)], loads or DEFAULT_LOADS, dwell_s=dwell_s)


def bias_sweep(
    biases: Sequence[float], points: Iterable[tuple[float, float]] = ((0.0, 0.0),), *, up_down: bool = True,
    experiment: str = "sweep", load: str = "rotor", loads: dict | None = None, iteration: int = 1,
    dwell_s: float = 5.0,
) -> Protocol:
    """At each point, sweep the bias through ``biases`` and (``up_down``) back again.

    The down leg approaches every operating point from the other side: the
    protocol for exposing hysteresis.
    """
    seq = list(biases) + (list(biases)[-2::-1] if up_down else [])
    parts = [_steps([p], _pairs(seq), load=load, experiment=experiment, iteration=iteration) for p in points]
    return _build(parts, loads or DEFAULT_LOADS, dwell_s=dwell_s)


def concat(*protocols: Protocol, dwell_s: float | None = None) -> Protocol:
    """Run protocols one after another (loads and assemblies are merged)."""
    loads, assemblies = {}, {}
    for p in protocols:
        for k, v in p.loads.items():
            if k in loads and loads[k] != v:
                raise ValueError(f"load {k!r} is defined differently in two protocols")
            loads[k] = v
        assemblies.update(p.assemblies)
    fields = ("v_set", "w_set", "bias_v", "bias_w", "load_id", "experiment", "iteration", "assembly")
    cat = {f: np.concatenate([getattr(p, f) for p in protocols]) for f in fields}
    return Protocol(**cat, loads=loads, assemblies=assemblies,
                    dwell_s=protocols[0].dwell_s if dwell_s is None else dwell_s)


def with_assembly(protocol: Protocol, assembly: int, origin_shift: tuple[float, float]) -> Protocol:
    """The same protocol run after a rotor reassembly that shifts the true origin by ``origin_shift`` [m]."""
    return dataclasses.replace(
        protocol, assembly=np.full(len(protocol), assembly, dtype=int),
        assemblies={**protocol.assemblies, assembly: tuple(float(s) for s in origin_shift)},
    )


def paper_table2(iterations: int = 10, center=(0.0, 0.0), loads: dict | None = None) -> Protocol:
    """Table 2: bias 1.4/1.6 A, ±20 µm on both axes, ``iterations`` repetitions (under ``loads["rotor"]``,
    default :data:`DEFAULT_LOADS`)."""
    return perturbation((1.4, 1.6), (20e-6,), center=center, iterations=iterations, experiment="table2", loads=loads)


def paper_table1(iterations: int = 10, center=(0.0, 0.0)) -> Protocol:
    """Table 1: bias pairs 1.4/1.5, 1.4/1.6 and 1.5/1.6 A (experiments "1"-"3"), ±20 µm, ``iterations`` each."""
    return concat(*(perturbation(b, (20e-6,), center=center, iterations=iterations, experiment=str(j + 1))
                    for j, b in enumerate(((1.4, 1.5), (1.4, 1.6), (1.5, 1.6)))))


PAPER_TABLE3_STARTS = ((0.0, 0.0), (30e-6, 30e-6), (-10e-6, -30e-6), (2.78e-6, -36.88e-6))
"""Table 3's initial rotor positions ``(v, w)`` [m]: each experiment is an origin search from one of them
(:func:`ambfit.studies.origin.search` with ``start=``)."""


def paper_table4(iterations: int = 10, center=(0.0, 0.0), origin_shift=(-80.7e-6, 24.4e-6)) -> Protocol:
    """Table 4: after a rotor reassembly (true origin moved by ``origin_shift`` [m]), bias pairs 1.0/1.4 and
    1.2/1.4 A with ±30, ±40 and ±50 µm pairs (experiments "1.0/1.4 ±30" ...), ``iterations`` each.

    The default shift moves the paper's origin (33.3, -11.3) µm to its Table 4 value (-47.4, 13.1) µm.
    """
    parts = [perturbation(b, (d,), center=center, iterations=iterations,
                          experiment=f"{b[0]:.1f}/{b[1]:.1f} ±{d * 1e6:.0f}")
             for b in ((1.0, 1.4), (1.2, 1.4)) for d in (30e-6, 40e-6, 50e-6)]
    return with_assembly(concat(*parts), 1, origin_shift)


def rich(
    biases: Sequence[float] = (1.0, 1.2, 1.4, 1.6), span: float = 40e-6, n_positions: int = 5,
    masses_kg: Sequence[float] = (0.0, 0.5, 1.0, 1.5), rotor_kg: float = 1.0, experiment: str = "rich",
    dwell_s: float = 5.0, center=(0.0, 0.0),
) -> Protocol:
    """A rich design: biases swept up and down at v and w set-points over ``center ± span`` [m]
    (v and w moved independently, so non-symmetric pairs are included) under several
    known loads (rotor plus hung masses).

    ``center`` [m, sensor coordinates]: where the set-points are centred.  On a real bearing that is the
    effective origin ``(-v0, -w0)`` the paper's origin search finds: centred on the sensor origin instead, the
    default ±40 µm reach 73 µm from the centre of the paper's rig, beyond its 60 µm back-up clearance
    (:func:`ambfit.rig.limits.limit_violations`).
    """
    lin = np.linspace(-span, span, n_positions)
    rng = np.random.default_rng(12345)  # fixed, so the design is a constant of the code
    w_pts = rng.permutation(lin)
    points = [(center[0] + v, center[1] + w) for v, w in zip(lin, w_pts)]
    parts, loads = [], {}
    for j, m in enumerate(masses_kg):
        lid = f"m{j}"
        loads[lid] = Load.gravity(rotor_kg + m, known=True)
        p = bias_sweep(biases, points, experiment=experiment, load=lid, loads={lid: loads[lid]}, iteration=j + 1)
        parts.append(p)
    return concat(*parts, dwell_s=dwell_s)


def serpentine(
    biases: Sequence[float] = (1.0, 1.1, 1.2, 1.3, 1.4, 1.5, 1.6), span=(40e-6, 30e-6), n_positions=(5, 3),
    masses_kg: Sequence[float] = (0.0, 0.5, 1.0, 1.5), rotor_kg: float = 1.0, *, seed: int = 0,
    experiment: str = "serpentine", dwell_s: float = 5.0, center=(0.0, 0.0),
) -> Protocol:
    """A design as a user might run it: set-points on a grid walked as a serpentine, biases in shuffled order.

    Under each known load (rotor plus ``masses_kg``) the rotor visits a ``n_positions = (n_v, n_w)`` grid over
    ``center ± span`` [m] row by row, each row of v set-points run in the opposite direction to the one before
    (a boustrophedon: neighbouring readings are neighbouring positions), and at each set-point applies every
    bias of ``biases`` [A] in an order shuffled afresh (from ``seed``), so the approach to each operating point
    differs from reading to reading instead of the up-and-down sweep of :func:`rich`.

    Examples
    --------
    >>> len(serpentine())   # 4 loads x 15 set-points x 7 biases: 840 rows of data
    420
    """
    rng = np.random.default_rng(seed)
    vs = center[0] + np.linspace(-span[0], span[0], n_positions[0])
    ws = center[1] + np.linspace(-span[1], span[1], n_positions[1])
    points = [(v, w) for j, w in enumerate(ws) for v in (vs if j % 2 == 0 else vs[::-1])]
    parts, loads = [], {}
    for j, m in enumerate(masses_kg):
        lid = f"m{j}"
        loads[lid] = Load.gravity(rotor_kg + m, known=True)
        for p in points:
            order = [(b, b) for b in rng.permutation(np.asarray(biases, dtype=float))]
            parts.append(_steps([p], order, load=lid, experiment=experiment, iteration=j + 1))
    return _build(parts, loads, dwell_s=dwell_s)


def from_dict(spec: dict, *, rotor_kg: float = PAPER_BEARING.rotor_mass) -> Protocol:
    """A protocol from a plain description (as read from TOML by ``ambfit simulate``).

    Units in the keys: ``*_um`` micrometres, ``*_A`` amperes, ``*_N`` newtons.

    ``[loads.NAME]`` tables hold ``mass_kg`` (a known vertical weight) or
    ``force_v_N``/``force_w_N`` with ``known = true|false``; ``[[block]]`` entries
    have ``kind`` = ``perturbation`` | ``grid`` | ``bias_sweep`` | ``paper_table2`` |
    ``rich`` and the keyword arguments of that builder (positions in µm; ``center_um`` for
    ``perturbation``, ``paper_table2`` and ``rich``).  ``rotor_kg``: the rotor weight share [kg]
    of the load ``"rotor"`` (:func:`rotor_loads`) and of the ``rich`` blocks (``ambfit simulate`` passes its
    bearing's ``rotor_mass``).
    """
    base = rotor_loads(rotor_kg)
    loads = dict(base)
    for name, d in spec.get("loads", {}).items():
        if "mass_kg" in d:
            loads[name] = Load.gravity(float(d["mass_kg"]), known=bool(d.get("known", True)))
        else:
            loads[name] = Load(float(d["force_v_N"]), float(d["force_w_N"]), bool(d.get("known", False)))
    blocks = spec.get("block", [])
    if not blocks:
        raise ValueError("protocol description has no [[block]] entries")
    parts = []
    um = 1e-6
    for i, b in enumerate(blocks):
        b = dict(b)
        kind = b.pop("kind", None)
        reassembly = b.pop("origin_shift_um", None)
        common = {k: b.pop(k) for k in ("experiment", "load", "iteration", "iterations") if k in b}
        if kind == "perturbation":
            p = perturbation(b.pop("biases_A"), [o * um for o in b.pop("offsets_um", [20])],
                             center=tuple(c * um for c in b.pop("center_um", (0, 0))), loads=loads, **common)
        elif kind == "grid":
            p = grid([(v * um, w * um) for v, w in b.pop("points_um")], b.pop("biases_A"), loads=loads, **common)
        elif kind == "bias_sweep":
            p = bias_sweep(b.pop("biases_A"), [(v * um, w * um) for v, w in b.pop("points_um", [(0, 0)])],
                           up_down=b.pop("up_down", True), loads=loads, **common)
        elif kind == "paper_table2":
            p = paper_table2(common.get("iterations", 10), center=tuple(c * um for c in b.pop("center_um", (0, 0))),
                             loads=loads)
        elif kind == "rich":
            p = rich(span=b.pop("span_um", 40) * um, biases=b.pop("biases_A", (1.0, 1.2, 1.4, 1.6)),
                     masses_kg=b.pop("masses_kg", (0.0, 0.5, 1.0, 1.5)), rotor_kg=rotor_kg,
                     center=tuple(c * um for c in b.pop("center_um", (0, 0))))
        else:
            raise ValueError(f"block {i}: unknown kind {kind!r}; valid: perturbation, grid, bias_sweep, "
                             "paper_table2, rich")
        if b:
            raise ValueError(f"block {i} ({kind}): unknown key(s) {sorted(b)}")
        if reassembly is not None:
            p = with_assembly(p, i + 1, tuple(s * um for s in reassembly))
        parts.append(p)
    return concat(*parts, dwell_s=float(spec.get("dwell_s", 5.0)))
