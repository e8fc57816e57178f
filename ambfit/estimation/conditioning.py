"""The solution space of the paper's Fig. 2: misfit over a (gap, origin) grid, and design comparison.

For one axis, every grid point ``(g0, x0)`` is scored by the χ² of the readings
with the linear parameters profiled out: ``k`` (from the known loads) and the
nuisance loads enter Eq. 4 linearly, so their best values at each grid point are
weighted least-squares closed forms.  Without a known load ``k`` is held and the
loads absorb the scale.  The weights are the effective-variance weights at the
least-squares optimum (held fixed over the map).  The whole grid is one
vectorised evaluation (401 x 201 points in well under a second).

Why the valley: with current perturbation at one position only, Eq. 6 fixes the
ratio ``(g0 - u) / (g0 + u)``, ``u = (x0 + x) cos(alpha)``, i.e. only ``u / g0``:
every point on a line through the origin of the (gap, u) plane fits.  A second
position adds a second such line; two nearly parallel lines (positions close
together, or far from the effective origin compared with their separation)
meet at a shallow angle and leave a long valley whose direction is the weakest
eigenvector of the Fisher information.  Symmetric pairs about the effective origin
make the two ratios move in opposite directions and the lines cross most steeply.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from ambfit.data import Dataset
from ambfit.estimation.core import K_REFERENCE, Model, build_problem, noise_std, to_theta
from ambfit.estimation.seeds import seed_loads_and_k
from ambfit.physics.bearing import AXES, PAPER_BEARING, Bearing
from ambfit.physics.model import ideal_force


@dataclasses.dataclass(frozen=True)
class SolutionSpace:
    """χ² over a (gap, origin) grid for one axis (SI units).

    ``chi2[i, j]`` is at ``gap[i]``, ``origin[j]``; ``rms`` is the RMS force misfit [N].
    """

    axis: str
    gap: np.ndarray
    origin: np.ndarray
    chi2: np.ndarray
    rms: np.ndarray
    n_rows: int
    widened: int = 0

    @property
    def minimum(self) -> tuple[float, float]:
        i, j = np.unravel_index(np.nanargmin(self.chi2), self.chi2.shape)
        return float(self.gap[i]), float(self.origin[j])

    @property
    def on_edge(self) -> bool:
        """The minimum lies on the grid's boundary: the valley runs beyond the grid and the true minimum may
        lie outside it (widen the ranges)."""
        i, j = np.unravel_index(np.nanargmin(self.chi2), self.chi2.shape)
        return bool(i in (0, len(self.gap) - 1) or j in (0, len(self.origin) - 1))

    def edge_text(self) -> str:
        """What the minimum on the edge means and what to do; empty when it is inside."""
        if not self.on_edge:
            return ""
        tried = f" (after widening the grid {self.widened} times)" if self.widened else ""
        return (f"axis {self.axis}: the minimum lies on the edge of the grid (gap {self.gap[0] * 1e6:.0f}-"
                f"{self.gap[-1] * 1e6:.0f} µm, origin {self.origin[0] * 1e6:.0f}-{self.origin[-1] * 1e6:.0f} µm)"
                f"{tried}: the valley runs beyond it, so the map does not show the best fit; give wider ranges")

    def delta_chi2(self) -> np.ndarray:
        return self.chi2 - np.nanmin(self.chi2)

    def summary(self) -> str:
        gm, xm = self.minimum
        text = (f"grid {self.chi2.shape[0]} x {self.chi2.shape[1]} (axis {self.axis}, {self.n_rows} rows, gap "
                f"{self.gap[0] * 1e6:.0f}-{self.gap[-1] * 1e6:.0f} µm, origin {self.origin[0] * 1e6:.0f}-"
                f"{self.origin[-1] * 1e6:.0f} µm); minimum at gap {gm * 1e6:.1f} µm, origin {xm * 1e6:.1f} µm")
        return text + ("; ON THE GRID'S EDGE" if self.on_edge else "")

    __str__ = summary


@functools.partial(jax.jit, static_argnames="cos_alpha")
def _grid_chi2(g, x0, x, it, ib, w, load, known, gidx_onehot, k_ref, cos_alpha):
    """χ² and mean-square misfit for grids g[G], x0[X] (vectorised) with profiled k and loads."""
    gg = g[:, None, None]
    unit = ideal_force(gg, x0[None, :, None], 1.0, it, ib, x[None, None, :], cos_alpha)   # [G, X, n], k = 1
    u = (x0[None, :, None] + x[None, None, :]) * cos_alpha
    # k from the known-load rows (weighted LS through the origin), k_ref if none
    num = jnp.sum(w * unit * load * known, axis=-1)
    den = jnp.sum(w * unit**2 * known, axis=-1)
    k = jnp.where(jnp.sum(known) > 0, num / jnp.where(den > 0, den, 1.0), k_ref)[..., None]
    f = k * unit
    # nuisance loads: weighted mean of the force over each group
    sw = jnp.einsum("n,nm->m", w, gidx_onehot)
    lmean = jnp.einsum("gxn,n,nm->gxm", f, w, gidx_onehot) / jnp.where(sw > 0, sw, 1.0)
    target = jnp.where(known, load, jnp.einsum("gxm,nm->gxn", lmean, gidx_onehot))
    res = f - target
    ok = jnp.all(jnp.abs(u) < 0.98 * gg, axis=-1)
    chi2 = jnp.where(ok, jnp.sum(w * res**2, axis=-1), jnp.nan)
    ms = jnp.where(ok, jnp.mean(res**2, axis=-1), jnp.nan)
    return chi2, ms


class GridSizeError(ValueError):
    """A χ² map with a step or ranges it cannot be made with (see :func:`grid_shape`)."""


MAX_GRID_CELLS = 2**25
"""Most grid points x rows the χ² map evaluates at once: each [gap, origin, row] array of float64 then takes
256 MiB, and the evaluation holds several.  The paper's Fig. 2 grid (401 x 201) over 40 rows is 3.2e6."""


def grid_shape(gap, origin, step: float, n_rows: int) -> tuple[int, int]:
    """Points of the χ² map along gap and origin (SI ranges ``(low, high)``, ``step`` [m]) for ``n_rows`` readings.

    Raises GridSizeError for a step that is not positive, a range with ``low >= high``, or a map beyond
    :data:`MAX_GRID_CELLS` (the message gives its size and the smallest step that fits).
    """
    if not (np.isfinite(step) and step > 0):
        raise GridSizeError(f"the grid step must be a positive number, got {step:g} m")
    for what, (lo, hi) in (("gap", gap), ("origin", origin)):
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise GridSizeError(f"the {what} range must be finite with low < high, got ({lo:g}, {hi:g}) m")
    n_g, n_x = (int(np.ceil((hi + step / 2 - lo) / step)) for lo, hi in (gap, origin))
    cells = float(n_g) * n_x * max(n_rows, 1)
    if cells > MAX_GRID_CELLS:
        least = np.sqrt((gap[1] - gap[0]) * (origin[1] - origin[0]) * max(n_rows, 1) / MAX_GRID_CELLS)
        raise GridSizeError(f"a grid of {n_g} gap x {n_x} origin points over {n_rows} rows is {cells:.3g} cells, more "
                         f"than the {MAX_GRID_CELLS:.3g} the map computes at once; use a step of at least "
                         f"{least * 1.01e6:.3g} µm or narrower ranges")
    return n_g, n_x


PAPER_FIG2 = {"gap": (600e-6, 1000e-6), "origin": (-100e-6, 100e-6)}
"""The axes of the paper's Fig. 2 [m] (its 762 µm rig): ``solution_space(data, **PAPER_FIG2)``."""

GRID_SIGMAS = 10.0
"""The default grid reaches at least this many standard errors of the fit on each side."""

GRID_GAP_FRACTIONS = (0.25, 0.125)
"""...and at least these fractions of the gap on each side, for the gap and the origin: the paper's Fig. 2
(±200 µm of gap, ±100 µm of origin about a 775 µm gap), so that the valley shows."""

GRID_POINTS = 401
"""Largest number of grid points along an axis by default (the step grows beyond 1 µm on wide grids)."""

MAX_WIDENINGS = 3
"""How often the default grid is doubled about its minimum while that minimum lies on its edge."""


def _default_ranges(g_hat: float, x_hat: float, sd_g: float, sd_x: float) -> tuple[tuple, tuple]:
    """Gap and origin ranges [m] centred on ``(g_hat, x_hat)``: ``GRID_SIGMAS`` standard errors or
    ``GRID_GAP_FRACTIONS`` of the gap on each side, whichever is wider."""
    half = [max(GRID_SIGMAS * sd if np.isfinite(sd) else 0.0, f * g_hat) for sd, f in zip((sd_g, sd_x),
                                                                                          GRID_GAP_FRACTIONS)]
    return (g_hat - half[0], g_hat + half[0]), (x_hat - half[1], x_hat + half[1])


def solution_space(data: Dataset | pd.DataFrame, axis: str = "v", *, gap=None, origin=None,
                   step: float | None = None, weights_at=None, bearing: Bearing = PAPER_BEARING,
                   **noise) -> SolutionSpace:
    """χ² map of one axis over a (gap, origin) grid.

    ``gap`` and ``origin``: ranges ``(low, high)`` [m]; by default centred on the least-squares estimate (the
    bearing's nominal gap and origin 0 when the fit fails), ``GRID_SIGMAS`` standard errors or
    ``GRID_GAP_FRACTIONS`` of the gap to each side, whichever is wider, and doubled about the minimum (up to
    ``MAX_WIDENINGS`` times) while the minimum lies on the grid's edge.  Given ranges are mapped as they are.
    Either way :attr:`SolutionSpace.on_edge` says whether the minimum lies on the edge.  ``step`` [m]: the grid
    step (default 1 µm, coarser when an axis would have more than ``GRID_POINTS`` points).  The paper's
    Fig. 2 axes: ``**PAPER_FIG2``.

    ``weights_at``: a :class:`ambfit.FitResult` whose optimum fixes the
    effective-variance weights and centres the default grid; default: fit the data first.
    ``noise``: ``sigma_i`` [A] and ``sigma_x`` [m], as in :func:`ambfit.estimation.fit.fit`.
    """
    from ambfit.estimation.fit import FitError, fit

    df = data.frame if isinstance(data, Dataset) else data
    if axis not in AXES:
        raise ValueError(f"axis must be one of {AXES}, got {axis!r}")
    sub = df[df["axis"] == axis].reset_index(drop=True)
    if sub.empty:
        raise ValueError(f"no rows of axis {axis!r}")
    if gap is not None and origin is not None and step is not None:
        grid_shape(gap, origin, step, len(sub))                 # (before the fit: a map that cannot be made)
    prob, meta = build_problem(sub, **noise)
    res = weights_at
    if res is None:
        try:
            res = fit(sub, bearing=bearing, debias="none", **noise)
        except FitError:  # unidentifiable designs still have a map: weight at the nominal point
            res = None
    sd_g = sd_x = np.nan
    if res is not None:
        vals = dict(zip(res.names, res.values))
        g_hat, x_hat = vals.get(f"g_{axis}0", bearing.nominal_gap), vals.get(f"{axis}0", 0.0)
        k_hat = vals.get(f"k_{axis}", K_REFERENCE)
        if f"g_{axis}0" in res.names and f"{axis}0" in res.names:
            sd_g, sd_x = res.error(f"g_{axis}0"), res.error(f"{axis}0")
    else:
        g_hat, x_hat, k_hat = bearing.nominal_gap, 0.0, K_REFERENCE
    g_pair, x_pair, k_pair = np.full(2, g_hat), np.full(2, x_hat), np.full(2, k_hat)
    loads = np.zeros(prob.n_loads)
    model = Model.of((), bearing)
    if prob.n_loads:
        th = seed_loads_and_k(to_theta(g_pair, x_pair, k_pair, loads), prob, bearing)
    else:
        th = to_theta(g_pair, x_pair, k_pair, loads)
    s = np.asarray(noise_std(jnp.asarray(th), prob, model))
    w = 1.0 / s**2
    gidx = np.asarray(prob.gidx)
    onehot = np.zeros((len(sub), max(prob.n_loads, 1)))
    if prob.n_loads:
        onehot[gidx >= 0, gidx[gidx >= 0]] = 1.0

    def grid(gap, origin):
        d = step if step is not None else max(1e-6, (gap[1] - gap[0]) / (GRID_POINTS - 1),
                                              (origin[1] - origin[0]) / (GRID_POINTS - 1))
        if step is None:        # (coarser still where the default map would exceed MAX_GRID_CELLS)
            d = max(d, 1.01 * np.sqrt((gap[1] - gap[0]) * (origin[1] - origin[0]) * len(sub) / MAX_GRID_CELLS))
        grid_shape(gap, origin, d, len(sub))
        gs = np.arange(max(gap[0], d), gap[1] + d / 2, d)      # a gap is positive
        xs = np.arange(origin[0], origin[1] + d / 2, d)
        chi2, ms = _grid_chi2(jnp.asarray(gs), jnp.asarray(xs), prob.x, prob.i_top, prob.i_bottom, jnp.asarray(w),
                              prob.load, prob.known.astype(float), jnp.asarray(onehot), K_REFERENCE,
                              bearing.cos_alpha)
        if not np.isfinite(np.asarray(chi2)).any():
            raise ValueError(f"axis {axis}: no point of the grid (gap {gap[0] * 1e6:.0f}-{gap[1] * 1e6:.0f} µm, "
                             f"origin {origin[0] * 1e6:.0f}-{origin[1] * 1e6:.0f} µm) keeps the readings' "
                             "positions inside the gap")
        return gs, xs, np.asarray(chi2), np.sqrt(np.asarray(ms))

    fixed = gap is not None or origin is not None
    auto_gap, auto_origin = _default_ranges(g_hat, x_hat, sd_g, sd_x)
    gap, origin = gap or auto_gap, origin or auto_origin
    widened = 0
    while True:
        space = SolutionSpace(axis, *grid(gap, origin), n_rows=len(sub), widened=widened)
        if fixed or not space.on_edge or widened == MAX_WIDENINGS:
            return space
        (gm, xm), widened = space.minimum, widened + 1
        gap = (gm - (gap[1] - gap[0]), gm + (gap[1] - gap[0]))
        origin = (xm - (origin[1] - origin[0]), xm + (origin[1] - origin[0]))


def weakest_direction(result, axis: str = "v") -> np.ndarray:
    """Unit vector in (gap, origin) of the least-determined combination, from the fit's covariance."""
    i, j = result.names.index(f"g_{axis}0"), result.names.index(f"{axis}0")
    c = result.cov[np.ix_([i, j], [i, j])]
    w, v = np.linalg.eigh(c)
    return v[:, -1]


# --- design comparison ---------------------------------------------------------------------------

def standard_designs(center=(-33.3e-6, 11.3e-6), *, same_load: bool = False) -> dict:
    """The designs the paper discusses, 10 repetitions each, with unknown loads.

    ``current-only``: one position, five biases; ``position-only``: one bias, five
    positions; ``symmetric (paper)``: ±20 µm pairs at 1.4/1.6 A; ``non-symmetric``:
    positions +10/+50 µm from the effective origin at 1.4/1.6 A; ``rich``: biases
    1.0-1.6 A at five positions over ±40 µm.

    ``same_load=False`` (default) gives every position its own unknown load, which is
    all Eq. 5 assumes (the load is the same only across the biases at one position):
    the information the paper's method uses.  ``same_load=True`` tells the fit that one
    load is carried at every position, which least squares can exploit and Eq. 7 cannot.
    """
    from ambfit.rig import protocol as P

    cv, cw = center

    def design(points, biases):
        parts = []
        for j, pt in enumerate(points):
            lid = "u" if same_load else f"u{j}"
            loads = {lid: P.Load.gravity(1.0, known=False)}
            for i in range(1, 11):
                parts.append(P.grid([pt], biases, load=lid, loads=loads, iteration=i))
        return P.concat(*parts)

    spread = [(cv + d, cw + d) for d in np.linspace(-40e-6, 40e-6, 5)]
    return {
        "current-only": design([(cv, cw)], [1.0, 1.2, 1.4, 1.6, 1.8]),
        "position-only": design(spread, [1.4]),
        "symmetric (paper)": design([(cv + 20e-6, cw + 20e-6), (cv - 20e-6, cw - 20e-6)], [1.4, 1.6]),
        "non-symmetric": design([(cv + 10e-6, cw + 10e-6), (cv + 50e-6, cw + 50e-6)], [1.4, 1.6]),
        "rich": design(spread, [1.0, 1.2, 1.4, 1.6]),
    }


def compare_designs(spec=None, noise=None, designs: dict | None = None) -> pd.DataFrame:
    """Condition number and Cramér-Rao bounds of gap and origin (v axis) for each design, under both load
    assumptions of :func:`standard_designs` (one unknown load per position, or one shared)."""
    from ambfit import rig
    from ambfit.estimation import information

    spec = spec or rig.PAPER_RIG
    noise = noise or rig.Noise()
    rows = []
    center = spec.centre
    sets = {"": designs} if designs else {"load per position": standard_designs(center),
                                          "one shared load": standard_designs(center, same_load=True)}
    for loads, ds in sets.items():
        for name, proto in ds.items():
            info = information.design_information(spec, proto, noise)
            rows.append({"design": name, "loads": loads, "readings": 2 * len(proto), "condition": info.condition,
                         "crlb_gap_um": info.std("g_v0") * 1e6, "crlb_origin_um": info.std("v0") * 1e6,
                         "weakest_gap_component": info.weakest.get("g_v0", np.nan)})
    return pd.DataFrame(rows)


# --- can these data determine an effect? ---------------------------------------------------------

def effect_identification(data: Dataset | pd.DataFrame, effects, start=None, *, bearing: Bearing = PAPER_BEARING,
                          sigma_i: float | None = None, sigma_x: float | None = None) -> dict:
    """How much each effect parameter's prior still holds after these data, at the start of the extended fit.

    The extended model's Jacobian is taken where its fit starts (the ideal law's estimate ``start``, fitted when
    not given; effects at their prior centre).  With the data's information ``J^T J`` (scaled parameters) and the
    unit prior of each effect coordinate, the posterior variance of a coordinate, ``[(J^T J + P)^-1]_jj`` in
    ``(0, 1]``, is the share of the prior's variance the data leave: near 1 the data do not determine that
    parameter, and a solver that looks for it wanders (this is the cause of a non-converged extended fit).

    Returns
    -------
    dict
        ``{parameter name: prior share}`` for every effect parameter.
    """
    from ambfit.estimation.fit import fit
    from ambfit.estimation.identification import prior_shares

    if start is None:
        start = fit(data, bearing=bearing, sigma_i=sigma_i, sigma_x=sigma_x, throw=False, debias="none")
    prob, meta = build_problem(data, sigma_i=sigma_i, sigma_x=sigma_x)
    return prior_shares(prob, meta, Model.of(tuple(effects), bearing), start)
