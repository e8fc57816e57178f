"""Force measurement from identified parameters: the paper's stated end goal.

Given a least-squares fit (with known loads, so that ``k`` is identified), the
force its model (Eq. 4 plus the fit's effects) predicts for any currents and position, with a standard error that
propagates the parameters' covariance (delta method) and, optionally, the
measurement noise of the inputs.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ambfit.estimation.core import HEAD_NAMES, Model, Problem, measured, si_scale, to_theta
from ambfit.estimation.fit import FitError, FitResult
from ambfit.estimation.model_file import ModelFileError  # noqa: F401  (raised by FittedModel.from_json)
from ambfit.estimation.units import FORCE_CONSTANTS, GAPS, ORIGINS
from ambfit.physics.bearing import AXES
from ambfit.physics.model import BearingParams, Readings, evaluate


def force(result: FitResult, axis: str, i_top, i_bottom, x, *, y=0.0, sigma_i: float = 0.0,
          sigma_x: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Bearing force [N] and its standard error for given currents [A] and position [m] on one axis.

    The paper's end goal.  The error propagates the covariance of every estimated parameter (effect
    parameters included; delta method) and, if given, the measurement noise of the currents and position.
    Needs ``k`` of that axis, i.e. a fit with known loads.  ``y`` is the other axis' position [m]
    (effects that couple the axes use it).  The same computation as :meth:`FittedModel.force`.
    """
    if axis not in AXES:
        raise ValueError(f"axis must be one of {AXES}, got {axis!r}")
    if f"k_{axis}" not in result.names:
        raise FitError(f"the force on axis {axis} needs k_{axis}, which this fit could not identify "
                       "(no known load on that axis)", result=result)
    shape = np.broadcast(i_top, i_bottom, x, y).shape
    it, ib, xx, yy = (jnp.asarray(np.broadcast_to(v, shape), dtype=float).ravel() for v in (i_top, i_bottom, x, y))
    r = Readings.build(axis=jnp.full(it.shape, AXES.index(axis)), i_top=it, i_bottom=ib, x=xx, y=yy)
    f, s = FittedModel.from_result(result).force(r, sigma_i=sigma_i, sigma_x=sigma_x)
    return f.reshape(shape), s.reshape(shape)


def predict(result: FitResult, data, *, rows: Readings | None = None) -> np.ndarray:
    """The force [N] the fitted model gives for every row of ``data`` (its own axis, both axes' currents),
    at the fit's gap, origin, k and effect parameters.  Rows of an axis whose k was not identified are NaN.
    ``rows``: ``data``'s readings when the caller has them (pairing the axes by time is the slow part)."""
    from ambfit.data import Dataset
    from ambfit.rows import readings

    df = data.frame if isinstance(data, Dataset) else data
    vals = dict(zip(result.names, result.values))
    nominal = result.bearing.nominal_gap
    params = BearingParams(jnp.asarray([vals.get(n, nominal) for n in GAPS]),
                           jnp.asarray([vals.get(n, 0.0) for n in ORIGINS]),
                           jnp.asarray([vals.get(n, np.nan) for n in FORCE_CONSTANTS]))
    return np.asarray(_force(params, readings(df) if rows is None else rows, result.effects, result.bearing))


@eqx.filter_jit
def _force(params, readings, effects, bearing):
    """The model's force at the readings (compiled once per model: force checks predict many times)."""
    return evaluate(params, readings, effects, bearing=bearing)[0]


def force_check(data, effects=(), *, bearing=None, base: FitResult | None = None, max_steps: int = 200,
                discrepancy: bool | tuple = False, fitted=(), each=None, **fit_kw) -> dict | None:
    """Leave-one-load-out force measurement (contract sections 2 and 3, ``force_check``).

    Each distinct known load of an axis in turn is left out, the model (the ideal law plus ``effects``)
    is fitted on the rest, and the force it predicts for the left-out readings is compared with the
    known load: the RMS and the largest of ``(F_predicted - load_N) / load_N`` over all left-out
    readings, and per load.  A load is skipped when leaving it out leaves its axis without a known load
    (k could not be calibrated).  Readings that the fit of every row (``base``) named outliers are left out of
    every refit, which does not test them again.  None when fewer than two distinct known loads exist.

    ``base`` is the fit of all rows with the same model (its estimate starts each refit).  With
    ``discrepancy``, each refit also gets the model-discrepancy term (:mod:`ambfit.estimation.discrepancy`)
    fitted on the rows it saw, the outliers among them, its parameters refitted to those (a tuple of groups: those
    of :mod:`ambfit.estimation.basis`, a family's signature;
    True: the default groups), and the figures of the model with it are under ``"discrepancy"``.  ``fitted`` holds
    refits of ``data``'s rows (in their order) already made with the same model, start and settings, as
    ``(held-out rows mask, FitResult, Discrepancy or None)`` (a diagnosis' cross-validation folds): a load whose
    left-out rows are exactly one of these masks reuses that refit instead of repeating it.  ``each(fn, items)``,
    if given, maps the left-out loads (a diagnosis passes its thread pool; default one after another).

    Besides the contract's per-reading figures, ``rms_rel_mean`` is the RMS over the left-out loads of the
    mean relative error of each load's readings (a force measured by averaging its readings),
    ``noise_floor_rel`` the per-reading figure a perfect model would reach: the RMS of each reading's force
    noise (its effective-variance std) over its load, and ``model_error_rel`` what is left of the per-reading
    RMS beyond that floor, ``sqrt(max(rms_rel^2 - noise_floor_rel^2, 0))`` (the model's own error; the
    readings' noise and the model's error add in quadrature).
    """
    from ambfit.data import Dataset, zero_based
    from ambfit.estimation.core import build_problem
    from ambfit.estimation.fit import fit
    from ambfit.physics.bearing import PAPER_BEARING

    bearing = PAPER_BEARING if bearing is None else bearing
    df = zero_based(data.frame if isinstance(data, Dataset) else data)
    if "load_N" not in df.columns:
        return None
    # a known load of 0 N has no relative error: its rows are left out of the figure (and counted)
    known = (df["load_N"].notna() & (df["load_N"].abs() > 0)).to_numpy()
    zero = int((df["load_N"] == 0).sum())
    keys = df["axis"].astype(str) + ":" + df["load_N"].map(lambda v: f"{v:.9g}")
    groups = list(dict.fromkeys(keys[known]))
    if len(groups) < 2:
        return None
    if base is None:
        base = fit(df, effects, bearing=bearing, max_steps=max_steps, throw=False, **fit_kw)
    keep = base.fitted_rows
    # the readings of the built problem the refits share (pairing the axes by time is the slow part)
    rows = build_problem(df, sigma_i=fit_kw.get("sigma_i"), sigma_x=fit_kw.get("sigma_x"))[0].readings

    def one(g):
        """The left-out load ``g``'s relative errors, noise floor, record (and with the discrepancy's errors)."""
        out = (keys == g).to_numpy() & known
        ax = g.split(":")[0]
        if not (known & ~out & keep & (df["axis"] == ax).to_numpy()).any():
            return None
        res, d = next(((f, d) for held, f, d in fitted if np.array_equal(held, out)), (None, None))
        if res is None:
            # the readings the fit of every row named outliers stay out, not tested again (as a diagnosis' folds)
            res = fit(df, effects, bearing=bearing, mask=(~out & keep).astype(float), start_from=base,
                      max_steps=max_steps, throw=False, **(fit_kw | {"alpha": 0.0}))
        load = df.loc[out, "load_N"].to_numpy(float)
        predicted, noise_n = _at_known_loads(res, df, rows, fit_kw)
        r = (predicted[out] - load) / load          # all rows: the other axis' currents pair by time_s
        floor = noise_n[out] / load
        entry = {"axis": ax, "load_N": float(load[0]), "rows": int(out.sum()),
                 "rms_rel": float(np.sqrt(np.mean(r**2))), "mean_rel": float(np.mean(r)),
                 "converged": bool(res.converged)}
        rd = None
        if discrepancy:
            from ambfit.estimation.discrepancy import fit_discrepancy, seen_rows

            if d is None:
                # on every row the refit could see, its outliers too, as a diagnosis' widened folds are fitted
                d = fit_discrepancy(res, df, sigma_i=fit_kw.get("sigma_i"), sigma_x=fit_kw.get("sigma_x"),
                                    mask=seen_rows(res, ~out).astype(float),
                                    **({"groups": discrepancy} if isinstance(discrepancy, tuple) else {}))
            rd = (predicted[out] + d.row_correction_n[out] - load) / load
            entry |= {"rms_rel_discrepancy": float(np.sqrt(np.mean(rd**2))), "mean_rel_discrepancy": float(np.mean(rd))}
        return r, floor, entry, rd

    done = (each or (lambda fn, items: [fn(x) for x in items]))(one, groups)
    skipped = [g for g, x in zip(groups, done) if x is None]
    kept = [x for x in done if x is not None]
    rel, floor, per_load, rel_d = ([x[j] for x in kept] for j in range(4))
    if not rel:
        return None
    noise = float(np.sqrt(np.mean(np.concatenate(floor) ** 2)))
    out = {"method": "leave-one-load-out", "model": base.model, "n_loads": len(per_load), **_figures(rel, noise),
           "noise_floor_rel": noise, "n_not_converged": sum(not p["converged"] for p in per_load),
           "zero_load_rows": zero, "loads": per_load, "skipped": skipped}
    if discrepancy:
        out["discrepancy"] = {"model": f"{base.model}+discrepancy", **_figures(rel_d, noise)}
    return out


def _at_known_loads(res: FitResult, df, rows, fit_kw: dict) -> tuple[np.ndarray, np.ndarray]:
    """The force [N] ``res`` gives each row of ``df`` with a known load, and its noise std [N] (other rows: any
    number); ``res`` is a fit of ``df``'s rows in their order, with ``fit_kw``.  As its solve measured them at its
    estimate, ``F = load + s z``, unless it held its noise (then predicted and propagated anew, each a compiled
    program of its own)."""
    z, s = res.residuals, res.row_noise
    if fit_kw.get("held_noise") is None and s is not None and np.shape(s) == np.shape(z) == (len(df),):
        return df["load_N"].to_numpy(float) + s * z, s
    return predict(res, df, rows=rows), force_noise(res, df, sigma_i=fit_kw.get("sigma_i"),
                                                    sigma_x=fit_kw.get("sigma_x"))


def _figures(rel: list, noise: float) -> dict:
    """Per-reading RMS and largest relative error, the RMS of the per-load mean errors, and the per-reading RMS
    beyond the readings' ``noise`` (in quadrature)."""
    r = np.concatenate(rel)
    rms = float(np.sqrt(np.mean(r**2)))
    return {"rms_rel": rms, "max_rel": float(np.max(np.abs(r))),
            "rms_rel_mean": float(np.sqrt(np.mean([np.mean(x) ** 2 for x in rel]))),
            "model_error_rel": float(np.sqrt(max(rms**2 - noise**2, 0.0)))}


def force_noise(res: FitResult, df, *, sigma_i: float | None = None, sigma_x: float | None = None) -> np.ndarray:
    """Each row's force noise std [N] under ``res``'s model: the readings' current and position noise (std
    columns, or ``sigma_i`` [A] / ``sigma_x`` [m] as the fit was given them) propagated through it."""
    from ambfit.estimation.core import Model, build_problem, noise_std

    prob, _ = build_problem(df, sigma_i=sigma_i, sigma_x=sigma_x)
    return np.asarray(noise_std(jnp.asarray(res.theta), prob, Model.of(res.effects, res.bearing)))


@dataclasses.dataclass(frozen=True)
class FittedModel:
    """A fitted force model, as ``ambfit identify``/``ambfit diagnose`` write it (``model_state``), ready to
    measure forces: parameters and covariance in SI units, the effects, the bearing.

    :meth:`force` gives the force on each reading's axis and its standard error (delta method over every
    estimated parameter, effect parameters included, plus the readings' own noise if given).
    """

    names: tuple
    values: np.ndarray
    cov: np.ndarray
    effects: tuple
    bearing: object
    model: str
    discrepancy: object = None          # a fitted ambfit.estimation.discrepancy.Discrepancy, added to the force
    file: object = None                 # the ambfit.estimation.model_file.ModelFile it was read from (provenance)
    state: dict | None = dataclasses.field(default=None, repr=False, compare=False)   # the model_state it came from

    def at(self, values) -> FittedModel:
        """This model with its parameters (the effects' included) at ``values`` (in the order of :attr:`names`)."""
        if self.state is None:
            raise ValueError("this model was not built from a model_state (FittedModel.from_state)")
        state = {**self.state, "values": [float(v) for v in values]}
        return dataclasses.replace(type(self).from_state(state, self.bearing), file=self.file)

    @classmethod
    def from_result(cls, result: FitResult) -> FittedModel:
        return cls.from_state(result.model_state(), result.bearing)

    @classmethod
    def from_json(cls, record: dict, bearing, source: str = "<json>", use: str | None = None) -> FittedModel:
        """From an identify JSON (its ``model_state``) or a diagnose JSON.

        ``use`` picks a diagnose JSON's model: ``"verdict"``, ``"discrepancy"`` (the verdict's model, or the
        ideal law when there is none, with the model-discrepancy correction) or ``"ideal"``; default: the
        verdict's model, else the discrepancy model (a verdict ``unexplained``), else the ideal law.

        Every value the force uses is checked first (:mod:`ambfit.estimation.model_file`): a damaged, foreign or
        newer file raises :class:`ModelFileError` naming the file, the key and the value.
        """
        from ambfit.estimation import model_file

        mf = model_file.read(record, source, use)
        model_file.check(mf, bearing)
        return dataclasses.replace(cls.from_state(mf.state, bearing, source), file=mf)

    @classmethod
    def from_state(cls, state: dict, bearing, source: str = "<json>") -> FittedModel:
        from ambfit.physics.effects import effect_by_name

        names, values = list(state["names"]), np.asarray(state["values"], dtype=float)
        cov = np.asarray(state["covariance"], dtype=float)
        if cov.shape != (len(names), len(names)) or len(values) != len(names):
            raise ModelFileError(f"{source}: model_state has {len(names)} names, {len(values)} values and a "
                                 f"{cov.shape} covariance")
        vals = dict(zip(names, values))
        effects = []
        for spec in state.get("effects", []):
            try:
                e = effect_by_name(spec["name"])
            except ValueError as exc:
                raise ModelFileError(f"{source}: {exc}") from None
            for piece in spec.get("off", []):
                e = e.without(piece)
            held = spec.get("held", {})
            # every parameter the file gives: estimated (under its name) or held (an older file may have
            # estimated one that is held now)
            for field in type(e).RANGES:
                shared = f"{spec['name']}.{field}"
                per_axis = [vals.get(f"{shared}[{ax}]") for ax in AXES]
                if shared in vals:
                    e = _set_field(e, field, jnp.full(2, vals[shared]))
                elif all(v is not None for v in per_axis):
                    e = _set_field(e, field, jnp.asarray(per_axis, dtype=float))
                elif field in held:
                    e = _set_field(e, field, jnp.broadcast_to(jnp.asarray(held[field], dtype=float), (2,)))
            effects.append(e)
        model = "+".join(s["name"] for s in state.get("effects", [])) or "ideal"
        disc = None
        if state.get("discrepancy") is not None:
            from ambfit.estimation.discrepancy import Discrepancy

            try:
                disc = Discrepancy.from_json(state["discrepancy"])
            except (KeyError, TypeError, ValueError) as exc:
                raise ModelFileError(f"{source}: the discrepancy term cannot be read ({exc})") from None
            if disc.names != tuple(names):
                raise ModelFileError(f"{source}: the discrepancy refers to parameters {list(disc.names)}, the model "
                                     f"has {names}")
            model += "+discrepancy"
        return cls(names=tuple(names), values=values, cov=cov, effects=tuple(effects), bearing=bearing, model=model,
                   discrepancy=disc, state=state)

    def _model(self) -> tuple[Model, np.ndarray, list[int]]:
        """The core's model of this one (the fields :attr:`names` estimates free, the others held at their values),
        its scaled parameter vector here and the entry of it that each of :attr:`names` is."""
        v = dict(zip(self.names, self.values))
        fields = []                     # (effect, field, one value for both axes) as the file names them
        for i, e in enumerate(self.effects):
            for f in type(e).RANGES:
                name = f"{type(e).name}.{f}"
                if name in v:
                    fields.append((i, f, True))
                elif all(f"{name}[{ax}]" in v for ax in AXES):
                    fields.append((i, f, False))
        model = Model.of(self.effects, self.bearing, tuple(fields))
        nominal = self.bearing.nominal_gap
        head = to_theta([v.get(n, nominal) for n in GAPS], [v.get(n, 0.0) for n in ORIGINS],
                        [v.get(n, np.nan) for n in FORCE_CONSTANTS])
        q = (np.array([v[n] for n in model.names()]) - np.asarray(model.centre)) / np.asarray(model.width)
        layout = list(HEAD_NAMES) + model.names()
        return model, np.concatenate([head, q]), [layout.index(n) for n in self.names]

    def force(self, readings: Readings, *, sigma_i=0.0, sigma_x=0.0, sigma_i_bottom=None):
        """Force [N] on each reading's own axis and its standard error [N].

        ``sigma_i`` (top coil; ``sigma_i_bottom`` for the bottom coil, default the same) [A] and ``sigma_x`` [m]
        are the readings' own noise std, a number or one per reading; they add to the parameters' error.  The
        force, its derivatives with respect to the parameters (delta method) and to the readings (their noise)
        come from the core's one measurement of the model (:func:`ambfit.estimation.core.measured`).
        """
        sigma_i_bottom = sigma_i if sigma_i_bottom is None else sigma_i_bottom
        model, theta, columns = self._model()
        n = readings.x.shape[0]

        def each(value):
            return jnp.broadcast_to(jnp.asarray(value, dtype=float), (n,))

        # every reading a known load of 0 N: F - L is the force, s_eff the readings' noise through it
        prob = Problem(readings=readings, s_top=each(sigma_i), s_bottom=each(sigma_i_bottom), s_x=each(sigma_x),
                       load=jnp.zeros(n), known=jnp.ones(n, dtype=bool), gidx=-jnp.ones(n, dtype=int),
                       k_free=jnp.ones(2, dtype=bool), mask=jnp.ones(n), s_held=jnp.zeros(n))
        f, s, d = (np.asarray(a) for a in measured(jnp.asarray(theta), prob, model))
        jac = d[:, columns] / si_scale(prob, model)[0][columns]          # dF/d(each of names) [N per SI unit]
        val, var = f, np.sum((jac @ self.cov) * jac, axis=1)
        if self.discrepancy is not None:
            # the correction is orthogonal to the parameters: its variance adds (no cross-covariance)
            delta, delta_std = self.discrepancy.correction(readings, jac)
            val, var = val + delta, var + delta_std**2
        return val, np.sqrt(var + s**2)


def _set_field(effect, field, value):
    return eqx.tree_at(lambda e: getattr(e, field), effect, value)
