"""The bearing's limits on a protocol: the rotor within the back-up clearance, the coils within their current limit.

A real rig's operator does not run a step that would put the rotor beyond the back-up bearing's
clearance or drive a coil beyond the current it was designed for.  :func:`step_limits` is the one
rule, used by the virtual rig (``ambfit simulate`` refuses such steps) and by the experiment design
(:func:`ambfit.estimation.design.recommend` never proposes them): the clearance is measured from the
bearing's geometric centre, where the rotor sits when the sensors read minus the origin ``(v0, w0)``.
:func:`limit_violations` names every such step of a protocol on a rig (the limits are the bearing
description's ``backup_clearance`` and ``max_current``), before the run from the set-points and
biases, after it from the simulated coil currents.

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

from ambfit.physics.bearing import AXES, Bearing
from ambfit.physics.effects import Effect
from ambfit.rig.protocol import Protocol
from ambfit.rig.virtual import RigSpec, _physical

_ROUND_OFF = 1e-9
"""Relative slack on both limits, so that a step exactly at a limit (a set-point on the clearance circle) is
within it despite round-off."""


@dataclasses.dataclass(frozen=True)
class StepLimits:
    """Each step's rotor distance from the bearing centre and its currents against the bearing's limits.

    Attributes
    ----------
    distance : array[n]
        The rotor's distance from the bearing's geometric centre [m].
    clearance : float
        The distance allowed [m]: the back-up clearance less the caller's margin.
    bias : array[n, 2]
        Commanded bias of each axis [A].
    current : array[n, 2, 2] or None
        Coil currents (axis, top/bottom) [A], simulated or predicted; None when not known.
    max_current : float
        The coil current limit [A].
    """

    distance: np.ndarray
    clearance: float
    bias: np.ndarray
    current: np.ndarray | None
    max_current: float

    @property
    def within_clearance(self) -> np.ndarray:
        """array[n] of bool: the rotor stays off the back-up bearing."""
        return self.distance <= self.clearance * (1 + _ROUND_OFF)

    @property
    def bias_within(self) -> np.ndarray:
        """array[n, 2] of bool: each axis' bias is within the coil current limit."""
        return self.bias <= self.max_current * (1 + _ROUND_OFF)

    @property
    def current_within(self) -> np.ndarray:
        """array[n] of bool: every coil current of the step is within the limit (True where not known)."""
        if self.current is None:
            return np.ones(len(self.distance), dtype=bool)
        return np.all(self.current <= self.max_current * (1 + _ROUND_OFF), axis=(1, 2))

    @property
    def ok(self) -> np.ndarray:
        """array[n] of bool: the step is within every limit."""
        return self.within_clearance & self.bias_within.all(axis=1) & self.current_within


def step_limits(set_points, biases, origin, bearing: Bearing, currents=None, *, margin: float = 0.0) -> StepLimits:
    """Whether each step keeps the rotor within the back-up clearance and every coil within its current limit.

    The clearance is measured from the rotor's geometric centre position, the bearing's centre: the point of
    equal gaps, which the sensors read as ``-origin``.  A rotor held at the sensor reading ``set_point`` is
    ``|set_point + origin|`` from it.  The rig passes its true origin (and where the rotor physically is); the
    design passes the estimated effective origin ``(v0, w0)`` and a ``margin`` for its uncertainty, so that
    what the design proposes the rig accepts.

    Parameters
    ----------
    set_points : array[n, 2]
        Where the rotor is held, ``(v, w)`` in sensor coordinates [m].
    biases : array[n, 2] or array[n]
        Bias current of each axis [A] (one column: the same on both axes).
    origin : array[2] or array[n, 2]
        The origin ``(v0, w0)`` [m]: the bearing centre is at sensor reading ``-origin``.
    bearing : Bearing
        Its ``backup_clearance`` [m] and ``max_current`` [A] are the limits.
    currents : array[n, 2, 2], optional
        Coil currents (axis, top/bottom) [A], simulated or predicted.
    margin : float
        Distance [m] kept from the clearance (default 0: the clearance itself).

    Examples
    --------
    >>> from ambfit import PAPER_BEARING
    >>> lim = step_limits([[-33.3e-6 + 20e-6, 11.3e-6 + 20e-6]], [1.6], (33.3e-6, -11.3e-6), PAPER_BEARING)
    >>> round(float(lim.distance[0]) * 1e6, 2), bool(lim.ok[0])
    (28.28, True)
    """
    pos = np.asarray(set_points, dtype=float).reshape(-1, 2) + np.asarray(origin, dtype=float)
    bias = np.asarray(biases, dtype=float)
    bias = np.repeat(bias[:, None], 2, axis=1) if bias.ndim == 1 else bias.reshape(-1, 2)
    return StepLimits(distance=np.hypot(pos[:, 0], pos[:, 1]), clearance=bearing.backup_clearance - margin,
                      bias=bias, current=None if currents is None else np.asarray(currents, dtype=float),
                      max_current=bearing.max_current)


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
    x, _ = _physical(protocol, effects)
    origin = np.asarray(spec.x0)
    shifts = np.array([protocol.assemblies[a] for a in protocol.assembly], dtype=float).reshape(len(protocol), 2)
    bias = np.stack([protocol.bias_v, protocol.bias_w], axis=1).astype(float)
    lim = step_limits(x, bias, origin[None, :] + shifts, b, currents)
    r = lim.distance
    out = []

    def violation(kind, s, value, limit, where):
        return LimitViolation(kind=kind, step=s + 1, experiment=str(protocol.experiment[s]),
                              iteration=int(protocol.iteration[s]),
                              set_point=(float(protocol.v_set[s]), float(protocol.w_set[s])), value=float(value),
                              limit=float(limit), where=where)

    for s in np.flatnonzero(~lim.within_clearance):
        shift = origin + np.array(protocol.assemblies[protocol.assembly[s]])
        out.append(violation("clearance", s, r[s], b.backup_clearance,
                             f"the rig's true origin ({shift[0] * 1e6:.1f}, {shift[1] * 1e6:.1f}) µm plus the "
                             "set-point"))
    for s, a in zip(*np.nonzero(~lim.bias_within)):
        out.append(violation("bias", s, bias[s, a], b.max_current, f"bias of axis {AXES[a]}"))
    if currents is not None:
        c = lim.current
        for s in np.flatnonzero(~lim.current_within):
            a, coil = np.unravel_index(int(np.argmax(c[s])), (2, 2))
            out.append(violation("current", s, c[s, a, coil], b.max_current,
                                 f"coil current ({'top' if coil == 0 else 'bottom'} coil of axis {AXES[a]})"))
    return sorted(out, key=lambda v: (v.step, v.kind))
