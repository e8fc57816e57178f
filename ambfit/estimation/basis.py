"""The discrepancy's basis: smooth functions of what shapes a horseshoe's force, in groups by the physics they carry.

For each horseshoe (top, bottom) with

- ``b = (i / I_max) / (1 -+ xi)``: the nominal flux density relative to that at the coil limit and nominal gap,
- ``xi = x cos(alpha) / g_nom``: the rotor displacement relative to the drawn gap,

a column is a force ``F_ref * (weight_top * h(b_top, xi) - weight_bottom * h(b_bottom, -xi))``, separately per axis,
with ``F_ref = k_geom (I_max / g_nom)^2`` one horseshoe's force at the coil limit.  Each family of unmodelled
physics changes the force through variables of its own, its *signature* (:data:`FAMILY_GROUPS`):

=================  ====================================================================================
group              columns
=================  ====================================================================================
shape              ``b^p xi^q`` (``1 <= p <= 6``, ``q <= 3``): the law's shape in flux density and gap
coupling           the same times the other axis' mean squared current; powers of the other axis' position
                   times this axis' flux, current and their products
control            the other axis' signed control current times this axis' current stiffness
hysteresis         ``b^p xi^q`` times the direction from which each coil current was approached
memory             each coil's state in plays of several widths (the path over several readings)
fading             each coil's departure from fading memories of its current, of several lengths and widths (a flux
                   that relaxes towards the current over the next readings)
drift              each coil's ``b^2``, ``b^2 xi`` times smooth functions of time: powers and settling curves
                   (and of temperature when read: powers and the temperature lagged through first-order lags)
drift_steps        the same times smooth steps across the run: a drift of any course, a random walk over the run
current_sensor     each coil's ``b / (1 -+ xi)`` times powers of its measured current
position_sensor    the force's slope in position times powers of the reading
position_spline    the force's slope in position times cubic B-splines of the reading over its range: a sensor
                   characteristic of any smooth shape (ripples of a few micrometres, a linearisation table)
=================  ====================================================================================

The columns of a group are what a smooth law of its variables, linearised about the ideal force, can add: a
current-channel error ``di(i)`` changes a horseshoe's force by ``2 F di / i``, a position-sensor error ``dx(x)`` by
``dF/dx dx``, a drift of gap or origin by ``dF/dg dg(t)``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ambfit._recent import Recent
from ambfit.physics.bearing import AXES, Bearing

P_MAX = 6
Q_MAX = 3
SHAPE_P_MIN = 1
"""The shape group's lowest power of flux density: a flux family changes the force only where there is flux, so no
column of the gap alone (``b^0 xi^q``: a spring of the rotor's position, which no law of flux density and gap
writes, would otherwise be named a flux family)."""
GROUPS = ("shape", "coupling", "hysteresis")
"""The basis' default groups, the ceiling of a diagnosis: the horseshoe law's shape in flux density and gap
(saturation, iron, fringing, leakage); what depends on the other axis (its currents and position: coupling through
the stator); what depends on the direction from which each coil current was approached (hysteresis).  Each group
has its own prior scale."""
SIGNATURE_GROUPS = ("control", "memory", "fading", "drift", "drift_steps", "current_sensor", "position_sensor",
                    "position_spline")
"""Further groups, each the signature of one family (see the module docstring)."""
ALL_GROUPS = GROUPS + SIGNATURE_GROUPS

FAMILY_GROUPS = {
    "saturation": ("shape",), "iron_reluctance": ("shape",), "fringing": ("shape",), "leakage": ("shape",),
    "cross_coupling": ("coupling", "control"), "hysteresis": ("hysteresis", "memory", "fading"),
    "thermal_drift": ("drift", "drift_steps"), "current_offset": ("current_sensor",),
    "current_gain": ("current_sensor",), "position_gain": ("position_sensor", "position_spline"),
}
"""Each contract family's signature: the groups that carry what a law of its variables, other than the library's,
could add (the flux families: flux density and gap per coil; hysteresis: the direction and path of each coil
current; drift: time and temperature; the sensors: their readings)."""

SLOW_GROUPS = ("drift", "drift_steps")
"""The groups whose terms are the force's own flux terms scaled by smooth functions of time and temperature: a
correction of them is alike for readings close in time, and cannot follow each reading's noise."""


def slow(groups) -> bool:
    """Whether a signature of ``groups`` holds :data:`SLOW_GROUPS` alone."""
    return bool(groups) and set(groups) <= set(SLOW_GROUPS)

X_SCALE = 0.05
"""Scale of the position polynomials of the coupling and position sensor groups, as a fraction of the nominal
gap (38 µm on the paper's bearing, about the largest displacement a protocol reaches): ``u = x / (X_SCALE g)``
and ``eta = y sin(alpha) / (X_SCALE g)`` keep every power of order one, so that one prior scale per group
serves all of them."""

SETTLE = (0.1, 0.3)
"""Time constants of the drift group's settling curves ``1 - exp(-t / tau)`` and temperature lags, as fractions of
the run's duration: a mount that settles, or a gap that follows the coils' temperature through the iron's thermal
lag, within the run (slower ones are the powers of time and of temperature)."""

TIME_STEPS = 12
"""The drift_steps group's smooth steps in time: one centred at each of ``k / TIME_STEPS`` of the run (``k`` = 1 ...
``TIME_STEPS - 1``), each rising over about one spacing, ``(tanh(2 (TIME_STEPS tau - k)) - tanh(-2 k)) / 2``: zero
at the clock's start, as the drift group's terms.  Under the group's Gaussian prior a sum of them is a random walk
over the run: a drift of any smooth course (a mount that creeps, then settles; a sudden shift), which the drift
group's powers and settling curves of time do not reach.  Over readings a fold's fit has not seen, the walk's
prediction passes from the level before them to the level after.  A group of its own, with its own prior scale:
the marginal likelihood leaves it out of a drift the powers follow."""

PLAY_WIDTHS = (0.005, 0.01, 0.02, 0.035, 0.05, 0.07, 0.1, 0.15)
"""Half-widths of the memory group's plays, as fractions of ``I_max`` (15-450 mA on the paper's rig: from the
library's narrow play to the perturbation's span, about geometric; the narrowest limit is the hysteresis group's
direction).  A play's state is not linear in its width: a law between two widths is expressed by their mix."""

FADING_MEMORIES = (0.5, 1.0, 2.0, 4.0, 8.0)
"""Lengths of the fading group's memories, in readings (``q = a q_prev + (1 - a) i``, ``a = exp(-1 /
memory)``, :func:`ambfit.rows.fading_states`): from a lag behind the last step alone to one over a run of several
steps, about geometric; a length between two is expressed by their mix."""

FADING_WIDTHS = (0.01, 0.025, 0.06, 0.15)
"""Half-widths of the fading group's states, as fractions of ``I_max`` (30-450 mA on the paper's rig): a state
``clip((i - q) / width, -1, 1)`` is a direction for a narrow width and linear in ``i - q`` for a wide one.  Each
state enters per coil as ``b`` and ``b xi`` (a lag of the magnetising current changes a horseshoe's force by its
current stiffness, ``b / (1 -+ xi)``).  A group of its own, with its own prior scale: in the memory group the plays'
scale would be the fading states' too."""

SPLINE_INTERVALS = 24
"""Most knot intervals of the position_spline group's cubic B-splines over the position readings' span: a ripple of
15 µm spans four of them over the paper's +-38 µm."""

POSITION_CLUSTER = 0.5e-6
"""Position readings closer than this [m] are one set-point of the protocol (its noise apart).  The position splines
have at most a third as many knot intervals as the readings have set-points: a function of the reading finer than
the set-points' spacing would follow each set-point's readings, their noise (a reading above its set-point reads a
force beyond it)."""

_MATRICES = Recent(8)
"""The last few basis matrices, by basis and readings (see :meth:`Basis.matrix`)."""


@dataclasses.dataclass(frozen=True)
class Basis:
    """The discrepancy's basis functions, fixed by the bearing description and, for drift and its steps, the span of
    the data's clock and thermometer (``t_ref`` [s], ``temp_ref``, ``temp_span`` [°C]), for the position splines the
    span of the position readings (``u_lo``, ``u_hi``, in units of :data:`X_SCALE` of the gap) and how many
    set-points they have (``u_intervals``, :data:`POSITION_CLUSTER`); not by the fit."""

    i_ref: float
    g_ref: float
    cos_alpha: float
    sin_alpha: float
    f_ref: float
    groups: tuple = GROUPS
    t_ref: float = 1.0
    temp_ref: float = 0.0
    temp_span: float = 1.0
    u_lo: float = -1.0
    u_hi: float = 1.0
    u_intervals: int = SPLINE_INTERVALS

    @classmethod
    def of(cls, bearing: Bearing, groups=GROUPS, readings=None) -> Basis:
        """The basis of ``bearing``; ``readings`` (those it will be fitted on) set the drift groups' time and
        temperature scales and the position splines' span."""
        unknown = set(groups) - set(ALL_GROUPS)
        if unknown:
            raise ValueError(f"unknown discrepancy group(s) {sorted(unknown)}; the groups are {ALL_GROUPS}")
        i_ref, g_ref = float(bearing.max_current), float(bearing.nominal_gap)
        scales = {}
        if readings is not None and set(SLOW_GROUPS) & set(groups):
            t = np.asarray(readings.time, dtype=float)
            temp = np.asarray(readings.temperature, dtype=float)
            temp = temp[np.isfinite(temp)]
            scales["t_ref"] = float(np.max(t, initial=0.0)) or 1.0
            if temp.size:
                scales |= {"temp_ref": float(temp.min()), "temp_span": float(np.ptp(temp)) or 1.0}
        if readings is not None and "position_spline" in groups:
            x, axis = np.asarray(readings.x, dtype=float), np.asarray(readings.axis)
            known = np.isfinite(x)
            if known.any() and np.ptp(x[known]) > 0:
                # each axis' set-points: its readings more than POSITION_CLUSTER apart; the splines serve both axes
                points = min(1 + int(np.sum(np.diff(np.sort(x[known & (axis == a)])) > POSITION_CLUSTER))
                             for a in np.unique(axis[known]))
                scales |= {"u_lo": float(x[known].min() / (X_SCALE * g_ref)),
                           "u_hi": float(x[known].max() / (X_SCALE * g_ref)),
                           "u_intervals": int(np.clip(points // 3, 1, SPLINE_INTERVALS))}
        return cls(i_ref=i_ref, g_ref=g_ref, cos_alpha=float(bearing.cos_alpha), sin_alpha=float(bearing.sin_alpha),
                   f_ref=float(bearing.force_constant() * (i_ref / g_ref) ** 2), groups=tuple(groups), **scales)

    def _columns(self, f) -> list[tuple[str, str, np.ndarray]]:
        """``(group, term, values)`` of one axis' basis functions from the features ``f`` (:meth:`_features`)."""
        bt, bb, xi = f["bt"], f["bb"], f["xi"]
        mono = [(p, q) for p in range(P_MAX + 1) for q in range(Q_MAX + 1) if (p, q) != (0, 0)]

        def horseshoes(p, q, top=1.0, bottom=1.0):
            # the top horseshoe's b^p xi^q less the bottom one's (its displacement is -xi), each weighted
            return top * bt**p * xi**q - bottom * bb**p * (-xi) ** q

        cols = []
        if "shape" in self.groups:
            cols += [("shape", f"b^{p} xi^{q}", horseshoes(p, q)) for p, q in mono if p >= SHAPE_P_MIN]
        if "coupling" in self.groups:
            cols += [("coupling", f"other-axis i^2 b^{p} xi^{q}", f["o"] * horseshoes(p, q))
                     for p, q in mono if p in (0, 2)]
            # powers of the other axis' displacement, scaled by this axis' flux or current (a shared back iron
            # carries its bias flux); no power 0: a term in this axis' readings alone is not the other axis'
            eta = f["eta"]
            for r in (1, 2, 3):
                cols += [("coupling", f"eta^{r}{name}", eta**r * v) for name, v in (
                    ("", np.ones_like(xi)), (" (b_t^2 + b_b^2)", bt**2 + bb**2), (" (b_t^2 - b_b^2)", bt**2 - bb**2),
                    (" (i_t + i_b)", f["it"] + f["ib"]), (" i_t i_b", f["it"] * f["ib"]))]
        if "control" in self.groups:
            # the other axis' control current, signed: a current-stiffness cross term (force per its current)
            c, k_i = f["c"], bt / (1.0 - xi) + bb / (1.0 + xi)
            cols += [("control", f"other-axis i_c {name}", c * v) for name, v in (
                ("", np.ones_like(xi)), ("k_i", k_i), ("k_i xi", k_i * xi), ("(b_t - b_b)", bt - bb),
                ("(b_t^2 + b_b^2)", bt**2 + bb**2), ("k_i i_c", k_i * c))]
        if "hysteresis" in self.groups:
            cols += [("hysteresis", f"direction b^{p} xi^{q}", horseshoes(p, q, f["dt"], f["db"]))
                     for p in range(5) for q in range(2)]
        if "memory" in self.groups:
            for j, w in enumerate(PLAY_WIDTHS):
                st, sb = f["play_top"][:, j], f["play_bottom"][:, j]
                cols += [("memory", f"play {w:g} I_max {coil} b{extra}", v)
                         for coil, s, b, x in (("top", st, bt, xi), ("bottom", sb, bb, -xi))
                         for extra, v in (("", s * b), ("^2", s * b**2), (" xi", s * b * x))]
        if "fading" in self.groups:
            for j, (m, w) in enumerate((m, w) for m in FADING_MEMORIES for w in FADING_WIDTHS):
                st, sb = f["fade_top"][:, j], f["fade_bottom"][:, j]
                cols += [("fading", f"fading {m:g} readings {w:g} I_max {coil} b{extra}", v)
                         for coil, s, b, x in (("top", st, bt, xi), ("bottom", sb, bb, -xi))
                         for extra, v in (("", s * b), (" xi", s * b * x))]
        def gap_and_origin(group, clocks):
            # each coil's b^2 and b^2 xi (a drift of gap and origin) times each function of time or temperature
            return [(group, f"{name} {coil} b^2{extra}", c * v) for name, c in clocks
                    for coil, v0 in (("top", bt**2), ("bottom", bb**2))
                    for extra, v in (("", v0), (" xi", v0 * xi))]

        if "drift" in self.groups:
            cols += gap_and_origin("drift", [(f"t^{r}", f["tau"] ** r) for r in (1, 2, 3)]
                                   + [(f"1 - exp(-t / {s:g} t_run)", -np.expm1(-f["tau"] / s)) for s in SETTLE]
                                   + [(f"T^{r}", f["theta"] ** r) for r in (1, 2)]
                                   + [(f"T lagged {s:g} t_run", f[f"theta_lag{j}"]) for j, s in enumerate(SETTLE)])
        if "drift_steps" in self.groups:
            # each step less its value at the clock's start: zero there, as the drift group's terms (and everywhere
            # for readings without a clock, where a step would be a term of the readings, not of time)
            cols += gap_and_origin("drift_steps", [
                (f"step at {k / TIME_STEPS:.3g} t_run",
                 0.5 * (np.tanh(2.0 * (TIME_STEPS * f["tau"] - k)) - np.tanh(-2.0 * k))) for k in range(1, TIME_STEPS)])
        if "current_sensor" in self.groups:
            cols += [("current_sensor", f"{coil} b i^{r}", v * i**r)
                     for coil, v, i in (("top", bt / (1.0 - xi), f["it"]), ("bottom", bb / (1.0 + xi), f["ib"]))
                     for r in range(4)]
        slope = bt**2 / (1.0 - xi) + bb**2 / (1.0 + xi)          # the force's slope in position, both horseshoes
        if "position_sensor" in self.groups:
            cols += [("position_sensor", f"dF/dx u^{r}", slope * f["u"] ** r) for r in range(1, 5)]
        if "position_spline" in self.groups:
            cols += [("position_spline", f"dF/dx B{k}(u)", slope * f["u_spline"][:, k])
                     for k in range(f["u_spline"].shape[1])]
        return cols

    def _features(self, readings, frame=None) -> dict:
        it, ib = np.asarray(readings.i_top) / self.i_ref, np.asarray(readings.i_bottom) / self.i_ref
        xi = np.asarray(readings.x) * self.cos_alpha / self.g_ref
        ot, ob = getattr(readings, "i_top_other", None), getattr(readings, "i_bottom_other", None)
        o = np.zeros_like(xi) if ot is None else np.nan_to_num(
            0.5 * ((np.asarray(ot) / self.i_ref) ** 2 + (np.asarray(ob) / self.i_ref) ** 2))
        c = np.zeros_like(xi) if ot is None else np.nan_to_num(0.5 * (np.asarray(ot) - np.asarray(ob)) / self.i_ref)
        f = {"it": np.abs(it), "ib": np.abs(ib), "bt": np.abs(it) / (1.0 - xi), "bb": np.abs(ib) / (1.0 + xi),
             "xi": xi, "o": o, "c": c,
             "u": np.asarray(readings.x) / (X_SCALE * self.g_ref),
             "eta": np.asarray(readings.y) * self.sin_alpha / (X_SCALE * self.g_ref),
             "dt": np.asarray(readings.dir_top, dtype=float), "db": np.asarray(readings.dir_bottom, dtype=float)}
        if set(SLOW_GROUPS) & set(self.groups):
            temp = (np.asarray(readings.temperature, dtype=float) - self.temp_ref) / self.temp_span
            tau = np.asarray(readings.time, dtype=float) / self.t_ref
            f |= {"tau": tau, "theta": np.nan_to_num(temp)} | {f"theta_lag{j}": _lagged(tau, temp, s)
                                                               for j, s in enumerate(SETTLE)}
        if "position_spline" in self.groups:
            f["u_spline"] = _splines(f["u"], self.u_lo, self.u_hi, self.u_intervals)
        if "memory" in self.groups:
            from ambfit.rows import play_states

            if frame is None:
                raise ValueError("the discrepancy's 'memory' group needs the table of the readings (their order)")
            widths = np.asarray(PLAY_WIDTHS) * self.i_ref
            f |= {"play_top": play_states(frame, "i_top_A", widths),
                  "play_bottom": play_states(frame, "i_bottom_A", widths)}
        if "fading" in self.groups:
            from ambfit.rows import fading_states

            if frame is None:
                raise ValueError("the discrepancy's 'fading' group needs the table of the readings (their order)")
            widths = np.asarray(FADING_WIDTHS) * self.i_ref
            f |= {f"fade_{coil}": fading_states(frame, f"i_{coil}_A", FADING_MEMORIES, widths)
                  for coil in ("top", "bottom")}
        return f

    def terms(self) -> list[tuple[str, str]]:
        """``(group, "axis: term")`` of every basis function, in column order."""
        z = np.zeros(1)
        one = self._columns({k: z for k in ("it", "ib", "bt", "bb", "xi", "u", "o", "c", "eta", "dt", "db", "tau",
                                            "theta")}
                            | {f"theta_lag{j}": z for j in range(len(SETTLE))}
                            | {"play_top": np.zeros((1, len(PLAY_WIDTHS))), "play_bottom": np.zeros((1, len(PLAY_WIDTHS))),
                               "fade_top": np.zeros((1, len(FADING_MEMORIES) * len(FADING_WIDTHS))),
                               "fade_bottom": np.zeros((1, len(FADING_MEMORIES) * len(FADING_WIDTHS))),
                               "u_spline": np.zeros((1, self.u_intervals + 3))})
        return [(g, f"{ax}: {t}") for ax in AXES for g, t, _ in one]

    def to_json(self) -> dict:
        return dataclasses.asdict(self) | {"groups": list(self.groups)} | _constants()

    @classmethod
    def from_json(cls, record: dict) -> Basis:
        """The basis of a saved discrepancy; one saved with other constants (:data:`P_MAX`, :data:`Q_MAX`,
        :data:`SHAPE_P_MIN`, :data:`X_SCALE`, :data:`SETTLE`, :data:`TIME_STEPS`, :data:`PLAY_WIDTHS`,
        :data:`FADING_MEMORIES`, :data:`FADING_WIDTHS`) would compute other columns under the same coefficients, and
        is refused."""
        if "p_max" in record:
            record = {"shape_p_min": 0} | record       # saved before the shape group left out b^0
        for key, value in _constants().items():
            if key in record and not np.allclose(np.asarray(record[key], dtype=float), value, rtol=1e-12, atol=0.0):
                raise ValueError(f"the discrepancy's basis was saved with {key} = {record[key]}, this ambfit's is "
                                 f"{value}: its coefficients belong to other columns; fit the discrepancy again")
        kw = {f.name: record[f.name] for f in dataclasses.fields(cls) if f.name in record}
        return cls(**kw | {"groups": tuple(kw["groups"]), "u_intervals": int(kw.get("u_intervals", SPLINE_INTERVALS))})

    def matrix(self, readings, frame=None) -> np.ndarray:
        """Force [N] of each basis function (unit coefficient) at each reading: array[n, m], axis by axis.
        ``frame``: the table the readings were made from (the memory and fading groups follow each coil's path
        through it).

        The last few readings' matrices are kept, by the readings' identity (a built problem's readings are
        shared by every fit of its table: a diagnosis fits the discrepancy on one table many times)."""
        key = (self, id(readings), id(frame))
        hit = _MATRICES.get(key)
        if hit is not None:
            return hit[2]
        ax = np.asarray(readings.axis)
        cols = np.stack([c for _, _, c in self._columns(self._features(readings, frame))], axis=1)
        out = self.f_ref * np.concatenate([np.where((ax == a)[:, None], cols, 0.0) for a in range(len(AXES))],
                                          axis=1)
        out.flags.writeable = False
        _MATRICES.put(key, (readings, frame, out))   # holding the inputs: their identity stays theirs while keyed
        return out

    def group_index(self) -> np.ndarray:
        """Index into ``groups`` of every column."""
        return np.array([self.groups.index(g) for g, _ in self.terms()])


def _constants() -> dict:
    """The module's constants that shape the columns, as a saved basis records them."""
    return {"p_max": P_MAX, "q_max": Q_MAX, "shape_p_min": SHAPE_P_MIN, "x_scale": X_SCALE, "settle": list(SETTLE),
            "time_steps": TIME_STEPS, "play_widths": list(PLAY_WIDTHS), "fading_memories": list(FADING_MEMORIES),
            "fading_widths": list(FADING_WIDTHS)}


def _splines(u: np.ndarray, lo: float, hi: float, intervals: int) -> np.ndarray:
    """Cubic B-splines on ``intervals`` equal knot intervals over ``[lo, hi]`` at ``u`` (clamped to it; NaN: the
    first): array[n, intervals + 3], each row summing to 1."""
    from scipy.interpolate import BSpline

    inner = np.linspace(lo, hi, intervals + 1)
    knots = np.r_[[lo] * 3, inner, [hi] * 3]
    x = np.clip(np.nan_to_num(np.asarray(u, dtype=float), nan=lo), lo, hi)
    return BSpline.design_matrix(x, knots, 3).toarray()


def _lagged(tau: np.ndarray, theta: np.ndarray, lag: float) -> np.ndarray:
    """``theta`` passed through a first-order lag of time constant ``lag`` (units of ``tau``), in time order from
    the first reading's value: ``y += (1 - exp(-dt / lag)) (theta - y)`` (exact for a temperature held between
    readings); a reading without a temperature (NaN) holds the lag where it is.  Zero without any temperature."""
    out = np.zeros_like(theta)
    known = np.isfinite(theta)
    if not known.any():
        return out
    order = np.argsort(tau, kind="stable")
    gain = -np.expm1(-np.diff(tau[order], prepend=tau[order][0]) / lag)
    y = theta[known][np.argmin(tau[known])]
    for k, g, now in zip(order, gain, theta[order]):     # a recursion: each output needs the one before
        if np.isfinite(now):
            y += g * (now - y)
        out[k] = y
    return out
