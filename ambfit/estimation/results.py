"""The least-squares result: estimates in SI units, health as named properties, and its faces.

Health follows iminuit's ``FMin``: each property is a yes/no answer and
:meth:`FitResult.health` gives the cause and the fix in words.

``converged``
    The estimated distance to the minimum is below ``EDM_MAX``.
``well_conditioned``
    The column-scaled Jacobian's condition number is below the threshold and every
    gap is known to better than the relative threshold.
``k_identified``
    Each present axis has a known load, so its force constant is calibrated (``k_by_axis`` per axis).
``adequate``
    χ² is consistent with the noise levels (p-value at least ``p_min``); ``None`` when
    the noise was estimated from the residuals, which makes χ²/dof 1 by construction.
``effects_identified``
    The data determine every effect parameter (:func:`ambfit.estimation.identification.prior_shares`);
    ``None`` when not measured.  Raised before non-convergence: an unseen effect makes the solver wander.
"""

from __future__ import annotations

import dataclasses
import html
import math
from collections.abc import Sequence

import numpy as np

from ambfit.estimation.units import CONTRACT_PARAMS, DISPLAY, GAPS, GEOMETRY, HEAD, display, si_unit, with_unit
from ambfit.physics.bearing import AXES, Bearing


@dataclasses.dataclass(frozen=True)
class Thresholds:
    """What counts as healthy (the keyword arguments of :func:`ambfit.fit`)."""

    max_condition: float = 1e8
    max_relative_gap_std: float = 0.1
    p_min: float = 1e-3
    max_steps: int = 200


@dataclasses.dataclass(frozen=True)
class FitResult:
    """Least-squares estimates with uncertainties and fit health (SI units).

    Attributes
    ----------
    names : list[str]
        Estimated parameters: ``g_v0``, ``g_w0``, ``v0``, ``w0``, ``k_v``/``k_w`` where
        known loads make them identifiable, ``load[<group>]`` nuisances [N], then the
        effect parameters ``effect.field[axis]``.
    values, std : array[p]
    cov, corr : array[p, p]
    chi2, dof :
        Sum of squared standardized residuals of the fitted rows and its degrees of freedom.
    residuals : array[n]
        Standardized residuals ``(F - L) / s_eff`` of every row, in file order (held-out rows too).
    edm : float
        Estimated distance to the minimum at the estimate.
    condition : float
        Condition number of the column-scaled Jacobian.
    weak_direction : str
        The least determined combination, in words.
    noise_source : str
        Where the noise levels came from; when estimated, ``cov`` is scaled by the reduced χ².
    effects : tuple of Effect
        The model's effects at their fitted values (empty for the ideal law).
    model : str
        ``ideal`` or the effect names joined by ``+``.
    theta : array
        The scaled parameter vector (:mod:`ambfit.estimation.core`).
    bias_correction : dict or None
        What was subtracted from the least-squares minimum to give ``values`` and ``theta`` (SI, per parameter:
        ``{"method": "second-order" | "bootstrap", name: {"subtracted": ...}}``, or ``{"method": "second-order",
        "skipped": why}`` where the correction does not apply and the estimate is the plain one); the other fields are
        measured
        at the corrected estimate, but for the solve's record (``edm``, ``num_steps``, ``optimistix``) and the
        outlier test, which are the minimum's.  None: the plain estimate.
    """

    names: list
    values: np.ndarray
    std: np.ndarray
    cov: np.ndarray
    corr: np.ndarray
    chi2: float
    dof: int
    residuals: np.ndarray
    edm: float
    optimistix: str
    num_steps: int
    condition: float
    weak_direction: str
    noise_source: str
    noise_estimated: bool
    start: str
    k_free: tuple
    n_rows: int
    n_fit_rows: int
    effects: tuple
    model: str
    bearing: Bearing
    theta: np.ndarray
    thresholds: Thresholds = Thresholds()
    bias_correction: dict | None = None
    loss: str = "linear"
    weights: np.ndarray | None = None
    rows: np.ndarray | None = None
    outliers: tuple = ()
    outlier_note: str = ""
    jacobian_rows: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)
    """Jacobian of every row's standardized residual (weight 1, held-out rows too) at ``theta``, free columns
    (what the outlier test's leverages need; measured with the solve)."""
    row_noise: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)
    """Effective noise std ``s_eff`` [N] of every row (held-out rows too) at ``theta``, measured with the solve: the
    unit of :attr:`residuals` (what the discrepancy's basis is standardized by)."""
    plain_shift: dict | None = None
    implausible: tuple = ()
    effect_identification: dict | None = None     # {effect parameter: share of its prior's variance left}

    # --- values ---------------------------------------------------------------------------------------------

    def value(self, name: str) -> float:
        """Estimate of ``name`` in SI units (:attr:`units`: gaps and origins in m, ``k`` in N·m²/A²).

        The contract JSON (:meth:`contract_params`) and the printed tables give gaps and origins in µm.
        """
        return float(self.values[self.names.index(name)])

    def error(self, name: str) -> float:
        """Standard error of ``name`` in SI units (:attr:`units`)."""
        return float(self.std[self.names.index(name)])

    @property
    def units(self) -> dict:
        """The unit of each parameter's :meth:`value` and :meth:`error`: ``{"g_v0": "m", "k_v": "N·m²/A²", ...}``."""
        return {n: si_unit(n) for n in self.names}

    @property
    def row_weights(self) -> np.ndarray:
        """Each row's weight in the fit: 1 for every row when no weights were recorded."""
        if self.weights is None:
            return np.ones(len(self.residuals))
        return np.asarray(self.weights, dtype=float)

    @property
    def fitted_rows(self) -> np.ndarray:
        """Which rows the fit used (bool per row): weight above 0; every row when no weights were recorded."""
        return self.row_weights > 0

    @property
    def reduced_chi2(self) -> float:
        return self.chi2 / max(self.dof, 1)

    @property
    def p_value(self) -> float:
        """Probability of a χ² at least this large if the model and the noise levels were right."""
        from scipy.special import chdtrc

        return float(chdtrc(self.dof, self.chi2))

    # --- health ---------------------------------------------------------------------------------------------

    @property
    def converged(self) -> bool:
        from ambfit.estimation.core import EDM_MAX

        return bool(self.edm < EDM_MAX)

    @property
    def relative_gap_std(self) -> float:
        rel = [self.error(n) / self.value(n) for n in GAPS if n in self.names]
        return max(rel) if rel else 0.0

    @property
    def well_conditioned(self) -> bool:
        t = self.thresholds
        return bool(self.condition < t.max_condition and self.relative_gap_std < t.max_relative_gap_std)

    @property
    def k_by_axis(self) -> dict:
        """``{"v": bool, "w": bool}``: whether each axis' force constant is calibrated by known loads."""
        return {ax: bool(self.k_free[a]) for a, ax in enumerate(AXES)}

    @property
    def k_identified(self) -> bool:
        """Every axis in the data has a known load, so its force constant is calibrated (force measurement works)."""
        present = {n[2] for n in self.names if n in GAPS}
        return all(self.k_by_axis[ax] for ax in present)

    @property
    def adequate(self) -> bool | None:
        """χ² consistent with the noise (p-value >= ``p_min``); None when the noise was estimated."""
        if self.noise_estimated:
            return None
        return bool(self.p_value >= self.thresholds.p_min)

    @property
    def chi2_lower_p(self) -> float:
        """Probability of a χ² at most this large if the model and the noise levels were right."""
        from scipy.special import chdtr

        return float(chdtr(self.dof, self.chi2))

    @property
    def noise_as_declared(self) -> bool | None:
        """χ² not improbably small for the declared noise (lower-tail p-value >= ``p_min``): std columns twice or
        ten times the real noise give χ²/dof 0.25 or 0.01, every error bar as many times too wide; None when the
        noise was estimated."""
        if self.noise_estimated or self.dof < 1:
            return None
        return bool(self.chi2_lower_p >= self.thresholds.p_min)

    def checks(self) -> list[tuple[str, bool | None, str]]:
        """Every health check as ``(name, passed, cause and fix)``; ``passed`` is None when it cannot be judged."""
        from ambfit.estimation.convergence import not_converged
        from ambfit.estimation.core import EDM_MAX
        from ambfit.estimation.identification import undetermined_text

        rel = self.relative_gap_std
        why = (f"condition number {self.condition:.3g} of the scaled Jacobian" if not
               self.condition < self.thresholds.max_condition else f"a gap has a relative standard error of {rel:.2g}")
        law = "the ideal law" if self.model == "ideal" else f"the model ({self.model})"
        missing = [ax for ax, ok in self.k_by_axis.items() if not ok and f"g_{ax}0" in self.names]
        unseen = undetermined_text(self.effect_identification or {})
        return [
            ("well_conditioned", self.well_conditioned,
             f"the design does not identify the parameters: {why}; {self.weak_direction}. Use two or more positions "
             "(the paper's symmetric pairs) and two or more biases"),
            ("effects_identified", None if self.effect_identification is None else not unseen, unseen),
            ("converged", self.converged, not_converged(self, EDM_MAX)),
            ("adequate", self.adequate,
             f"{law} does not fit these data, χ²/dof {self.reduced_chi2:.3g} on {self.dof} dof "
             f"(p = {self.p_value:.2g}); the estimates' errors assume it does; run ambfit diagnose"),
            ("noise_as_declared", self.noise_as_declared,
             f"χ²/dof {self.reduced_chi2:.3g} on {self.dof} dof is improbably small for the declared noise (p = "
             f"{self.chi2_lower_p:.2g} of a χ² this small): the std columns or --current-noise-ma/--position-noise-um "
             f"overstate the noise about {1 / math.sqrt(max(self.reduced_chi2, 1e-12)):.2g}-fold, and every error "
             "bar with it; give the real noise (or leave it out to estimate it from the residuals)"),
            ("plausible", not self.implausible, "; ".join(map(str, self.implausible)) +
             " (ambfit identify exits 3 unless --accept-implausible)"),
            ("no_outliers", not self.outliers, self._outlier_text()),
            ("k_identified", self.k_identified,
             f"k_{' and k_'.join(missing)} not identified: no known load on axis {' and '.join(missing)}; hang known "
             "masses to calibrate it (gap and origin do not need it, force measurement does)"),
        ]

    @property
    def plausible(self) -> bool:
        """No estimate is ruled out by the bearing description (:mod:`ambfit.estimation.plausibility`)."""
        return not self.implausible

    def _outlier_text(self) -> str:
        if not self.outliers:
            return ""
        kept = self.loss == "linear"
        text = (f"{len(self.outliers)} reading(s) beyond the outlier bound"
                f"{', kept in the fit (loss linear)' if kept else ', left out of the fit'}: "
                + "; ".join(map(str, self.outliers[:5])) + (" ..." if len(self.outliers) > 5 else ""))
        if self.plain_shift:
            n, d = max(self.plain_shift.items(), key=lambda kv: abs(kv[1]))
            text += f". With them, {n} would move by {d:+.1f} standard errors"
        return text

    def health(self, *, include_k: bool = False) -> list[str]:
        """Every failed health check as a sentence with its likely cause and the fix (empty when healthy).

        A missing force constant is a property of the design, not a failure of the fit: listed only with
        ``include_k`` (:meth:`notes` always says it).
        """
        return [text for name, ok, text in self.checks() if ok is False and (include_k or name != "k_identified")]

    def raise_for_health(self) -> None:
        """Raise :class:`ambfit.FitError`, carrying this result, when the fit is not identifiable or not converged
        (adequacy is reported, not raised: an inadequate model still has estimates worth reading)."""
        from ambfit.estimation.core import FitError

        for name, ok, text in self.checks():
            if name in ("well_conditioned", "converged") and not ok:
                raise FitError(text, result=self)
            if name == "effects_identified" and ok is False and not self.converged:   # the cause of the failure
                raise FitError(text, result=self)

    def goodness_of_fit(self) -> dict:
        """Contract section 2's ``goodness_of_fit`` record."""
        return {"reduced_chi2": self.reduced_chi2, "dof": self.dof, "p_value": self.p_value,
                "adequate": self.adequate, "p_min": self.thresholds.p_min}

    # --- faces ----------------------------------------------------------------------------------------------

    def contract_params(self) -> dict:
        """Contract section 2 parameter block (µm, N m²/A²)."""
        return {key: {"value": self.value(name) * f, "std": self.error(name) * f}
                for name, key, f in CONTRACT_PARAMS if name in self.names}

    def to_json(self) -> dict:
        """The contract record (section 2) plus fit health, marked as an identify model file
        (:func:`ambfit.estimation.model_file.stamp`: schema, kind, ambfit version)."""
        from ambfit.estimation.model_file import stamp

        head = [n for n in self.names if not n.startswith("load[")]
        with np.errstate(invalid="ignore"):
            corr = {f"{a}|{b}": float(self.corr[self.names.index(a), self.names.index(b)])
                    for i, a in enumerate(head) for b in head[i + 1:]}
        return stamp({
            "method": "least_squares", "model": self.model, "params": self.contract_params(),
            "converged": self.converged, "n_rows": self.n_rows, "goodness_of_fit": self.goodness_of_fit(),
            "well_conditioned": self.well_conditioned, "health": self.health(),
            "reduced_chi2": self.reduced_chi2, "dof": self.dof, "condition": self.condition,
            "weak_direction": self.weak_direction, "noise_source": self.noise_source, "start": self.start,
            "k_identified": self.k_by_axis, "correlations": corr,
            "effect_params": {n: {"value": self.value(n), "std": self.error(n)} for n in self.names if "." in n},
            "nuisance_loads_N": {n[5:-1]: {"value": self.value(n), "std": self.error(n)}
                                 for n in self.names if n.startswith("load[")},
            "bias_correction": self.bias_correction,
            "model_state": self.model_state(),
            "loss": self.loss, "outliers": [o.to_json() for o in self.outliers],
            "outlier_shift_sigma": self.plain_shift, "implausible": [f.to_json() for f in self.implausible],
        }, "identify")

    def model_state(self) -> dict:
        """Everything ``ambfit force`` needs to predict forces with errors from this fit, in SI units: the
        estimated parameters and their covariance, the model's effects (name, switched-off pieces), and the
        bearing description it was fitted with (what a reader judges the values against)."""
        keep = [j for j, n in enumerate(self.names) if not n.startswith("load[")]
        return {"names": [self.names[j] for j in keep], "values": [float(self.values[j]) for j in keep],
                "covariance": [[float(self.cov[i, j]) for j in keep] for i in keep],
                "effects": [{"name": type(e).name, "off": list(getattr(e, "off", ())), "held": _held_fields(e)}
                            for e in self.effects],
                "bearing": self.bearing.name, "bearing_description": self.bearing.to_dict(),
                "units": "SI (m, N·m²/A², effect parameters as named)"}

    def to_dataframe(self):
        """One row per estimated parameter: name, value and std in SI and in the display unit."""
        import pandas as pd

        rows = []
        for n, v, s in zip(self.names, self.values, self.std):
            dv, unit = display(n, v)
            rows.append({"parameter": n, "value": v, "std": s, "display_value": dv,
                         "display_std": display(n, s)[0], "display_unit": unit})
        return pd.DataFrame(rows)

    def _rows(self):
        for n in self.names:
            if n.startswith("load["):
                continue
            yield n, *with_unit(n, self.value(n), self.error(n))

    def display_row(self) -> dict:
        """The head parameters as ``{"g_v0 [µm]": "774.5 ± 1.4", ...}`` plus χ²/dof (one table row)."""
        shown = {n: v for n, v, _ in self._rows()}
        row = {f"{n} [{DISPLAY[n][0]}]": shown.get(n, "–") for n in HEAD}
        row["χ²/dof"] = f"{self.reduced_chi2:.2f}"
        return row

    def notes(self) -> list[str]:
        """What a reader of the estimates should know besides the numbers: noise, start, conditioning, k."""
        out = [f"noise: {self.noise_source}; start: {self.start}; condition {self.condition:.3g}; {self.weak_direction}"]
        if self.bias_correction:
            bc = self.bias_correction
            if bc.get("skipped"):
                out.append(f"second-order bias not subtracted: {bc['skipped']}")
            elif bc.get("method") == "second-order":
                out.append("second-order bias subtracted (µm): " + ", ".join(
                    f"{n} {bc[n]['subtracted'] * 1e6:+.3f}" for n in GEOMETRY if n in bc))
            else:
                out.append("bias correction subtracted (µm): " + ", ".join(
                    f"{n} {bc[n]['subtracted'] * 1e6:+.3f} ± {bc[n]['mc_error'] * 1e6:.3f}" for n in GEOMETRY if n in bc)
                    + f" ({bc['n']} synthetic sets)")
        out += [f"k_{ax} not identified: no known load on axis {ax} (gap and origin do not need it)"
                for ax, ok in self.k_by_axis.items() if not ok]
        if self.outlier_note:
            out.append(self.outlier_note)
        return out

    def summary(self) -> str:
        """A short text summary: estimates in display units, χ², health."""
        lines = [f"least squares ({self.model}), {self.n_rows} rows, χ²/dof {self.reduced_chi2:.3g} on {self.dof} dof"]
        lines += [f"  {n:<24} {v} {u}" for n, v, u in self._rows()]
        lines += [f"  ! {h}" for h in self.health()] or [f"  healthy: {self._healthy()}"]
        return "\n".join(lines)

    def _healthy(self) -> str:
        """What a fit with no failed health check has passed: converged and well conditioned, and whether its fit to the
        readings was judged (not when the noise was estimated from them) and its ``k`` determined."""
        checks = {name: (ok, text) for name, ok, text in self.checks()}
        words = ["converged", "well conditioned"]
        words.append("fits its readings" if checks["adequate"][0] else "its fit to the readings not judged (the noise "
                     "estimated from them)")
        if checks["k_identified"][0] is False:
            words.append(checks["k_identified"][1].split(":")[0])
        return ", ".join(words)

    __str__ = summary

    def __repr__(self) -> str:
        est = ", ".join(f"{n}={v}" for n, v, _ in list(self._rows())[:4])
        return f"FitResult(model={self.model!r}, {est}, converged={self.converged})"

    def _repr_html_(self) -> str:
        rows = "".join(f"<tr><td>{html.escape(n)}</td><td>{html.escape(v)}</td><td>{html.escape(u)}</td></tr>"
                       for n, v, u in self._rows())
        health = "".join(f"<li>{html.escape(h)}</li>" for h in self.health()) or "<li>healthy</li>"
        return (f"<b>least squares ({html.escape(self.model)})</b>, {self.n_rows} rows, "
                f"χ²/dof {self.reduced_chi2:.3g} on {self.dof} dof"
                f"<table><tr><th>parameter</th><th>estimate</th><th>unit</th></tr>{rows}</table><ul>{health}</ul>")


def _held_fields(effect) -> dict:
    """The values of an effect's parameters that were held, not fitted (``RANGES`` fields outside ``ranges()``),
    as plain lists: what a model file needs besides the estimates to give the same forces."""
    return {f: np.asarray(getattr(effect, f), dtype=float).tolist() for f in type(effect).RANGES
            if f not in effect.ranges()}


def table(results: Sequence):
    """Many fits as one table (a study's estimates): a row per fit of :func:`ambfit.estimation.fit.fit_many`, with
    each parameter's value and ``<name>_std`` [SI], ``converged``, ``chi2``, ``dof`` and ``num_steps``; a data set
    whose fit raised has NaN estimates and its message in ``error``."""
    import pandas as pd

    rows = []
    for res in results:
        if isinstance(res, BaseException):
            rows.append({"error": str(res), "converged": False})
            continue
        row = dict(zip(res.names, res.values))
        row.update({f"{n}_std": s for n, s in zip(res.names, res.std)})
        row.update(converged=res.converged, chi2=res.chi2, dof=res.dof, num_steps=res.num_steps, error="")
        rows.append(row)
    return pd.DataFrame(rows)
