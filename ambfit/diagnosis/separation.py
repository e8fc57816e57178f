"""What would tell undecided candidates apart: the protocol, within the bearing's limits, that separates them best.

When several families explain the data alike (verdict ``undecided``), each candidate's model, as fitted to these
data, predicts the force of readings that another protocol would take.  Where two models predict differently
beyond what refitting one of them can absorb, data from that protocol would tell them apart: the T-optimal
(Atkinson and Fedorov, *Biometrika* 62, 1975) or Box-Hill (*Technometrics* 9, 1967) discrimination
``D = min_theta sum(((F_a - F_b(theta)) / s)^2)``, the noise-free χ² of model ``b`` fitted to data made by ``a``,
linearised about ``b``'s fit.  Half of it is the expected log Bayes factor for ``a`` over ``b`` when ``a`` is
true.  A protocol separates the candidates by the least of these over every ordered pair; :func:`separate_by`
scores a few protocols scaled to the bearing (a bias sweep towards the coil limit, set-points across the positions
already read, the biases in shuffled order), each kept within the bearing's limits by the candidates' own models,
and this data set's own readings, and returns the best.

:func:`time_tied` says when the readings' time is (almost) a function of the set-points, biases and loads (nested
sweeps): a drift is then indistinguishable from an effect of the operating point, and shuffling the order breaks
the tie.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools

import numpy as np
import pandas as pd


@dataclasses.dataclass(frozen=True)
class Separation:
    """The protocol that best separates the candidates, and how well each scored.

    Attributes
    ----------
    protocol : str
        What to run.
    expected_log_bayes : float
        The least expected log Bayes factor over every ordered pair of candidates, on that protocol.
    on_these_data : float
        The same on the readings already taken.
    protocols : dict
        Every protocol scored: ``{description: expected log Bayes factor}``.
    time_tied : float or None
        Share of the readings' time variance that their operating points explain (None without times).
    separates : bool
        Whether that protocol's expected log Bayes factor clears :attr:`ambfit.diagnosis.verdict.Rules.separate_log_bayes`.
    design : Protocol or None
        That protocol's steps (:class:`ambfit.rig.protocol.Protocol`), centred where the readings were: what to run.
    largest_current, current_read, current_limit : float or None
        The largest coil current [A] that protocol needs by the candidates' models as fitted (an extrapolation where
        it is beyond the largest the readings hold, ``current_read``), and the bearing's coil current limit [A].
    """

    protocol: str
    expected_log_bayes: float
    on_these_data: float
    protocols: dict
    time_tied: float | None = None
    separates: bool = False
    design: object = dataclasses.field(default=None, repr=False, compare=False)
    largest_current: float | None = None
    current_read: float | None = None
    current_limit: float | None = None

    def current_note(self) -> str | None:
        """The largest coil current the protocol needs, in words (None when not measured)."""
        if self.largest_current is None:
            return None
        said = (f"that protocol needs coil currents up to {self.largest_current:.2f} A by these data's fitted models, "
                f"against the coil limit of {self.current_limit:g} A")
        if self.current_read is not None and self.largest_current <= self.current_read:
            return said
        read = "" if self.current_read is None else \
            f" beyond the largest these readings hold ({self.current_read:.2f} A),"
        return said + f":{read} an extrapolation; watch the currents as it runs"

    def to_json(self) -> dict:
        out = {"protocol": self.protocol, "expected_log_bayes": self.expected_log_bayes,
               "on_these_data": self.on_these_data, "separates": self.separates, "protocols": dict(self.protocols)}
        if self.largest_current is not None:
            out["largest_coil_current_A"] = self.largest_current
            out["largest_coil_current_read_A"] = self.current_read
            out["coil_current_limit_A"] = self.current_limit
        if self.time_tied is not None:
            out["time_explained_by_operating_points"] = self.time_tied
        return out


def time_tied(df: pd.DataFrame) -> float | None:
    """R² of the readings' time regressed on their operating points (axis, bias, set-points or positions, load):
    near 1 when the protocol's order nests its sweeps, so that time runs with the operating point."""
    if "time_s" not in df or df["time_s"].isna().any() or np.ptp(df["time_s"].to_numpy(float)) <= 0:
        return None
    cols = [c for c in ("bias_A", "v_set_um", "w_set_um") if c in df and df[c].notna().all()] or ["bias_A", "v_um",
                                                                                                  "w_um"]
    parts = [pd.get_dummies(df[c].round(6).astype(str), drop_first=True) for c in cols]
    if "load_id" in df:
        parts.append(pd.get_dummies(df["load_id"].astype(str), drop_first=True))
    x = np.column_stack([np.ones(len(df))] + [p.to_numpy(float) for p in parts if p.shape[1]])
    t = df["time_s"].to_numpy(float)
    fitted = x @ np.linalg.lstsq(x, t, rcond=None)[0]
    return float(1.0 - np.sum((t - fitted) ** 2) / np.sum((t - t.mean()) ** 2))


def separate_by(models: list, df: pd.DataFrame, bearing, noise: dict, enough: float = 5.0) -> Separation | None:
    """The protocol that best separates ``models`` (fitted :class:`~ambfit.estimation.results.FitResult` of each
    candidate on ``df``); None when fewer than two can be compared.  ``enough``: the expected log Bayes factor
    that counts as separating (:attr:`ambfit.diagnosis.verdict.Rules.separate_log_bayes`)."""
    if len(models) < 2:
        return None
    runs = _protocols(models, df, bearing)
    own, *each = _discriminations(models, [(df, noise)] + [(data, {}) for _, _, data, _ in runs])
    scores = {what: v for (what, _, _, _), v in zip(runs, each) if np.isfinite(v)}
    if not scores:
        return None
    best = max(scores, key=scores.get)
    _, design, _, current = next(run for run in runs if run[0] == best)
    return Separation(protocol=best, expected_log_bayes=scores[best], on_these_data=own, protocols=scores,
                      time_tied=time_tied(df), separates=scores[best] > enough, design=design,
                      largest_current=current, current_read=_current_read(df), current_limit=float(bearing.max_current))


def _current_read(df: pd.DataFrame) -> float | None:
    """The largest coil current [A] the readings hold (None without any)."""
    read = df[[c for c in ("i_top_A", "i_bottom_A") if c in df]].abs().to_numpy(float)
    top = float(np.nanmax(read)) if read.size and np.isfinite(read).any() else np.nan
    return top if np.isfinite(top) else None


def _listed(values, most: int = 8) -> str:
    """``values`` spelt out, or, when there are more than ``most``, their number and range."""
    if len(values) > most:
        return f"{len(values)} of them, {min(values):g}-{max(values):g}"
    return ", ".join(f"{v:g}" for v in values)


HEADROOM = 0.97
"""A protocol is kept when none of the candidates' models, as fitted to these data, drives a coil beyond this
share of the coil current limit to run it (nor the ideal law at the first candidate's gap, origin and k).  The ideal
law alone is not enough: on the law zoo (seed 3131, ``benchmarks/separation_zoo.py``) a bias sweep to 80 % of a
3 A limit under four loads needed 2.71-2.75 A by the ideal law and 3.03-3.5 A on the rigs that made the data
(leakage, saturation), which the fitted laws of those families mostly see.  Beyond the readings' own currents their
prediction is an extrapolation, hence the margin and the largest current reported
(:attr:`Separation.largest_current`); on that seed every recommendation runs within the limit on the rig that made
its data (``reports/gap/separation.md``).  The margin is set by the library's iron reluctance case
(``tests/test_undecided.py``), which separates only with its sweep at 2.4 A: 2.83 A of a 3 A limit (a margin of
0.9 lowers the sweep to 2.1 A, and the follow-up stays ``undecided`` between iron reluctance and saturation)."""

SWEEP_TOPS = (0.8, 0.7, 0.6, 0.5)
"""The bias sweep's top as a share of the coil current limit: the highest of these whose currents keep
:data:`HEADROOM`."""

REACH = 0.6
"""The set-points' largest distance from the middle of the readings, as a share of the back-up clearance."""

SPANS = (1.0, 0.75, 0.5, 0.35)
"""The set-points' reach as a share of :data:`REACH`: the widest of these whose set-points are safe
wherever the stator's centre is, given the positions already read (:func:`safe_anywhere`)."""

GAIN_STEPS = 3
"""Gain errors tried per axis across the ``position_gain`` family's range (:func:`sensor_gain_errors`): its ends
and none, on each axis (``GAIN_STEPS**2`` pairs)."""

CENTRE_CELLS = 60
"""Cells across the back-up clearance of the grid on which :func:`safe_anywhere` looks for the stator's possible
centres (1 µm on a 60 µm clearance); a set-point keeps one cell more from the clearance, which covers the grid's
miss of the feasible region's edge (at most half a cell's diagonal)."""


def _hull(points: np.ndarray) -> np.ndarray:
    """The vertices of ``points``' convex hull (all of them when they are fewer than 3 or on one line): what a
    farthest distance or a within-distance-of-all test of a convex set needs."""
    from scipy.spatial import ConvexHull, QhullError

    pts = np.unique(points, axis=0)
    if len(pts) < 3:
        return pts
    try:
        return pts[ConvexHull(pts).vertices]
    except QhullError:                       # (on one line: its two ends)
        along = (pts - pts.mean(axis=0)) @ np.linalg.svd(pts - pts.mean(axis=0))[2][0]
        return pts[[int(np.argmin(along)), int(np.argmax(along))]]


def sensor_gain_errors() -> tuple[float, ...]:
    """The position sensors' gain errors under which a recommended set-point must be safe (:func:`safe_anywhere`):
    :data:`GAIN_STEPS` across the ``position_gain`` family's range (:class:`~ambfit.physics.effects.PositionGain`),
    either sign.  A sensor reading low puts the rotor further out than its set-point says; one reading high widens
    the region the readings leave for the stator's centre."""
    from ambfit.physics.effects import PositionGain

    top = PositionGain.RANGES["gain_error"][1]
    return tuple(float(e) for e in np.linspace(-top, top, GAIN_STEPS))


def safe_anywhere(points: np.ndarray, visited: np.ndarray, clearance: float,
                  gain_errors: tuple[float, ...] = (0.0,)) -> np.ndarray:
    """Whether each of ``points [n, 2]`` is within ``clearance`` of every centre the stator may have: every point
    within ``clearance`` of all the ``visited [m, 2]`` positions (the rotor was at each of them, so the centre was
    within the clearance of each), all [m].  Wider than the positions' convex hull (a point beyond readings near the
    rim can be safe), and safe whatever the fitted origin says.  Where no centre is within the clearance of every
    position (readings farther apart than its diameter: a reassembled rotor, a glitch), none is safe.

    Points and positions are read by the position sensors: a sensor reading ``1 + e`` times the displacement puts
    the rotor at ``1 / (1 + e)`` times what it reads.  A point is safe when it is safe under every pair of
    ``gain_errors`` on the two axes (:func:`sensor_gain_errors` for a rig whose sensors' gain is not known better).
    """
    if not len(gain_errors):
        raise ValueError("gain_errors: at least one gain error (0.0: the sensors read the displacement as it is)")
    pts = np.asarray(points, float).reshape(-1, 2)
    vis = np.asarray(visited, float).reshape(-1, 2)
    safe = np.ones(len(pts), bool)
    for pair in sorted(itertools.product(gain_errors, repeat=2), key=lambda p: np.abs(p).sum()):
        scale = 1.0 + np.asarray(pair)
        safe[safe] = _safe_at(pts[safe] / scale, vis / scale, clearance)     # (only the points still safe)
        if not safe.any():
            break
    return safe


def _safe_at(points: np.ndarray, visited: np.ndarray, clearance: float) -> np.ndarray:
    """:func:`safe_anywhere` with sensors reading the displacement as it is."""
    pts = np.asarray(points, float).reshape(-1, 2)
    vis = _hull(np.round(np.asarray(visited, float).reshape(-1, 2) / 1e-7) * 1e-7)
    if not len(vis):
        return np.zeros(len(pts), bool)
    cell = clearance / CENTRE_CELLS
    mid = 0.5 * (vis.min(axis=0) + vis.max(axis=0))
    axis = np.arange(-clearance, clearance + cell, cell)
    grid = mid[None, :] + np.stack(np.meshgrid(axis, axis), axis=-1).reshape(-1, 2)
    # a centre within the clearance of the hull's vertices is within it of every position
    grid = grid[np.all(np.hypot(grid[:, None, 0] - vis[None, :, 0], grid[:, None, 1] - vis[None, :, 1]) <= clearance,
                       axis=1)]
    if not len(grid):
        return np.zeros(len(pts), bool)
    edge = _hull(grid)                          # (the farthest point of the centres' convex region is a vertex)
    far = np.max(np.hypot(pts[:, None, 0] - edge[None, :, 0], pts[:, None, 1] - edge[None, :, 1]), axis=1)
    return far <= clearance - cell


def _where_read(df: pd.DataFrame) -> np.ndarray:
    """Where each reading was [m, sensor coordinates; rows x (v, w)]: its commanded set-point (``v_set_um``,
    ``w_set_um``) where the table gives one, else its measured position (NaN where neither is known)."""
    def axis(a):
        """One axis' column [µm]: the set-point where given, else the position."""
        pos = df[f"{a}_um"].to_numpy(float)
        if f"{a}_set_um" not in df:
            return pos
        return np.where(df[f"{a}_set_um"].notna().to_numpy(), df[f"{a}_set_um"].to_numpy(float), pos)

    return np.stack([axis("v"), axis("w")], axis=1) * 1e-6


def _middle(df: pd.DataFrame) -> np.ndarray:
    """The middle of the range of where the readings were (:func:`_where_read`) [m], 0 on an axis without any."""
    out = []
    for xs in _where_read(df).T:
        xs = xs[np.isfinite(xs)]
        out.append(0.5 * (xs.min() + xs.max()) if len(xs) else 0.0)
    return np.asarray(out)


def designs(df: pd.DataFrame, bearing, top: float = SWEEP_TOPS[0], span: float = SPANS[0]) -> dict:
    """The protocols scored, scaled to the bearing and centred where the readings were (:func:`_middle`):
    ``{description: Protocol}`` (a bias sweep to ``top`` of the coil limit, set-points across ``span`` of
    :data:`REACH` of the back-up clearance at these data's biases, the same biases as the sweep in shuffled order).

    Not the fitted effective origin: it is where the forces balance, which an error in one coil's channel can move
    tens of µm from the stator's centre (on the law zoo a protocol centred there would have taken the rotor 62 µm
    from the centre of a 60 µm clearance)."""
    from ambfit.rig import protocol

    centre = tuple(_middle(df))
    reach = span * REACH * bearing.backup_clearance / np.sqrt(2.0)
    biases = np.unique(np.round(df["bias_A"].to_numpy(float), 3))
    sweep = tuple(np.round(np.linspace(0.25, top, 6) * bearing.max_current, 3))
    kg = bearing.rotor_mass
    masses = (0.0, 0.5 * kg, kg, 1.5 * kg)
    return {
        f"a bias sweep {sweep[0]:g}-{sweep[-1]:g} A (up and down) at 5 set-points within ±{reach * 1e6:.0f} µm of "
        "the middle of the readings, under 4 known loads":
            protocol.rich(biases=sweep, span=reach, center=centre, masses_kg=masses, rotor_kg=kg),
        f"9 set-points across ±{reach * 1e6:.0f} µm of the middle of the readings at this data's biases "
        f"({_listed(biases)} A), under 4 known loads":
            protocol.rich(biases=tuple(biases), span=reach, n_positions=9, center=centre, masses_kg=masses,
                          rotor_kg=kg),
        f"the biases {sweep[0]:g}-{sweep[-1]:g} A in shuffled order at a 5 x 3 grid of set-points within "
        f"±{reach * 1e6:.0f} µm of the middle of the readings, under 4 known loads (time does not run with the "
        "sweep)":
            protocol.serpentine(biases=sweep, span=(reach, 0.75 * reach), center=centre, masses_kg=masses,
                                rotor_kg=kg, seed=7),
    }


def _protocols(models: list, df: pd.DataFrame, bearing) -> list[tuple[str, object, pd.DataFrame, float]]:
    """Each of :func:`designs` (description, protocol) with its readings, simulated on a rig of the first model's
    fitted gap, origin and k (the ideal law: only where the readings fall matters), and the largest coil current it
    needs.  Its set-points are drawn in until they are safe wherever the stator's centre is (:data:`SPANS`,
    :func:`safe_anywhere`), and its sweep lowered until every model of ``models`` (the candidates' fits), run on it
    at its own fitted gap, origin and k, keeps the coil currents within :data:`HEADROOM`.  A protocol that cannot is
    left out; when none can, a sweep at the set-points already read (:func:`_at_the_readings`)."""
    from ambfit.rig import virtual as rig

    def rig_of(fitted):
        vals = dict(zip(fitted.names, fitted.values))
        return rig.RigSpec.for_bearing(bearing).with_truth(
            g0=(vals.get("g_v0", bearing.nominal_gap), vals.get("g_w0", bearing.nominal_gap)),
            x0=(vals.get("v0", 0.0), vals.get("w0", 0.0)),
            k=(vals["k_v"], vals["k_w"]) if {"k_v", "k_w"} <= set(vals) else None)

    thermometer = "temperature_C" in df and bool(df["temperature_C"].notna().any())

    def largest(spec, design, effects=()) -> float:
        """The largest coil current [A] of ``design`` run by ``effects`` on ``spec`` (inf: it cannot be run)."""
        try:
            currents = rig.simulate(spec, design, list(effects), noise=rig.NOISE_FREE, seed=0,
                                    thermometer=thermometer).physical_currents
        except (rig.RigError, ValueError):
            return np.inf
        top = float(np.max(np.abs(currents)))
        return top if np.isfinite(top) else np.inf

    spec = rig_of(models[0])
    sigma = _noise_of(df)
    visited = df[["v_um", "w_um"]].to_numpy(float) * 1e-6
    visited = visited[np.all(np.isfinite(visited), axis=1)]
    if not len(visited):
        return []
    limit = HEADROOM * bearing.max_current
    needs = {}

    def need_of(what, design) -> float:
        """The largest coil current ``design`` needs by the ideal law and each model with effects (judged once per
        description: a protocol the sweep's top does not change is the same protocol), stopping beyond the limit."""
        if what not in needs:
            need = largest(spec, design)
            for m in (m for m in models if m.effects):
                if need > limit:
                    break
                need = max(need, largest(rig_of(m), design, m.effects))
            needs[what] = need
        return needs[what]

    def run(what, design) -> tuple:
        sim = rig.simulate(spec, design, noise=rig.Noise(current=sigma[0], position=sigma[1]), seed=0,
                           thermometer=thermometer)
        return what, design, sim.data, needs[what]

    listed = functools.cache(lambda top, span: list(designs(df, bearing, top, span).items()))
    gains = sensor_gain_errors()

    def safe(slot, span) -> bool:
        """Whether the slot's set-points at ``span`` are safe wherever the stator's centre is (the top does not
        move them)."""
        design = listed(SWEEP_TOPS[0], span)[slot][1]
        return bool(np.all(safe_anywhere(np.stack([design.v_set, design.w_set], axis=1), visited,
                                         bearing.backup_clearance, gains)))

    out = []
    for slot in range(len(listed(SWEEP_TOPS[0], SPANS[0]))):
        span = next((span for span in SPANS if safe(slot, span)), None)
        if span is None:
            continue
        # the widest reach among the readings, whatever its currents; the highest sweep within the headroom
        tries = (listed(top, span)[slot] for top in SWEEP_TOPS)
        chosen = next((entry for entry in tries if need_of(*entry) <= limit), None)
        if chosen is not None:
            out.append(run(*chosen))
    if not out:                              # (readings too close together for any reach: their own set-points)
        tries = (_at_the_readings(df, bearing, top) for top in SWEEP_TOPS)
        chosen = next((entry for entry in tries if need_of(*entry) <= limit), None)
        if chosen is not None:
            return [run(*chosen)]
    return out


def _at_the_readings(df: pd.DataFrame, bearing, top: float) -> tuple[str, object]:
    """A bias sweep to ``top`` of the coil limit at the (at most 5) set-points already read nearest their middle,
    under the loads of :func:`designs`: where the rotor has been, safe whatever the centre."""
    from ambfit.rig import protocol

    seen = _where_read(df)
    seen = np.unique(np.round(seen[np.all(np.isfinite(seen), axis=1)] / 1e-7) * 1e-7, axis=0)
    points = seen[np.argsort(np.hypot(*(seen - _middle(df)).T))[:5]]
    first = next(iter(designs(df, bearing, top).values()))
    names = list(dict.fromkeys(first.load_id))
    sweep = tuple(np.round(np.linspace(0.25, top, 6) * bearing.max_current, 3))
    design = protocol.concat(*(protocol.bias_sweep(sweep, [tuple(p) for p in points], loads=first.loads, load=name,
                                                   experiment=f"sweep under {name}") for name in names))
    return (f"a bias sweep {sweep[0]:g}-{sweep[-1]:g} A (up and down) at the {len(points)} set-point(s) already read "
            f"nearest their middle, under {len(names)} known loads", design)


def _noise_of(df: pd.DataFrame) -> tuple[float, float]:
    """The readings' typical current [A] and position [m] noise (std columns, else the rig's default)."""
    from ambfit.rig import virtual as rig

    cur = df[["i_top_std_A", "i_bottom_std_A"]].median().mean() if {"i_top_std_A", "i_bottom_std_A"} <= set(df) \
        else np.nan
    pos = df[["v_std_um", "w_std_um"]].median().mean() * 1e-6 if {"v_std_um", "w_std_um"} <= set(df) else np.nan
    return (float(cur) if np.isfinite(cur) and cur > 0 else rig.Noise().current,
            float(pos) if np.isfinite(pos) and pos > 0 else rig.Noise().position)


def _discriminations(models: list, tables: list) -> list[float]:
    """The least expected log Bayes factor, over every ordered pair of ``models``, on each of ``tables``' readings
    (``(data, noise)`` each).  Each model is measured on every table at once: the tables' problems padded to one
    shape (rows and loads) and vmapped, so that a model compiles one program whatever the tables' lengths."""
    from jax import tree_util

    from ambfit.data import zero_based
    from ambfit.estimation.batches import load_bucket, pad, placed_columns, row_bucket
    from ambfit.estimation.core import Model, build_problem, free_mask, measured_sets

    built = [build_problem(zero_based(data), **noise) for data, noise in tables]
    # tables whose problems share a structure (which optional columns they have) are measured together
    kinds: dict = {}
    for t, (prob, _) in enumerate(built):
        kinds.setdefault(tree_util.tree_structure(prob), []).append(t)
    preds: list = [[] for _ in tables]
    for members in kinds.values():
        rows = row_bucket(max(len(np.asarray(built[t][0].mask)) for t in members))
        loads = load_bucket(max(len(built[t][1].load_groups) for t in members))
        # (the tables too, to a power of two with copies of the first: a few batch shapes in all)
        width = 1 << (len(members) - 1).bit_length()
        stacked = pad([built[t][0] for t in members + members[:1] * (width - len(members))], rows)
        for m in models:
            model = Model.of(m.effects, m.bearing)
            head, tail = m.theta[:6], m.theta[len(m.theta) - model.n:]
            theta = np.tile(np.concatenate([head, np.zeros(loads), tail]), (width, 1))
            f, s, jac = (np.asarray(a) for a in measured_sets(theta, stacked, model))
            for b, t in enumerate(members):
                prob, meta = built[t]
                n = len(np.asarray(prob.mask))
                # the table's own columns (the head, its loads, the effects) that it estimates
                cols = placed_columns(6 + len(meta.load_groups), model.n, loads)[free_mask(prob, meta, model)]
                # each model's Jacobian once: it is the refitted side of every pair it is in
                preds[t].append((f[b, :n], s[b, :n], jac[b, :n][:, cols]))
    return [_least(p) for p in preds]


def _least(preds: list) -> float:
    """The least expected log Bayes factor over every ordered pair of models measured on one table (``(F - L,
    s_eff, Jacobian)`` each, with loads at zero: a load's column absorbs them)."""
    least = np.inf
    for (fa, _, _), (fb, sb, jac) in itertools.permutations(preds, 2):
        delta = (fa - fb) / sb
        ok = np.isfinite(delta) & np.all(np.isfinite(jac), axis=1)
        if not ok.any():
            continue
        left = delta[ok] - jac[ok] @ np.linalg.lstsq(jac[ok], delta[ok], rcond=None)[0]
        least = min(least, 0.5 * float(left @ left))
    return float(least)
