"""The law zoo: random data sets for judging the diagnosis on laws it was not written for (issue 31, item 5).

A :class:`Case` is drawn whole by :func:`draw_case`: what kind of truth it holds (no effect, one contract family,
two at once, or an effect of no family), a law of each family drawn from that family's broad classes with a
random structure and magnitude (:mod:`ambfit.rig.zoo_magnetic`, :mod:`ambfit.rig.zoo_hysteresis`,
:mod:`ambfit.rig.zoo_measurement`), the rig's true gaps (within 2 µm of the nominal 762 µm) and origins (within
40 µm), the protocol (the library's :func:`~ambfit.rig.protocol.rich` or :func:`~ambfit.rig.protocol.serpentine`,
or :func:`random_protocol`) centred where the operator found the origin, the bearing's heating, and which
optional columns the rig writes.
:func:`draw` simulates it, drawing again when the rig cannot run it or a step leaves the bearing's limits
(:func:`ambfit.rig.limits.limit_violations`).  ``benchmarks/gap_zoo.py`` scores the diagnosis on such draws.

Example
-------
>>> import numpy as np
>>> case, data = draw(np.random.default_rng(3))
>>> case.kind in KINDS and len(data) == 2 * len(case.protocol)
True
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd

from ambfit.physics.bearing import PAPER_BEARING
from ambfit.physics.effects import EFFECTS, Effect
from ambfit.rig import protocol as protocols
from ambfit.rig.laws import as_recorded
from ambfit.rig.limits import limit_violations
from ambfit.rig.protocol import Load, Protocol
from ambfit.rig.virtual import PAPER_RIG, RigError, RigSpec, simulate
from ambfit.rig.zoo_hysteresis import HYSTERESIS
from ambfit.rig.zoo_magnetic import MAGNETIC
from ambfit.rig.zoo_measurement import MEASUREMENT, NO_FAMILY, Heating, TemperatureDrift
from ambfit.rig.zoo_shapes import ZooLaw

FAMILIES: tuple[str, ...] = tuple(EFFECTS)
"""The contract's families (section 3), in its order."""
LAWS: dict[str, tuple[type[ZooLaw], ...]] = {f: {**MAGNETIC, **HYSTERESIS, **MEASUREMENT}[f] for f in FAMILIES}
"""Each family's law classes."""
KINDS: dict[str, float] = {"none": 0.15, "single": 0.55, "pair": 0.20, "no_family": 0.10}
"""Kinds of truth and their chances: no effect, one family (each family equally likely), two families at once,
an effect of no family."""
PROTOCOLS: dict[str, float] = {"rich": 0.25, "serpentine": 0.25, "random": 0.5}
"""Protocols and their chances."""
TEMPERATURE_WRITTEN = 0.35
"""Chance that the rig writes ``temperature_C`` (a thermometer on the bearing)."""
TIME_DROPPED = 0.07
"""Chance that the rig writes no ``time_s`` either."""
ORIGIN_ERROR = 2e-6
"""Standard deviation [m] of the origin the operator centres the set-points on (an origin search's error)."""
REACH = 55e-6
"""Largest distance [m] of a set-point from the centre of the protocol: the paper bearing's 60 µm back-up
clearance less the origin's error."""
MASSES = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5)
"""Masses [kg] hung on the rotor in random protocols (each a known load)."""
NO_FAMILY_TRUTH = "no_family"


@dataclasses.dataclass(frozen=True)
class Case:
    """One drawn data set's truth and how it is recorded.

    Attributes
    ----------
    kind : str
        ``"none"``, ``"single"``, ``"pair"`` or ``"no_family"`` (:data:`KINDS`).
    truth : tuple of str
        The contract families of the laws in contract order; ``()`` for no effect, ``("no_family",)`` for an
        effect no family describes.
    laws : tuple of ZooLaw
        The laws that make the truth.
    effects : tuple of Effect
        What the rig applies: the laws and the bearing's heating, history-dependent laws last.
    protocol : Protocol
    protocol_kind : str
        ``"rich"``, ``"serpentine"`` or ``"random"``.
    spec : RigSpec
        The rig with its true gaps and origins.
    dropped : tuple of str
        Optional columns the rig does not write (``temperature_C``, ``time_s``).
    """

    kind: str
    truth: tuple[str, ...]
    laws: tuple[ZooLaw, ...]
    effects: tuple[Effect, ...]
    protocol: Protocol
    protocol_kind: str
    spec: RigSpec
    dropped: tuple[str, ...]

    @property
    def label(self) -> str:
        """The truth as one string: ``"none"``, ``"no_family"`` or the families joined with ``+``."""
        return "+".join(self.truth) or "none"

    def describe(self) -> dict:
        """A small JSON record: kind, truth, each law's class and parameters, protocol, rig truth, columns."""
        return {"kind": self.kind, "truth": list(self.truth), "protocol": self.protocol_kind,
                "steps": len(self.protocol), "dropped": list(self.dropped),
                "laws": [{"law": law.name, "family": law.family or NO_FAMILY_TRUTH, "params": law.describe()}
                         for law in self.laws],
                "g0_um": [g * 1e6 for g in self.spec.g0], "x0_um": [x * 1e6 for x in self.spec.x0]}


def _disc(rng, center, radius, n) -> list[tuple[float, float]]:
    """``n`` points drawn uniformly over the disc of ``radius`` [m] around ``center``."""
    r, phi = radius * np.sqrt(rng.random(n)), rng.uniform(0.0, 2.0 * np.pi, n)
    return [(center[0] + a * np.cos(p), center[1] + a * np.sin(p)) for a, p in zip(r, phi)]


def _shuffled(p: Protocol, rng) -> Protocol:
    """The same steps in a random order."""
    order = rng.permutation(len(p))
    fields = ("v_set", "w_set", "bias_v", "bias_w", "load_id", "experiment", "iteration", "assembly")
    return dataclasses.replace(p, **{f: np.asarray(getattr(p, f))[order] for f in fields})


def _biases(rng, lo, hi) -> list[float]:
    return [round(float(b), 3) for b in rng.uniform(0.9, 1.8, int(rng.integers(lo, hi + 1)))]


def random_protocol(rng: np.random.Generator, center=(0.0, 0.0), reach: float = REACH,
                    rotor_kg: float = PAPER_BEARING.rotor_mass) -> Protocol:
    """A protocol as an experimenter might improvise it: random blocks in a random order, 100-400 steps.

    Blocks are the paper's perturbation (2-3 random biases, 1-3 offsets, 1-3 iterations), grids of random
    set-points with random biases (half of them run in a shuffled order) and bias sweeps (rising or falling,
    up and down or not) at random set-points; every set-point within ``reach`` [m] of ``center`` (sensor
    coordinates), biases 0.9-1.8 A, each block under one of 1-4 known loads (``rotor_kg`` plus hung masses,
    :data:`MASSES`), one experiment or one per block, 2, 5 or 10 s between readings.
    """
    masses = np.sort(rng.choice(MASSES, size=int(rng.integers(1, 5)), replace=False))
    loads = {f"m{j}": Load.gravity(rotor_kg + float(m), known=True) for j, m in enumerate(masses)}
    dwell = float(rng.choice([2.0, 5.0, 10.0]))
    single = rng.random() < 0.5
    parts, steps, budget = [], 0, int(rng.integers(100, 401))
    while steps < budget:
        j = len(parts) + 1
        kw = {"experiment": "random" if single else f"R{j}", "load": str(rng.choice(list(loads))), "loads": loads,
              "dwell_s": dwell}
        kind = rng.choice(["perturbation", "grid", "bias_sweep"])
        if kind == "perturbation":
            offsets = rng.uniform(10e-6, reach / np.sqrt(2.0), int(rng.integers(1, 4)))
            p = protocols.perturbation(sorted(_biases(rng, 2, 3)), offsets, center=tuple(center),
                                       iterations=int(rng.integers(1, 4)), first_iteration=j, **kw)
        elif kind == "grid":
            p = protocols.grid(_disc(rng, center, reach, int(rng.integers(4, 13))), _biases(rng, 2, 5), iteration=j,
                               **kw)
            p = _shuffled(p, rng) if rng.random() < 0.5 else p
        else:
            sweep = sorted(_biases(rng, 3, 7), reverse=bool(rng.random() < 0.5))
            p = protocols.bias_sweep(sweep, _disc(rng, center, reach, int(rng.integers(1, 5))),
                                     up_down=bool(rng.random() < 0.7), iteration=j, **kw)
        parts.append(p)
        steps += len(p)
    return protocols.concat(*(parts[k] for k in rng.permutation(len(parts))), dwell_s=dwell)


def draw_protocol(rng: np.random.Generator, kind: str, center) -> Protocol:
    """A protocol of ``kind`` (:data:`PROTOCOLS`) centred on ``center`` [m] with a random span within :data:`REACH`."""
    center = tuple(float(c) for c in center)
    if kind == "rich":
        return protocols.rich(span=rng.uniform(25e-6, REACH / np.sqrt(2.0)), center=center)
    if kind == "serpentine":
        sv = rng.uniform(25e-6, 40e-6)
        sw = rng.uniform(15e-6, min(30e-6, np.sqrt(REACH**2 - sv**2)))
        return protocols.serpentine(span=(sv, sw), seed=int(rng.integers(2**31)), center=center)
    if kind == "random":
        return random_protocol(rng, center)
    raise ValueError(f"unknown protocol kind {kind!r}; valid: {', '.join(PROTOCOLS)}")


def _families(rng, kind) -> tuple[str, ...]:
    if kind == "none":
        return ()
    if kind == "no_family":
        return (NO_FAMILY_TRUTH,)
    picked = rng.choice(len(FAMILIES), size=1 if kind == "single" else 2, replace=False)
    return tuple(FAMILIES[k] for k in sorted(picked))


def draw_case(rng: np.random.Generator, *, kind: str | None = None, truth: tuple[str, ...] | None = None) -> Case:
    """A random :class:`Case` (see the module docstring); ``kind`` and ``truth`` hold those fixed when given."""
    kind = kind or str(rng.choice(list(KINDS), p=list(KINDS.values())))
    if kind not in KINDS:
        raise ValueError(f"unknown case kind {kind!r}; valid: {', '.join(KINDS)}")
    truth = _families(rng, kind) if truth is None else tuple(truth)
    while True:
        spec = PAPER_RIG.with_truth(g0=rng.uniform(760e-6, 764e-6, 2), x0=rng.uniform(-40e-6, 40e-6, 2))
        protocol_kind = str(rng.choice(list(PROTOCOLS), p=list(PROTOCOLS.values())))
        proto = draw_protocol(rng, protocol_kind, -np.asarray(spec.x0) + rng.normal(0.0, ORIGIN_ERROR, 2))
        duration = float(proto.time[-1])
        classes = [NO_FAMILY if f == NO_FAMILY_TRUTH else LAWS[f] for f in truth]
        laws = tuple(c[int(rng.integers(len(c)))].draw(rng, duration) for c in classes)
        heating = () if any(isinstance(law, TemperatureDrift) for law in laws) else (Heating.draw(rng, duration),)
        effects = (*(e for e in laws if not e.stateful), *heating, *(e for e in laws if e.stateful))
        dropped = ()
        if rng.random() >= TEMPERATURE_WRITTEN:
            dropped += ("temperature_C",)
        if rng.random() < TIME_DROPPED:
            dropped += ("time_s",)
        if not limit_violations(spec, proto, effects):
            return Case(kind, truth, laws, effects, proto, protocol_kind, spec, dropped)


def simulate_case(case: Case, seed: int | np.random.Generator = 0) -> pd.DataFrame:
    """The case's data as the rig records it (the contract's columns less ``case.dropped``).

    Raises
    ------
    RigError
        When the rig cannot balance a step, or a coil current leaves the bearing's limit.
    """
    sim = simulate(case.spec, case.protocol, case.effects, seed=seed)
    bad = limit_violations(case.spec, case.protocol, case.effects, sim.physical_currents)
    if bad:
        raise RigError(f"{len(bad)} step(s) beyond the bearing's limits, the first: {bad[0]}")
    return as_recorded(sim.data, case.dropped)


def draw(rng: np.random.Generator, *, kind: str | None = None, tries: int = 50) -> tuple[Case, pd.DataFrame]:
    """A random case and its data: :func:`draw_case`, then :func:`simulate_case`, drawing the case's laws,
    rig and protocol again (its kind and truth kept) until the rig can run it, at most ``tries`` times."""
    case = draw_case(rng, kind=kind)
    for _ in range(tries):
        try:
            return case, simulate_case(case, rng)
        except RigError:
            case = draw_case(rng, kind=case.kind, truth=case.truth)
    raise RigError(f"no runnable case of truth {case.label!r} in {tries} draws")
