"""The bearing's limits on a protocol: the rotor within the back-up clearance, the coils within their current limit.

A real rig's operator does not run a step that would put the rotor beyond the back-up bearing's
clearance or drive a coil beyond the current it was designed for.  :func:`limit_violations` names
every such step of a protocol on a rig (the limits are the bearing description's
``backup_clearance`` and ``max_current``), before the run from the set-points and biases, after
it from the simulated coil currents.

Example
-------
>>> from ambfit.rig import PAPER_RIG, protocol
>>> limit_violations(PAPER_RIG, protocol.paper_table2(iterations=1))
[]
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from ambfit.physics.bearing import AXES
from ambfit.physics.effects import Effect
from ambfit.rig.protocol import Protocol
from ambfit.rig.virtual import RigSpec, _physical


def rotor_positions(spec: RigSpec, protocol: Protocol, effects: Sequence[Effect] = ()) -> np.ndarray:
    """The rotor's position relative to the bearing's geometric centre at each step, array[n, 2] ``(v, w)`` [m].

    The set-point is in sensor coordinates; the rotor sits at the set-point (sensor effects undone) plus the true
    origin ``x0`` (and the step's reassembly shift).  Its length is what the back-up bearing's clearance bounds.
    """
    x, _ = _physical(protocol, effects)
    shifts = np.array([protocol.assemblies[a] for a in protocol.assembly], dtype=float).reshape(len(protocol), 2)
    return x + np.asarray(spec.x0)[None, :] + shifts


@dataclasses.dataclass(frozen=True)
class LimitViolation:
    """One protocol step beyond the bearing's limits: the rotor beyond the back-up clearance, or a coil current
    beyond the coil current limit.

    ``step`` counts from 1 (its readings are the CSV's rows ``2 step - 1`` and ``2 step``); ``set_point`` [m] is in
    sensor coordinates; ``value`` and ``limit`` are the rotor's distance from the bearing centre and the clearance
    [m] (``kind == "clearance"``), or the commanded bias (``"bias"``) or the simulated coil current (``"current"``)
    and the coil current limit [A].
    """

    kind: str
    step: int
    experiment: str
    iteration: int
    set_point: tuple[float, float]
    value: float
    limit: float
    where: str = ""

    def __str__(self) -> str:
        head = (f"step {self.step} (experiment {self.experiment}, iteration {self.iteration}, set-point "
                f"({self.set_point[0] * 1e6:.1f}, {self.set_point[1] * 1e6:.1f}) µm)")
        if self.kind == "clearance":
            return (f"{head}: the rotor would be {self.value * 1e6:.1f} µm from the bearing centre ({self.where}), "
                    f"beyond the back-up clearance of {self.limit * 1e6:.1f} µm")
        return f"{head}: {self.where} {self.value:.3g} A, beyond the coil current limit of {self.limit:g} A"


def limit_violations(spec: RigSpec, protocol: Protocol, effects: Sequence[Effect] = (),
                     currents: np.ndarray | None = None) -> list[LimitViolation]:
    """Every step of ``protocol`` that would put the rotor beyond the back-up clearance, command a bias beyond
    the coil current limit, or (given the simulated ``currents``, array[n, 2 axes, 2 coils] [A], e.g.
    :attr:`Simulation.physical_currents`) drive a coil beyond it.  The limits are ``spec.bearing``'s
    ``backup_clearance`` and ``max_current``.  Empty when the protocol is safe on this bearing.

    A real rig's operator does not run these steps: the rotor would touch the back-up bearing, or the coils
    would overheat or saturate beyond what the bearing was designed for.
    """
    b = spec.bearing
    pos = rotor_positions(spec, protocol, effects)
    r = np.hypot(pos[:, 0], pos[:, 1])
    origin = np.asarray(spec.x0)
    bias = np.stack([protocol.bias_v, protocol.bias_w], axis=1).astype(float)
    out = []

    def violation(kind, s, value, limit, where):
        return LimitViolation(kind=kind, step=s + 1, experiment=str(protocol.experiment[s]),
                              iteration=int(protocol.iteration[s]),
                              set_point=(float(protocol.v_set[s]), float(protocol.w_set[s])), value=float(value),
                              limit=float(limit), where=where)

    for s in np.flatnonzero(r > b.backup_clearance * (1 + 1e-9)):
        shift = origin + np.array(protocol.assemblies[protocol.assembly[s]])
        out.append(violation("clearance", s, r[s], b.backup_clearance,
                             f"the rig's true origin ({shift[0] * 1e6:.1f}, {shift[1] * 1e6:.1f}) µm plus the "
                             "set-point"))
    for s, a in zip(*np.nonzero(bias > b.max_current)):
        out.append(violation("bias", s, bias[s, a], b.max_current, f"bias of axis {AXES[a]}"))
    if currents is not None:
        c = np.asarray(currents)
        for s in np.flatnonzero(np.any(c > b.max_current * (1 + 1e-9), axis=(1, 2))):
            a, coil = np.unravel_index(int(np.argmax(c[s])), (2, 2))
            out.append(violation("current", s, c[s, a, coil], b.max_current,
                                 f"coil current ({'top' if coil == 0 else 'bottom'} coil of axis {AXES[a]})"))
    return sorted(out, key=lambda v: (v.step, v.kind))
