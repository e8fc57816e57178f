"""The seed paper's Tables 1-4 and Figs. 2, 3 and 5 rerun on the virtual rig, side by side with the paper.

The paper's results live in ``data/paper/`` (one CSV per table, units in the column
names, source table and row in columns; ``rig_settings.csv`` for the numbers stated in
the text).  :func:`reproduce` runs each table row's protocol on
:data:`ambfit.rig.PAPER_RIG` the way the paper did (the effective-origin search of
:mod:`ambfit.studies.origin`, 10 iterations, Eq. 5-7 per iteration, the row is the mean over
the iterations) and repeats the whole set of experiments ``replicates`` times to
*predict* each row's scatter and each table's between-row spread from the rig's
noise, which is calibrated on Table 2's per-iteration scatter only.

What the rig knows about the paper (and so cannot predict): its true gaps and
origins are the paper's overall means (775/763 µm, 33.3/-11.3 µm, Table 4 after a
reassembly shift to -47.4/13.1 µm).  Agreement of the *means* is therefore by
construction; the *spreads* are the prediction.

Example
-------
>>> from ambfit.studies import paper
>>> paper.load_table(1)[["source_row", "g_v0_um"]].to_dict("records")[0]
{'source_row': '1', 'g_v0_um': 778.71}
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd

from ambfit.rig.virtual import PAPER_RIG, Noise, RigSpec

QUANTITIES = ("v0_um", "w0_um", "g_v0_um", "g_w0_um")
"""The four identified quantities of every table, µm."""

TABLE4_SHIFT = (-80.7e-6, 24.4e-6)
"""Origin shift of the Table 4 reassembly [m]: the paper's 33.3/-11.3 µm to -47.4/13.1 µm."""


def data_dir() -> Path:
    """``data/paper/`` of the source tree (or the copy packaged with a wheel)."""
    package = Path(__file__).resolve().parents[1]
    for cand in (package.parent / "data" / "paper", package / "paper_data"):
        if (cand / "table1.csv").exists():
            return cand
    raise FileNotFoundError(f"the paper's tables are not found next to {package} (data/paper/ or ambfit/paper_data/)")


def _read(name: str) -> pd.DataFrame:
    return pd.read_csv(data_dir() / name, dtype={"source_row": str, "source_no": str}, keep_default_na=False,
                       na_values={c: [""] for c in QUANTITIES})


def load_table(n: int, averages: bool = False) -> pd.DataFrame:
    """Table ``n`` (1-4) as printed: numbered rows only, or (``averages=True``) only the printed average row."""
    if n not in (1, 2, 3, 4):
        raise ValueError(f"the paper has Tables 1-4, got {n}")
    df = _read(f"table{n}.csv")
    is_row = df["source_row"].str.fullmatch(r"\d+")
    out = df[~is_row if averages else is_row].reset_index(drop=True)
    num = [c for c in out.columns if c.endswith(("_um", "_A"))]
    out[num] = out[num].apply(pd.to_numeric, errors="coerce")
    return out


def settings() -> pd.DataFrame:
    """The rig settings stated in the paper's text (quantity, value, unit, source)."""
    return _read("rig_settings.csv")


@dataclasses.dataclass(frozen=True)
class Row:
    """One experiment of the paper: a table row's protocol (SI units)."""

    table: int
    row: int
    biases: tuple[float, float]
    offset: float
    start: tuple[float, float] = (0.0, 0.0)
    origin_shift: tuple[float, float] = (0.0, 0.0)

    @property
    def label(self) -> str:
        s = f"T{self.table}.{self.row} {self.biases[0]:.1f}/{self.biases[1]:.1f} A ±{self.offset * 1e6:.0f} µm"
        if self.start != (0.0, 0.0):
            s += f" from ({self.start[0] * 1e6:g}, {self.start[1] * 1e6:g}) µm"
        return s


def rows() -> list[Row]:
    """The experiments of Tables 1, 3 and 4 (Table 2 is the iterations of Table 1's row 2)."""
    out = []
    for t in (1, 3, 4):
        for r in load_table(t).itertuples():
            start = (r.initial_v_um * 1e-6, r.initial_w_um * 1e-6) if t == 3 else (0.0, 0.0)
            out.append(Row(table=t, row=int(r.source_row), biases=(r.bias_low_A, r.bias_high_A),
                           offset=r.pair_v_um * 1e-6, start=start,
                           origin_shift=TABLE4_SHIFT if t == 4 else (0.0, 0.0)))
    return out


def run_row(row: Row, *, spec: RigSpec = PAPER_RIG, noise: Noise = Noise(), seed=0, iterations: int = 10):
    """The paper's experiment for one row: the effective-origin search (:func:`ambfit.studies.origin.search`)."""
    from ambfit.studies import origin

    s = spec if row.origin_shift == (0.0, 0.0) else spec.with_truth(x0=np.asarray(spec.x0) + row.origin_shift)
    return origin.search(s, biases=row.biases, offset=row.offset, start=row.start, iterations=iterations,
                         noise=noise, seed=seed, experiment=f"T{row.table}.{row.row}")


def iteration_values(search) -> np.ndarray:
    """Per-iteration (v0, w0, g_v0, g_w0) [µm] of one search, array[iterations, 4]."""
    return np.column_stack([search.x0[:, 0], search.x0[:, 1], search.g0[:, 0], search.g0[:, 1]]) * 1e6


@dataclasses.dataclass(frozen=True)
class Reproduction:
    """The paper's experiments on the rig.

    Attributes
    ----------
    rows : list[Row]
    run : array[rows, iterations, 4]
        The reproduction (one seeded run): per-iteration Eq. 7 estimates, µm, in
        :data:`QUANTITIES` order.
    replicates : array[R, rows, iterations, 4]
        ``R`` independent repetitions of every experiment (the prediction).
    searches : list[OriginSearch]
        The reproduction's searches (data and trajectories), one per row.
    least_squares : list[dict | None]
        ambfit's least-squares fit of each reproduction row's readings (value, std), µm.
    noise : Noise
    seconds : float
    """

    rows: list
    run: np.ndarray
    replicates: np.ndarray
    searches: list
    least_squares: list
    noise: Noise
    spec: RigSpec
    seconds: float
    failed: int

    @property
    def table2_index(self) -> int:
        """Index of Table 1's row 2, whose iterations are Table 2."""
        return next(j for j, r in enumerate(self.rows) if r.table == 1 and r.row == 2)

    def _index(self, table: int) -> list[int]:
        return [j for j, r in enumerate(self.rows) if r.table == table]

    def comparison(self) -> pd.DataFrame:
        """Every row of Tables 1-4, paper vs reproduction, one line per row and quantity.

        Columns: ``table, row, label, quantity, paper, rig_run`` (this reproduction),
        ``rig_mean, rig_sd`` (predicted mean and standard deviation of the row's value
        over replicates), ``diff = paper - rig_mean`` [µm], ``z = diff / rig_sd`` and,
        where fitted, ``ls, ls_std`` (least squares on the reproduction's readings).
        """
        out = []
        rep_means = self.replicates.mean(axis=2)               # [R, rows, 4]
        run_means = self.run.mean(axis=1)                      # [rows, 4]
        tables = {t: load_table(t).set_index("source_row") for t in (1, 3, 4)}
        for j, r in enumerate(self.rows):
            paper = tables[r.table].loc[str(r.row)]
            for q, name in enumerate(QUANTITIES):
                m, s = float(rep_means[:, j, q].mean()), float(rep_means[:, j, q].std(ddof=1))
                ls = self.least_squares[j]
                out.append({"table": r.table, "row": r.row, "label": r.label, "quantity": name,
                            "paper": float(paper[name]), "rig_run": float(run_means[j, q]), "rig_mean": m,
                            "rig_sd": s, "diff": float(paper[name]) - m, "z": (float(paper[name]) - m) / s,
                            "ls": np.nan if ls is None else ls[name][0],
                            "ls_std": np.nan if ls is None else ls[name][1]})
        # Table 2: the iterations of Table 1's row 2
        j2 = self.table2_index
        t2 = load_table(2)
        for it in range(min(len(t2), self.run.shape[1])):
            for q, name in enumerate(QUANTITIES):
                vals = self.replicates[:, j2, it, q]
                m, s = float(vals.mean()), float(vals.std(ddof=1))
                p = float(t2[name].iloc[it])
                out.append({"table": 2, "row": it + 1, "label": f"T2 iteration {it + 1}", "quantity": name,
                            "paper": p, "rig_run": float(self.run[j2, it, q]), "rig_mean": m, "rig_sd": s,
                            "diff": p - m, "z": (p - m) / s, "ls": np.nan, "ls_std": np.nan})
        # the printed averages (row 0): mean of the table's rows
        for t in (1, 2, 3, 4):
            avg = load_table(t, averages=True).iloc[0]
            idx = [j2] if t == 2 else self._index(t)
            for q, name in enumerate(QUANTITIES):
                sims = rep_means[:, idx, q].mean(axis=1)
                m, s = float(sims.mean()), float(sims.std(ddof=1))
                p = float(avg[name])
                out.append({"table": t, "row": 0, "label": f"T{t} average", "quantity": name, "paper": p,
                            "rig_run": float(run_means[idx, q].mean()), "rig_mean": m, "rig_sd": s, "diff": p - m,
                            "z": (p - m) / s, "ls": np.nan, "ls_std": np.nan})
        return pd.DataFrame(out)

    def spread(self) -> pd.DataFrame:
        """The paper's spread against the rig's prediction, per table and quantity.

        Table 2: the sample sd of the 10 iterations (the *calibration*); Tables 1, 3, 4:
        the sample sd of the rows' values (each a 10-iteration mean; *predictions*).
        ``rig_median``/``rig_lo``/``rig_hi``: median and 5-95 % range of that sd over
        the replicates; ``ratio`` = paper / rig median; ``percentile`` of the paper's
        sd in the rig's distribution.
        """
        out = []
        j2 = self.table2_index
        for t in (2, 1, 3, 4):
            paper = load_table(t)
            for q, name in enumerate(QUANTITIES):
                p_sd = float(np.std(paper[name].to_numpy(float), ddof=1))
                if t == 2:
                    sims = self.replicates[:, j2, :, q].std(axis=1, ddof=1)
                    run = float(self.run[j2, :, q].std(ddof=1))
                    role = "calibration"
                else:
                    idx = self._index(t)
                    # (two index lists split by a slice would move the row axis first: select in two steps)
                    sims = self.replicates[:, idx][..., q].mean(axis=2).std(axis=1, ddof=1)   # [R]
                    run = float(self.run[idx, :, q].mean(axis=1).std(ddof=1))
                    role = "prediction"
                med = float(np.median(sims))
                out.append({"table": t, "quantity": name, "role": role, "n": len(paper), "paper_sd": p_sd,
                            "rig_run_sd": run, "rig_median": med, "rig_lo": float(np.quantile(sims, 0.05)),
                            "rig_hi": float(np.quantile(sims, 0.95)), "ratio": p_sd / med,
                            "percentile": float(np.mean(sims < p_sd) * 100)})
        return pd.DataFrame(out)

    def noise_calibration(self, prob: float = 0.90) -> dict:
        """The current noise Table 2 calls for: ``sigma_i = sigma_rig * s_paper / s_rig``, with ``s`` the
        per-iteration Eq. 7 gap scatter pooled over both axes (RMS of the two sds).  Eq. 7's gap scatter is
        proportional to the current noise (the 0.1 µm position noise adds under 1 %), so one run at the rig's
        level suffices.  The interval is the chi-square interval of the paper's pooled sd (2 x 9 degrees of
        freedom) combined with the rig's Monte Carlo error."""
        from scipy.stats import chi2

        j2 = self.table2_index
        t2 = load_table(2)
        s_paper = float(np.sqrt(np.mean([np.var(t2[q].to_numpy(float), ddof=1) for q in ("g_v0_um", "g_w0_um")])))
        sims = self.replicates[:, j2, :, 2:4]                     # [R, iterations, 2]
        s_rig = float(np.sqrt(np.mean(np.var(sims, axis=1, ddof=1))))
        dof = 2 * (len(t2) - 1)
        lo, hi = (s_paper * np.sqrt(dof / chi2.ppf([1 - (1 - prob) / 2, (1 - prob) / 2], dof))).tolist()
        scale = self.noise.current / s_rig
        return {"paper_pooled_gap_scatter_um": s_paper, "rig_pooled_gap_scatter_um": s_rig,
                "rig_current_noise_mA": self.noise.current * 1e3, "calibrated_current_noise_mA": s_paper * scale * 1e3,
                "interval_mA": [lo * scale * 1e3, hi * scale * 1e3], "prob": prob, "dof": dof,
                "rig_level_inside": bool(lo * scale <= self.noise.current <= hi * scale)}

    def autocorrelation(self) -> pd.DataFrame:
        """Lag-1 autocorrelation of Table 2's iterations: the paper's against the rig's distribution
        (independent iterations give values near -0.1 with a 5-95 % range of about ±0.5)."""
        j2 = self.table2_index
        t2 = load_table(2)

        def lag1(x):
            x = np.asarray(x, float) - np.mean(x)
            return float(np.sum(x[1:] * x[:-1]) / np.sum(x * x))

        out = []
        for q, name in enumerate(QUANTITIES):
            sims = np.array([lag1(self.replicates[k, j2, :, q]) for k in range(len(self.replicates))])
            p = lag1(t2[name])
            out.append({"quantity": name, "paper": p, "rig_median": float(np.median(sims)),
                        "rig_lo": float(np.quantile(sims, 0.05)), "rig_hi": float(np.quantile(sims, 0.95)),
                        "percentile": float(np.mean(sims < p) * 100)})
        return pd.DataFrame(out)

    def trend(self, first: int = 2) -> pd.DataFrame:
        """Linear trend of Table 2's origins over iterations ``first``..10 (iteration 1 is uncentred):
        the paper's slope [µm per iteration] with its OLS standard error, and the rig's 5-95 % range of the
        same slope for independent iterations.  A drift that runs *during* experiments shows here; one that
        happens *between* experiments does not."""
        j2 = self.table2_index
        t2 = load_table(2)
        sl = slice(first - 1, None)

        def fit(y):
            x = np.arange(len(y), dtype=float)
            a = np.vstack([x, np.ones_like(x)]).T
            c = np.linalg.lstsq(a, y, rcond=None)[0]
            r = y - a @ c
            return float(c[0]), float(np.sqrt(r @ r / (len(y) - 2) / np.sum((x - x.mean()) ** 2)))

        out = []
        for q, name in enumerate(QUANTITIES[:2]):
            y = t2[name].to_numpy(float)[sl]
            slope, se = fit(y)
            sims = np.array([fit(self.replicates[k, j2, sl, q])[0] for k in range(len(self.replicates))])
            out.append({"quantity": name, "iterations": f"{first}-{len(t2)}", "paper_slope": slope, "paper_se": se,
                        "over_experiment": slope * (len(y) - 1), "rig_lo": float(np.quantile(sims, 0.05)),
                        "rig_hi": float(np.quantile(sims, 0.95)), "percentile": float(np.mean(sims < slope) * 100)})
        return pd.DataFrame(out)

    def between_experiment_sd(self) -> pd.DataFrame:
        """The spread between experiments that per-reading noise does not explain, µm:
        ``sqrt(max(s_paper^2 - sd_rig_row^2, 0))`` per table and quantity (a variance component)."""
        sp = self.spread()
        comp = self.comparison()
        out = []
        for r in sp[sp["role"] == "prediction"].itertuples():
            row_sd = float(comp[(comp["table"] == r.table) & (comp["quantity"] == r.quantity)]["rig_sd"].mean())
            out.append({"table": r.table, "quantity": r.quantity, "paper_sd": r.paper_sd, "rig_row_sd": row_sd,
                        "extra_sd": float(np.sqrt(max(r.paper_sd**2 - row_sd**2, 0.0)))})
        return pd.DataFrame(out)


def reproduce(*, replicates: int = 200, seed: int = 0, spec: RigSpec = PAPER_RIG, noise: Noise = Noise(),
              iterations: int = 10, least_squares: bool = True, progress=None, workers: int | None = None,
              scheduler: str | None = None, chunk_size: int | None = None) -> Reproduction:
    """Run every experiment of Tables 1-4 once (the reproduction) and ``replicates`` more times (the prediction).

    Each experiment is the paper's effective-origin search; seeds are drawn from one
    :class:`numpy.random.SeedSequence` (one child per replicate), so the result is reproducible and
    does not depend on where the replicates run: in this process (the default), on ``workers`` local
    processes or on the Dask cluster at ``scheduler`` (:mod:`ambfit.engine`; an enclosing
    ``with ambfit.engine.Engine(...)`` block is used when neither is given), ``chunk_size`` replicates per
    task.  Replicates whose Eq. 7 validity checks reject an iteration are counted in ``failed`` and
    left out.  ``progress``, if given, is called as ``progress(phase, done, total)`` ("experiments",
    "replicates").
    """
    import functools
    import time

    from ambfit import engine

    t0 = time.perf_counter()
    rs = rows()
    ss = np.random.SeedSequence(seed)
    run_seed, *rep_seeds = ss.spawn(1 + replicates)
    run_rngs = run_seed.spawn(len(rs))
    searches = []
    for j, (r, s) in enumerate(zip(rs, run_rngs), 1):
        searches.append(run_row(r, spec=spec, noise=noise, seed=np.random.default_rng(s), iterations=iterations))
        if progress is not None:
            progress("experiments", j, len(rs))
    run = np.stack([iteration_values(s) for s in searches])
    ls_out = []
    if least_squares:
        from ambfit.estimation.fit import FitError, fit
        from ambfit.estimation.units import GAPS, ORIGINS

        for s in searches:
            try:
                res = fit(s.data)
            except FitError:
                ls_out.append(None)
                continue
            ls_out.append({f"{n}_um": (res.value(n) * 1e6, res.error(n) * 1e6) for n in ORIGINS + GAPS})
    else:
        ls_out = [None] * len(rs)
    one = functools.partial(_replicate, rows=tuple(rs), spec=spec, noise=noise, iterations=iterations)
    with engine.using(workers, scheduler) as eng:
        out = eng.map(one, rep_seeds, chunk_size=chunk_size, progress=progress, what="replicates")
    reps = [r for r in out if r is not None]
    failed = len(out) - len(reps)
    if len(reps) < 2:
        raise RuntimeError(f"only {len(reps)} of {replicates} replicates ran; the rig's noise is too large for Eq. 7")
    return Reproduction(rows=rs, run=run, replicates=np.stack(reps), searches=searches, least_squares=ls_out,
                        noise=noise, spec=spec, seconds=time.perf_counter() - t0, failed=failed)


def _replicate(seed: np.random.SeedSequence, *, rows: tuple, spec: RigSpec, noise: Noise,
               iterations: int) -> np.ndarray | None:
    """One replicate of every experiment: per-iteration values, array[rows, iterations, 4] [µm]; None when Eq. 7's
    validity checks reject an iteration of one of them."""
    from ambfit.estimation.closed_form import ClosedFormError

    try:
        return np.stack([iteration_values(run_row(r, spec=spec, noise=noise, seed=np.random.default_rng(s),
                                                  iterations=iterations))
                         for r, s in zip(rows, seed.spawn(len(rows)))])
    except ClosedFormError:
        return None


def fig2_data(seed: int = 7) -> pd.DataFrame:
    """The paper's Fig. 2 setting on the rig: pairs at ±20 µm in sensor coordinates with the rotor left at the
    back-up bearing centre (13.3 and 53.3 µm from the effective origin: not symmetric about it), 10
    repetitions, one unknown load per position (the information Eq. 5-7 use)."""
    from ambfit.rig import protocol as P
    from ambfit.rig.virtual import simulate

    parts = []
    for j, d in enumerate((20e-6, -20e-6)):
        lid = f"pos{j}"
        parts += [P.grid([(d, d)], [1.4, 1.6], load=lid, loads={lid: P.Load.gravity(1.0, known=False)},
                         iteration=i, experiment="fig2") for i in range(1, 11)]
    return simulate(PAPER_RIG, P.concat(*parts), seed=seed).data
