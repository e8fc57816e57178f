"""The virtual AMB test rig: equilibria under a controller, sensor noise, unmodelled physics.

At each protocol step the controller holds the rotor's *measured* position at the
commanded set-point (integral action: zero static error) and splits its output
into control currents ``i_top = bias + i_c``, ``i_bottom = bias - i_c`` (each
clipped at zero, amplifiers cannot drive negative current).  The rig solves, per
axis, for the ``i_c`` at which the true magnetic force (ideal law plus the
effects it is given) balances the static load, by bisection on the monotone
force-current curve, then records what the sensors report plus Gaussian noise.
Readings are solved in order, so history-dependent effects (hysteresis) and
time-dependent ones (thermal drift) act as on a real rig.

Example
-------
>>> from ambfit.rig import protocol, virtual as rig
>>> sim = rig.simulate(rig.PAPER_RIG, protocol.paper_table2(iterations=1), seed=1)
>>> sorted(sim.data["axis"].unique().tolist())
['v', 'w']
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from ambfit.physics.bearing import AXES, PAPER_BEARING, Bearing
from ambfit.physics.effects import Effect
from ambfit.physics.model import BearingParams, Readings, evaluate
from ambfit.rig.protocol import Protocol

_BISECTION_STEPS = 110  # halves a 40 A bracket below one ulp of the current
_COUPLED_ROUNDS = 12
"""Rounds of the axes' fixed-point iteration when an effect couples them through their currents: a coupling
of a few per cent of the own-current sensitivity shrinks the error by that factor per round, and the force
residual check (``FORCE_TOLERANCE_N``) catches a coupling too strong to converge."""
FORCE_TOLERANCE_N = 1e-9
"""Largest force residual [N] the rig accepts at an equilibrium."""


class RigError(RuntimeError):
    """The rig cannot realise a protocol step (load beyond capacity, gap closed, ...)."""


@dataclasses.dataclass(frozen=True)
class RigSpec:
    """A bearing test rig: the bearing as drawn, the amplifier, and the true effective parameters.

    Attributes
    ----------
    bearing : Bearing
        The bearing's facts (pole angle, turns, pole face, nominal gap, ...).
    lamination : float
        True lamination (stacking) coefficient in Eq. 3 [-].
    amplifier_limit : float
        Amplifier limit [A]: a step that needs more coil current than this fails.
    g0, x0 : tuple[float, float]
        True effective gaps and origins ``(v, w)`` [m] of the ideal-law description.
    k : tuple[float, float] or None
        True force constants [N m^2/A^2]; None derives them from the winding.
    """

    bearing: Bearing = PAPER_BEARING
    lamination: float = PAPER_BEARING.lamination
    amplifier_limit: float = 5.0
    g0: tuple[float, float] = (775.0e-6, 763.0e-6)
    x0: tuple[float, float] = (33.3e-6, -11.3e-6)
    k: tuple[float, float] | None = None

    @property
    def name(self) -> str:
        return self.bearing.name

    @property
    def nominal_gap(self) -> float:
        """Nominal radial air gap [m] (the drawing's value)."""
        return self.bearing.nominal_gap

    @property
    def centre(self) -> tuple[float, float]:
        """Where the sensors read the bearing's centre [m]: ``-x0`` (a protocol run around it stays within the
        back-up clearance however far the sensors' zero is from it)."""
        return (-self.x0[0], -self.x0[1])

    @property
    def force_constant(self) -> float:
        """Eq. 3's ``k`` from the winding, pole area and true lamination [N m^2/A^2]."""
        return self.bearing.force_constant(self.lamination)

    @property
    def load_capacity(self) -> float:
        """Force at the coil current limit on one coil, rotor centred at the nominal gap [N]."""
        return self.force_constant * self.bearing.max_current**2 / self.nominal_gap**2

    def params(self, origin_shift=(0.0, 0.0)) -> BearingParams:
        """The true effective parameters (optionally after a reassembly shift [m])."""
        k = self.k if self.k is not None else (self.force_constant,) * 2
        return BearingParams.from_values(self.g0, np.asarray(self.x0) + np.asarray(origin_shift), k)

    @classmethod
    def for_bearing(cls, bearing: Bearing) -> RigSpec:
        """The default rig built around ``bearing`` as drawn (:data:`PAPER_RIG` for the paper's bearing).

        The true gaps keep the paper rig's excess over its drawing as a fraction of the nominal gap (775/762
        and 763/762 of ``bearing.nominal_gap``: an effective gap a little above the air gap, as the paper
        found), the true lamination is the bearing's nominal one and the amplifier keeps the paper rig's
        headroom over the coil current limit (5 A for its 3 A).  The origins stay the paper's (33.3, -11.3) µm:
        a sensor offset, not a property of the gap.  The static load (the bearing's ``rotor_mass``) is the
        protocol's: :func:`ambfit.rig.protocol.rotor_loads`.
        """
        scale = bearing.nominal_gap / PAPER_RIG.nominal_gap
        return dataclasses.replace(
            PAPER_RIG, bearing=bearing, lamination=bearing.lamination, g0=tuple(g * scale for g in PAPER_RIG.g0),
            amplifier_limit=PAPER_RIG.amplifier_limit * bearing.max_current / PAPER_RIG.bearing.max_current)

    @property
    def loads(self) -> dict:
        """The protocol loads of this rig's rotor: ``{"rotor": Load}``, the bearing's ``rotor_mass``."""
        from ambfit.rig.protocol import rotor_loads

        return rotor_loads(self.bearing.rotor_mass)

    def with_truth(self, g0=None, x0=None, k=None) -> RigSpec:
        """A copy with other true parameters (pairs ``(v, w)``, SI units)."""
        kw = {}
        if g0 is not None:
            kw["g0"] = tuple(float(a) for a in np.broadcast_to(g0, (2,)))
        if x0 is not None:
            kw["x0"] = tuple(float(a) for a in np.broadcast_to(x0, (2,)))
        if k is not None:
            kw["k"] = tuple(float(a) for a in np.broadcast_to(k, (2,)))
        return dataclasses.replace(self, **kw)


PAPER_RIG = RigSpec()
"""The seed paper's rig (:data:`ambfit.physics.bearing.PAPER_BEARING`); the true effective gaps
and origins are the paper's identified values (775/763 µm, 33.3/-11.3 µm)."""


@dataclasses.dataclass(frozen=True)
class Noise:
    """Sensor noise: independent Gaussian errors on each recorded reading.

    Attributes
    ----------
    current : float
        Standard deviation of each recorded coil current [A].  The default 0.6 mA
        reproduces the paper's Table 2 scatter (per-iteration Eq. 7 gap std of
        about 35 µm on the v axis; measured on this rig: 35 µm over 2000 iterations).
    position : float
        Standard deviation of each recorded position [m].
    """

    current: float = 0.6e-3
    position: float = 0.1e-6


NOISE_FREE = Noise(0.0, 0.0)


@dataclasses.dataclass(frozen=True)
class RigState:
    """What the rig remembers between runs: magnetising currents ``m[axis, coil]`` [A] and the clock [s]."""

    m: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((2, 2)))
    time: float = 0.0


@dataclasses.dataclass(frozen=True)
class Simulation:
    """A simulated data set (contract format) and the truth behind it."""

    data: pd.DataFrame
    truth: dict
    state: RigState
    force_residual: np.ndarray  # array[n_steps, 2] [N]
    physical_currents: np.ndarray  # array[n_steps, 2 axes, 2 coils] [A]


def _solve_steps(params_by_step, readings_template, loads, effects, bearing, amplifier_limit, m0):
    """Scan over steps; each step solves both axes' control currents by bisection.

    When an effect couples the axes through their currents (``needs_other_axis``), each axis is solved with
    the other's currents of the previous round, for ``_COUPLED_ROUNDS`` rounds (a fixed-point iteration that
    contracts as fast as the coupling is weak); without one there is a single round and no other-axis currents.
    """
    coupled = any(getattr(e, "needs_other_axis", False) for e in effects)

    def step(m_prev, inp):
        g0, x0, k, x, y, bias, t, temp, load = inp
        params = BearingParams(g0, x0, k)

        def force_at(ic, other):
            it = jnp.maximum(bias + ic, 0.0)
            ib = jnp.maximum(bias - ic, 0.0)
            r = Readings(axis=jnp.arange(2), i_top=it, i_bottom=ib, x=x, y=y, bias=bias,
                         time=jnp.full(2, t), temperature=temp, dir_top=jnp.zeros(2), dir_bottom=jnp.zeros(2),
                         i_top_other=None if other is None else jnp.maximum(bias + other, 0.0)[::-1],
                         i_bottom_other=None if other is None else jnp.maximum(bias - other, 0.0)[::-1])
            f, ctx = evaluate(params, r, effects, bearing=bearing, physical=True,
                              m_prev_top=m_prev[:, 0], m_prev_bottom=m_prev[:, 1])
            return f - load, ctx, it, ib

        def solve(other):
            def bisect(_, lohi):
                lo, hi = lohi
                mid = 0.5 * (lo + hi)
                r = force_at(mid, other)[0]
                return jnp.where(r > 0, lo, mid), jnp.where(r > 0, mid, hi)

            # Within the amplifier range each coil current lies in [0, amplifier_limit].
            span = jnp.maximum(amplifier_limit - bias, 0.0)
            lo, hi = jax.lax.fori_loop(0, _BISECTION_STEPS, bisect, (-span, span))
            rlo, rhi = force_at(lo, other)[0], force_at(hi, other)[0]
            return jnp.where(jnp.abs(rlo) < jnp.abs(rhi), lo, hi)

        if coupled:
            ic = jax.lax.fori_loop(0, _COUPLED_ROUNDS, lambda _, ic: solve(ic), jnp.zeros(2))
            res, ctx, it, ib = force_at(ic, ic)
        else:
            ic = solve(None)
            res, ctx, it, ib = force_at(ic, None)
        m_new = jnp.stack([ctx.m_top, ctx.m_bottom], axis=1)
        return m_new, (res, it, ib)

    return jax.lax.scan(step, m0, (*params_by_step, *readings_template, loads))


_solve_jit = eqx.filter_jit(_solve_steps)  # the bearing is hashable: a static argument


def _temperature(effects: Sequence[Effect], time_s: np.ndarray, ambient_C: float) -> np.ndarray:
    temp = np.full_like(time_s, ambient_C, dtype=float)
    for e in effects:
        temp = temp + (np.asarray(e.temperature(time_s, ambient_C)) - ambient_C)
    return temp


def _sense(effects, axis, i_top, i_bottom, x, y):
    for e in effects:
        i_top, i_bottom, x, y = e.sense(axis, i_top, i_bottom, x, y)
    return i_top, i_bottom, x, y


def _unsense(effects, axis, i_top, i_bottom, x, y):
    for e in reversed(tuple(effects)):
        i_top, i_bottom, x, y = e.unsense(axis, i_top, i_bottom, x, y)
    return i_top, i_bottom, x, y


def _records(protocol, bias, it_m, ib_m, v_m, w_m, sets, tt, temp, noise) -> pd.DataFrame:
    """The recorded readings as contract rows: one row per step and axis (SI inside, file units out)."""
    rows = []
    for s in range(len(protocol)):
        for a, name in enumerate(AXES):
            lo = protocol.loads[protocol.load_id[s]]
            rows.append({
                "axis": name, "bias_A": bias[s, a], "i_top_A": it_m[s, a], "i_bottom_A": ib_m[s, a],
                "v_um": v_m[s] * 1e6, "w_um": w_m[s] * 1e6,
                "load_N": (lo.force_v, lo.force_w)[a] if lo.known else np.nan,
                "load_id": protocol.load_id[s], "experiment": protocol.experiment[s],
                "iteration": int(protocol.iteration[s]),
                "v_set_um": sets[s, 0] * 1e6, "w_set_um": sets[s, 1] * 1e6,
                "time_s": tt[s], "temperature_C": temp[s],
                # Zero noise is written as an empty cell ('not known'): a zero std cannot weight a reading.
                "i_top_std_A": noise.current or np.nan, "i_bottom_std_A": noise.current or np.nan,
                "v_std_um": round(noise.position * 1e6, 12) or np.nan,
                "w_std_um": round(noise.position * 1e6, 12) or np.nan,
            })
    return pd.DataFrame(rows)


def _physical(protocol: Protocol, effects: Sequence[Effect]) -> tuple[np.ndarray, np.ndarray]:
    """Where the rotor physically is in sensor coordinates at each step, ``(x, y)`` array[n, 2] [m] (``x``: each
    axis' own position, ``y``: the other axis'): the controller holds the *measured* positions at the set-points,
    so physical = unsense(set)."""
    n = len(protocol)
    sets = np.stack([protocol.v_set, protocol.w_set], axis=1).astype(float)
    _, _, x, y = _unsense(effects, np.array([[0, 1]]), np.zeros((n, 2)), np.zeros((n, 2)), sets, sets[:, ::-1])
    return np.asarray(x), np.asarray(y)


def simulate(
    spec: RigSpec, protocol: Protocol, effects: Sequence[Effect] = (), noise: Noise = Noise(), *,
    seed: int | np.random.Generator = 0, state: RigState | None = None, ambient_C: float = 22.0,
    thermometer: bool = True,
) -> Simulation:
    """Run ``protocol`` on the rig and return the recorded data in the contract format.

    Parameters
    ----------
    spec : RigSpec
        Rig geometry and true effective parameters.
    protocol : Protocol
        Steps to run, in order.
    effects : sequence of Effect
        Unmodelled physics the rig applies as truth.
    noise : Noise
        Sensor noise (std of each recorded current [A] and position [m]).
    seed : int or numpy Generator
        Seed of the noise.
    state : RigState, optional
        Rig state to continue from (hysteresis memory and clock); default: a
        demagnetised rig at t = 0.
    ambient_C : float
        Ambient temperature [°C].
    thermometer : bool
        Record the bearing temperature (``temperature_C``); without, the effects see none, as a fit of the data
        will, and a :class:`~ambfit.physics.effects.ThermalDrift` acts through time (from the rig's clock zero).

    Raises
    ------
    RigError
        When a step's load cannot be balanced to within ``FORCE_TOLERANCE_N`` or a
        set-point closes a gap.
    """
    effects = tuple(effects)
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    state = state or RigState()
    n = len(protocol)
    time = state.time + protocol.time
    temp = _temperature(effects, time, ambient_C) if thermometer else np.full(n, np.nan)
    shifts = np.array([protocol.assemblies[a] for a in protocol.assembly], dtype=float).reshape(n, 2)
    base = spec.params()
    g0 = np.broadcast_to(np.asarray(base.g0), (n, 2))
    x0 = np.asarray(base.x0)[None, :] + shifts
    k = np.broadcast_to(np.asarray(base.k), (n, 2))

    axis2 = np.array([0, 1])
    sets = np.stack([protocol.v_set, protocol.w_set], axis=1).astype(float)
    x_phys, y_phys = _physical(protocol, effects)
    u = (x0 + x_phys) * spec.bearing.cos_alpha
    if np.any(np.abs(u) >= 0.95 * g0):
        bad = int(np.argmax(np.any(np.abs(u) >= 0.95 * g0, axis=1)))
        raise RigError(f"step {bad}: set-point ({sets[bad, 0] * 1e6:.1f}, {sets[bad, 1] * 1e6:.1f}) µm "
                       "closes a pole gap to under 5 % of the effective gap")
    bias = np.stack([protocol.bias_v, protocol.bias_w], axis=1).astype(float)
    load = np.array([[protocol.loads[l].force_v, protocol.loads[l].force_w] for l in protocol.load_id]).reshape(n, 2)
    tt = np.asarray(time, dtype=float)
    temps = np.repeat(np.asarray(temp, dtype=float)[:, None], 2, axis=1)

    # (NumPy inputs: the compiled solve converts them; an eager JAX conversion of each new shape compiles a program)
    m_end, (res, it, ib) = _solve_jit(
        (np.asarray(g0, dtype=float), np.asarray(x0, dtype=float), np.asarray(k, dtype=float)),
        (np.asarray(x_phys, dtype=float), np.asarray(y_phys, dtype=float), bias, tt, temps),
        np.asarray(load, dtype=float), effects, spec.bearing, spec.amplifier_limit, np.asarray(state.m, dtype=float),
    )
    res, it, ib = np.asarray(res), np.asarray(it), np.asarray(ib)
    worst = float(np.max(np.abs(res))) if n else 0.0
    nonfinite = ~np.isfinite(res).all(axis=1)
    if nonfinite.any():
        s = int(np.argmax(nonfinite))
        raise RigError(
            f"step {s} (experiment {protocol.experiment[s]}, bias {bias[s].tolist()} A): the force law gives no "
            f"finite force with the effects {_named(effects)}; an effect parameter is outside its physical range "
            "(e.g. a saturation flux density that is not positive)")
    if worst > FORCE_TOLERANCE_N:
        s = int(np.argmax(np.abs(res).max(axis=1)))
        raise RigError(
            f"step {s} (experiment {protocol.experiment[s]}, load {protocol.load_id[s]!r}, "
            f"bias {bias[s].tolist()} A): the bearing cannot balance the load to {FORCE_TOLERANCE_N:g} N "
            f"(residual {np.abs(res[s]).max():.3g} N) with coil currents within the amplifier limit of "
            f"{spec.amplifier_limit:g} A; the load is beyond the capacity at this set-point"
        )

    # What the sensors report: physical -> sensed, plus noise.
    it_m, ib_m, x_m, y_m = (np.asarray(a) for a in _sense(effects, axis2[None, :], it, ib, x_phys, y_phys))
    it_m = it_m + rng.normal(0.0, noise.current, it_m.shape) if noise.current > 0 else it_m
    ib_m = ib_m + rng.normal(0.0, noise.current, ib_m.shape) if noise.current > 0 else ib_m
    pos_noise = rng.normal(0.0, noise.position, (n, 2)) if noise.position > 0 else np.zeros((n, 2))
    v_m = x_m[:, 0] + pos_noise[:, 0]  # the same position sample is recorded with both axes' rows
    w_m = x_m[:, 1] + pos_noise[:, 1]

    data = _records(protocol, bias, it_m, ib_m, v_m, w_m, sets, tt, temp, noise).drop(
        columns=[] if thermometer else ["temperature_C"])
    truth = {
        "rig": spec.name,
        "params": {str(a): spec.params(protocol.assemblies[a]).as_dict_um() for a in sorted(protocol.assemblies)},
        "effects": [{"name": e.name, **e.describe()} for e in effects],
        "noise": {"current_A": noise.current, "position_um": noise.position * 1e6},
        "seed": seed if isinstance(seed, int) else None,
        "n_steps": n,
    }
    return Simulation(data=data, truth=truth, state=RigState(np.asarray(m_end), float(time[-1]) if n else state.time),
                      force_residual=res, physical_currents=np.stack([it, ib], axis=-1))


def _named(effects) -> str:
    """The effects with their parameters, as ``--effect`` takes them."""
    def one(e):
        params = ",".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in e.describe().items())
        return f"{e.name or type(e).__name__}:{params}" if params else (e.name or type(e).__name__)

    return "; ".join(map(one, effects)) or "(none)"


def write_truth(truth: dict, path) -> None:
    """Write the truth record of a simulation next to its CSV (JSON; :mod:`ambfit._output`: atomically, through
    links, into devices)."""
    from ambfit._output import write_json

    write_json(path, truth)
