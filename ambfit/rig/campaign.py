"""A campaign on the virtual rig: one machine logged for hours or weeks, experiment after experiment.

Between experiments the bearing warms up and cools down, so its effective gap and origin
drift (thermal growth of the rotor, the stator and the sensor mounts), and now and then
the rotor is set down and re-levitated, after which it settles about a slightly different
origin.  :func:`simulate_campaign` runs one perturbation experiment every ``interval_s``
seconds on :data:`ambfit.rig.PAPER_RIG` with

* :class:`TimeDrift`, an effect whose gap and origin change with the rig's clock, linearly or
  as an exponential approach (first-order thermal growth), within and between experiments;
* a re-levitation jump: the true origin shifts by ``jump`` [m] from experiment ``jump_at`` on
  (a protocol *assembly*, as :func:`ambfit.rig.protocol.with_assembly` models a reassembly).

It composes :func:`ambfit.rig.virtual.simulate` per experiment: each experiment starts at
its campaign time with the rig's hysteresis memory carried over, so ``time_s`` runs over
the whole campaign and the data are one contract table.  :func:`ambfit.studies.campaign.analyse`
identifies them window by window.

The physics of the drift is the :class:`ambfit.physics.effects.ThermalDrift` effect's
(gap ~0.1 µm/K from differential expansion, origin 0.3-2 µm/K from sensor-mount growth),
written against time instead of temperature, because a campaign log has a clock but not
always a thermometer.

Example
-------
>>> sim = simulate_campaign(experiments=3, iterations=1, seed=1)
>>> sim.data["experiment"].unique().tolist(), float(sim.data["time_s"].max()) > 2 * 2 * 3600
(['E1', 'E2', 'E3'], True)
"""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pandas as pd

from ambfit.physics.bearing import AXES
from ambfit.physics.stages import Effect, _ax, _set
from ambfit.rig.protocol import perturbation, with_assembly
from ambfit.rig.virtual import PAPER_RIG, Noise, RigSpec, RigState, simulate

HOUR = 3600.0
"""Seconds per hour."""


class TimeDrift(Effect):
    """Gap and origin drifting with the rig's clock ``t`` [s] (rig side: the fit does not model it).

    ``g0(t) = g0 + dg_dt f(t)``, ``x0(t) = x0 + dx0_dt f(t)`` with ``f(t) = t`` (``tau_s`` infinite: a
    steady drift) or ``f(t) = tau_s (1 - exp(-t / tau_s))`` (first-order thermal growth towards
    ``dg_dt tau_s``; the rates are those at ``t = 0``).  Rates are per axis ``(v, w)`` or one value for
    both, in m/s.  Schweitzer & Maslen (eds.), *Magnetic Bearings*, Springer 2009, ch. 4: the gap and
    origin of a radial bearing follow its thermal state.
    """

    dg_dt: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(0.05e-6 / HOUR))
    dx0_dt: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray((0.2e-6 / HOUR, -0.1e-6 / HOUR)))
    tau_s: float = math.inf
    name: ClassVar[str] = "campaign_drift"
    UNITS: ClassVar = {"dg_dt": "m/s", "dx0_dt": "m/s", "tau_s": "s"}

    def shape(self, time_s):
        """``f(t)`` [s]: how far the drift has run at ``time_s`` (the rates multiply it)."""
        t = jnp.asarray(time_s, dtype=float)
        if math.isinf(self.tau_s):
            return t
        return self.tau_s * -jnp.expm1(-t / self.tau_s)

    def geometry(self, ctx):
        f = self.shape(ctx.time)
        return _set(ctx, g0=ctx.g0 + _ax(self.dg_dt, ctx.axis) * f, x0=ctx.x0 + _ax(self.dx0_dt, ctx.axis) * f,
                    y0=ctx.y0 + _ax(self.dx0_dt, 1 - ctx.axis) * f)

    def describe(self) -> dict:
        """Rates [m/s] per axis and ``tau_s`` [s] (None for a steady drift), JSON-ready."""
        return {"dg_dt": np.broadcast_to(np.asarray(self.dg_dt, float), (2,)).tolist(),
                "dx0_dt": np.broadcast_to(np.asarray(self.dx0_dt, float), (2,)).tolist(),
                "tau_s": None if math.isinf(self.tau_s) else float(self.tau_s)}

    def at(self, time_s) -> tuple[np.ndarray, np.ndarray]:
        """The drift's change of ``(g0, x0)`` at ``time_s`` [s], each array[..., 2] ``(v, w)`` [m]."""
        f = np.asarray(self.shape(np.asarray(time_s, dtype=float)))[..., None]
        return (np.broadcast_to(np.asarray(self.dg_dt, float), (2,)) * f,
                np.broadcast_to(np.asarray(self.dx0_dt, float), (2,)) * f)


@dataclasses.dataclass(frozen=True)
class CampaignSimulation:
    """A simulated campaign (contract table over the whole campaign) and its truth.

    Attributes
    ----------
    data : pandas.DataFrame
        Every reading; ``experiment`` is ``E1``, ``E2``, ...; ``time_s`` counts from the campaign's start.
    truth : dict
        JSON-ready: rig, drift rates [µm/h], jump (experiment and size [µm]), noise, seed, and per experiment
        its start time [s] and the true parameters at its mid-time [µm].
    starts : array[n]
        Start time of each experiment [s].
    spec : RigSpec
    drift : TimeDrift
    jump_at : int or None
        The experiment (counted from 1) from which the origin is shifted, or None.
    jump : tuple[float, float]
        The re-levitation shift ``(dv0, dw0)`` [m].
    """

    data: pd.DataFrame
    truth: dict
    starts: np.ndarray
    spec: RigSpec
    drift: TimeDrift
    jump_at: int | None
    jump: tuple[float, float]

    def true_params(self, time_s) -> dict:
        """True ``g_v0, v0, g_w0, w0`` [m] at ``time_s`` [s] (array-like; the jump counts from its experiment's
        start)."""
        t = np.asarray(time_s, dtype=float)
        dg, dx = self.drift.at(t)
        shift = np.zeros(t.shape + (2,))
        if self.jump_at is not None:
            shift = np.where((t >= self.starts[self.jump_at - 1])[..., None], np.asarray(self.jump), 0.0)
        g = np.asarray(self.spec.g0) + dg
        x = np.asarray(self.spec.x0) + dx + shift
        return {"g_v0": g[..., 0], "v0": x[..., 0], "g_w0": g[..., 1], "w0": x[..., 1]}

    def true_rates(self, time_s: float = 0.0) -> dict:
        """Drift rates [m/s] of ``g_v0, v0, g_w0, w0`` at ``time_s`` (constant for a steady drift)."""
        slope = 1.0 if math.isinf(self.drift.tau_s) else math.exp(-time_s / self.drift.tau_s)
        dg = np.broadcast_to(np.asarray(self.drift.dg_dt, float), (2,)) * slope
        dx = np.broadcast_to(np.asarray(self.drift.dx0_dt, float), (2,)) * slope
        return {"g_v0": float(dg[0]), "v0": float(dx[0]), "g_w0": float(dg[1]), "w0": float(dx[1])}


def simulate_campaign(
    spec: RigSpec = PAPER_RIG, *, experiments: int = 12, interval_s: float = 2 * HOUR, iterations: int = 10,
    biases=(1.4, 1.6), offset: float = 20e-6, drift: TimeDrift | None = None,
    jump_at: int | str | None = "middle",
    jump: tuple[float, float] = (3e-6, -2e-6), noise: Noise = Noise(), effects=(), seed: int = 0,
    dwell_s: float = 5.0,
) -> CampaignSimulation:
    """Run one perturbation experiment every ``interval_s`` [s] under drift, with one re-levitation jump.

    Parameters
    ----------
    spec : RigSpec
        The rig; its ``g0``, ``x0`` are the truth at the campaign's start.
    experiments : int
        Number of experiments (``E1`` ... ``En``).
    interval_s : float
        Time between the starts of consecutive experiments [s].
    iterations, biases, offset :
        Each experiment: :func:`ambfit.rig.protocol.perturbation` with these biases [A] and ±``offset`` [m]
        pairs, ``iterations`` times, centred on the effective origin at the campaign's start (where an
        origin search left the rotor; drift and jump move the rotor a few µm from it).
    drift : TimeDrift, optional
        Default :class:`TimeDrift` (gap +0.05 µm/h, origin +0.2/-0.1 µm/h, steady).  ``TimeDrift(0.0, 0.0)``: none.
    jump_at : int, "middle" or None
        Experiment (from 1) from which the origin is shifted by ``jump`` [m]; ``"middle"`` (default): the one
        after the middle of the campaign (E7 of 12); None: no jump.
    noise : Noise
    effects : sequence of Effect
        Further physics the rig applies (the drift is added to them).
    seed : int
        Seeds the noise of every experiment (one :class:`numpy.random.SeedSequence`).
    dwell_s : float
        Time between readings within an experiment [s].
    """
    if experiments < 1:
        raise ValueError(f"a campaign needs at least one experiment, got {experiments}")
    if jump_at == "middle":
        jump_at = experiments // 2 + 1 if experiments > 1 else None
    if jump_at is not None and not 1 <= jump_at <= experiments:
        raise ValueError(f"jump_at must name one of the experiments 1..{experiments}, got {jump_at}")
    drift = TimeDrift() if drift is None else drift
    starts = np.arange(experiments, dtype=float) * float(interval_s)
    length = 2 * len(biases) * iterations * dwell_s
    if experiments > 1 and length >= interval_s:
        raise ValueError(f"an experiment lasts {length:g} s, longer than the interval of {interval_s:g} s")
    rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(experiments)]
    centre = spec.centre
    state = RigState()
    frames, per_experiment = [], []
    sim = CampaignSimulation(pd.DataFrame(), {}, starts, spec, drift, jump_at, tuple(jump))
    for j in range(experiments):
        p = perturbation(biases, (offset,), center=centre, iterations=iterations, experiment=f"E{j + 1}",
                         dwell_s=dwell_s)
        if jump_at is not None and j + 1 >= jump_at:
            p = with_assembly(p, 1, jump)
        run = simulate(spec, p, (*effects, drift), noise, seed=rngs[j], state=RigState(state.m, starts[j]))
        state = run.state
        frames.append(run.data)
        mid = starts[j] + 0.5 * length
        per_experiment.append({"experiment": f"E{j + 1}", "start_s": float(starts[j]), "mid_s": float(mid),
                               **{f"{k}_um": float(v) * 1e6 for k, v in sim.true_params(mid).items()}})
    rates = sim.true_rates()
    truth = {
        "rig": spec.name, "experiments": experiments, "interval_s": float(interval_s), "iterations": iterations,
        "biases_A": [float(b) for b in biases], "offset_um": offset * 1e6,
        "drift": {"shape": "steady" if math.isinf(drift.tau_s) else "exponential",
                  "tau_s": None if math.isinf(drift.tau_s) else drift.tau_s,
                  "rates_um_per_h_at_start": {k: v * 1e6 * HOUR for k, v in rates.items()}},
        "jump": None if jump_at is None else {"experiment": f"E{jump_at}",
                                              **{f"d{ax}0_um": s * 1e6 for ax, s in zip(AXES, jump)}},
        "noise": {"current_A": noise.current, "position_um": noise.position * 1e6},
        "effects": [{"name": e.name, **e.describe()} for e in (*effects, drift)],
        "seed": seed, "per_experiment": per_experiment,
    }
    return dataclasses.replace(sim, data=pd.concat(frames, ignore_index=True), truth=truth)
