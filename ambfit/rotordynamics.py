"""The identified bearing in a rotor model: its linearised coefficients and a ROSS bearing element.

A rotordynamic model sees an active magnetic bearing through two numbers per axis at the operating point: the
current gain ``k_i = ∂F/∂i`` [N/A] (the control current ``i`` drives the top coil at ``bias + i`` and the bottom
coil at ``bias - i``) and the position stiffness ``k_s = ∂F/∂x`` [N/m] (positive: the force grows towards the
nearer pole, the bearing's negative stiffness).  :func:`linearise` takes both from an identified model (a
least-squares fit, a model file of ``ambfit identify``/``ambfit diagnose``, or a posterior), effects included:
saturation lowers both, and the ideal law's Eq. 4 knows nothing of it.  Both are the bearing's, per physical ampere
and metre: the effects of the sensors and current channels a model fits (a position gain, a current zero) are the
measurement's, and belong in the controller's ``k_sense`` and ``k_amp``, not in the bearing.  Their uncertainty comes
from the parameters' (draws from the fit's covariance, or the posterior's own draws).  (Schweitzer and Maslen,
*Magnetic Bearings*, Springer 2009, pp. 69-80: the linearised actuator, which ROSS follows.)

With a controller (``C(s) = kp + ki/s + kd s / (1 + s / n_f)``, amplifier and sensor gains) the bearing acts as
``k_eq(ω) = -k_s + k_i k_amp k_sense Re C(jω)`` and ``c_eq(ω) = k_i k_amp k_sense Im C(jω) / ω`` on each axis,
the convention of ROSS's ``MagneticBearingElement`` (whose ``ks`` is ``-k_s``).  :func:`bearing_element` builds a
ROSS ``BearingElement`` from them (the optional extra ``ambfit[ross]``; ROSS is imported there and nowhere else).

Example
-------
>>> from ambfit.rig import protocol, virtual as rig
>>> from ambfit.estimation.fit import fit
>>> data = rig.simulate(rig.PAPER_RIG, protocol.paper_table2(center=(-33.3e-6, 11.3e-6)), seed=1).data
>>> lin = linearise(fit(data), "v", 1.5)
>>> round(lin.k_i, 1), round(lin.k_s, -2)                   # N/A, N/m on the paper's rig at 1.5 A
(34.6, 61900.0)
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ambfit.physics.bearing import AXES

DRAWS = 400
"""Parameter draws behind each coefficient's uncertainty (a relative error of the sd near 1 / sqrt(2 x 400))."""


@dataclasses.dataclass(frozen=True)
class Linearisation:
    """The bearing on one axis linearised at a bias [A] and ``position`` [m, sensor coordinates]: ``k_i`` [N/A],
    ``k_s`` [N/m], their standard errors and covariance ``cov`` (``[[var k_i, cov], [cov, var k_s]]``), the model
    they come from."""

    axis: str
    bias_A: float
    position: float
    k_i: float
    k_s: float
    cov: np.ndarray
    model: str
    draws: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)
    """``(k_i, k_s)`` at each parameter draw behind ``cov``, array[draws, 2]: one axis' draws and the other's, made
    with the same ``seed``, come from the same parameter draws."""

    @property
    def k_i_std(self) -> float:
        return float(np.sqrt(self.cov[0, 0]))

    @property
    def k_s_std(self) -> float:
        return float(np.sqrt(self.cov[1, 1]))

    def coefficients(self, frequency, *, kp: float, kd: float = 0.0, ki: float = 0.0, n_f: float = 10_000.0,
                     k_amp: float = 1.0, k_sense: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Equivalent stiffness [N/m] and damping [N s/m] of the closed loop at ``frequency`` [rad/s]: the PID
        with a filtered derivative of ROSS's ``MagneticBearingElement`` (gains in its units)."""
        w = np.asarray(frequency, dtype=float)
        s = 1j * w
        c = kp + ki / s + kd * s / (1 + s / n_f)
        gain = self.k_i * k_amp * k_sense
        return -self.k_s + gain * c.real, gain * c.imag / w

    def draw(self, j: int) -> Linearisation:
        """The linearisation at parameter draw ``j`` (no uncertainty of its own)."""
        return dataclasses.replace(self, k_i=float(self.draws[j, 0]), k_s=float(self.draws[j, 1]),
                                   cov=np.zeros((2, 2)), draws=None)

    @property
    def correlation(self) -> float | None:
        """Correlation of ``k_i`` and ``k_s`` (None without uncertainty)."""
        if not (self.cov[0, 0] > 0 and self.cov[1, 1] > 0):
            return None
        return float(self.cov[0, 1] / np.sqrt(self.cov[0, 0] * self.cov[1, 1]))

    def display_row(self) -> dict:
        """One ``{column: text}`` row: axis, bias, where, ``k_i`` and ``k_s`` with their errors, correlation."""
        from ambfit.estimation.units import pm

        corr = self.correlation
        return {"axis": self.axis, "bias [A]": f"{self.bias_A:g}",
                "at sensor reading [µm]": f"{self.position * 1e6:.2f}",       # (the bearing centre is -origin)
                "k_i [N/A]": pm(self.k_i, self.k_i_std, 2), "k_s [N/m]": pm(self.k_s, self.k_s_std, 2),
                "corr": "–" if corr is None else f"{corr:+.2f}"}

    def to_json(self) -> dict:
        return {"axis": self.axis, "bias_A": self.bias_A, "position_um": self.position * 1e6, "model": self.model,
                "k_i_N_per_A": self.k_i, "k_i_std": self.k_i_std, "k_s_N_per_m": self.k_s, "k_s_std": self.k_s_std,
                "correlation": self.correlation}


@eqx.filter_jit
def _gains(params, effects, bearing, axis: int, bias, x, y):
    """``(k_i, k_s)`` of the model at one operating point: derivatives of its force by autodiff."""
    from ambfit.physics.model import Readings, evaluate

    def force(i_c, xx):
        r = Readings.build(axis=jnp.array([axis]), i_top=jnp.array([bias + i_c]), i_bottom=jnp.array([bias - i_c]),
                           x=jnp.array([xx]), y=jnp.array([y]), bias=jnp.array([bias]),
                           i_top_other=jnp.array([bias]), i_bottom_other=jnp.array([bias]))
        return evaluate(params, r, effects, bearing=bearing, physical=True)[0][0]

    return jnp.stack(jax.grad(force, argnums=(0, 1))(0.0, x))


def _model_of(model):
    """A :class:`~ambfit.estimation.measure.FittedModel` of a fit, a model file's record, or itself; None for a
    posterior (its draws are used instead)."""
    from ambfit.estimation.bayes import Posterior
    from ambfit.estimation.measure import FittedModel
    from ambfit.estimation.results import FitResult

    if isinstance(model, FittedModel):
        return model
    if isinstance(model, FitResult):
        return FittedModel.from_result(model)
    if isinstance(model, Posterior):
        return None
    raise TypeError(f"linearise needs a FitResult, a FittedModel or a Posterior, not {type(model).__name__}")


def _head(values: dict, bearing):
    from ambfit.estimation.units import FORCE_CONSTANTS, GAPS, ORIGINS
    from ambfit.physics.model import BearingParams

    return BearingParams(jnp.asarray([values.get(n, bearing.nominal_gap) for n in GAPS]),
                         jnp.asarray([values.get(n, 0.0) for n in ORIGINS]),
                         jnp.asarray([values.get(n, np.nan) for n in FORCE_CONSTANTS]))


def linearise(model, axis: str, bias_A: float, *, position: float | None = None, draws: int = DRAWS,
              seed: int = 0) -> Linearisation:
    """``k_i`` and ``k_s`` of ``axis`` at bias ``bias_A`` [A], from an identified model with its effects.

    ``model``: a :class:`~ambfit.estimation.results.FitResult`, a :class:`~ambfit.estimation.measure.FittedModel`
    (``FittedModel.from_json`` of an identify or diagnose JSON) or a :class:`~ambfit.estimation.bayes.Posterior`.
    ``position``: where on the axis [m, sensor coordinates]; default the bearing centre, ``-origin`` (the
    other axis at its centre too).  The values are the model's at its estimate (a posterior's: at its mean); the
    covariance is that of ``draws`` evaluations at parameters drawn from the fit's covariance (or at the
    posterior's draws).  Needs ``k`` of the axis (known loads).
    """
    from ambfit.estimation.measure import FittedModel

    if axis not in AXES:
        raise ValueError(f"axis must be one of {AXES}, got {axis!r}")
    if not bias_A > 0:
        raise ValueError(f"bias_A must be positive, got {bias_A!r}")
    fm = _model_of(model)
    rng = np.random.default_rng(seed)
    if fm is None:                                      # a posterior: the ideal law at its mean, and its draws
        names = list(model.names)
        flat = model.draws.reshape(-1, len(names))
        sample = flat[rng.choice(len(flat), size=min(draws, len(flat)), replace=False)]
        base = FittedModel(names=tuple(names), values=flat.mean(axis=0), cov=np.cov(flat.T), effects=(),
                           bearing=model.ls.bearing, model="ideal")
        effects_of = None
    else:
        base, names = fm, list(fm.names)
        sample = rng.multivariate_normal(fm.values, fm.cov, size=draws, method="eigh") if draws else np.empty((0,))
        effects_of = fm.at if fm.effects else None
    if f"k_{axis}" not in names:
        raise ValueError(f"k_{axis} is not identified by this model (no known load on axis {axis}): the force, "
                         "and so k_i and k_s, are known only up to that factor")
    other = AXES[1 - AXES.index(axis)]
    values = dict(zip(names, base.values))
    x = -values.get(f"{axis}0", 0.0) if position is None else float(position)
    y = -values.get(f"{other}0", 0.0)
    a = AXES.index(axis)

    def at(fitted):
        v = dict(zip(names, fitted.values))
        return np.asarray(_gains(_head(v, fitted.bearing), fitted.effects, fitted.bearing, a, float(bias_A), x, y))

    k = at(base)
    if len(sample):
        ks = np.array([at(effects_of(row) if effects_of else dataclasses.replace(base, values=row))
                       for row in sample])
        cov = np.cov(ks.T)
    else:
        ks, cov = None, np.zeros((2, 2))
    return Linearisation(axis=axis, bias_A=float(bias_A), position=float(x), k_i=float(k[0]), k_s=float(k[1]),
                         cov=cov, model=base.model.removesuffix("+discrepancy"), draws=ks)


@contextlib.contextmanager
def _quiet():
    """Whatever a library prints while it is imported (ROSS announces a missing REFPROP on stdout) kept out of
    ambfit's output: Python's streams and the file descriptors under them."""
    saved = [os.dup(1), os.dup(2)]
    try:
        with open(os.devnull, "w") as null, contextlib.redirect_stdout(io.StringIO()), \
                contextlib.redirect_stderr(io.StringIO()):
            os.dup2(null.fileno(), 1)
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in saved:
            os.close(fd)


EXTRA = "pip install 'ambfit[ross]'"


def ross():
    """The ``ross`` module, imported quietly; ImportError naming the extra when it is not installed."""
    try:
        with _quiet():
            import ross as rs
    except ImportError as exc:
        raise ImportError(f"the rotor model needs ROSS (ross-rotordynamics), which is not installed ({EXTRA})") \
            from exc
    return rs


def bearing_element(v: Linearisation, w: Linearisation, n: int, *, kp: float, kd: float = 0.0, ki: float = 0.0,
                    n_f: float = 10_000.0, k_amp: float = 1.0, k_sense: float = 1.0, frequency=None,
                    sensors_axis_rotation: float = np.pi / 4, tag: str | None = None, **kwargs):
    """A ROSS ``BearingElement`` at node ``n`` with the identified bearing's closed-loop coefficients.

    ``v`` and ``w``: :func:`linearise` of each axis; the controller gains as ROSS's ``MagneticBearingElement``
    takes them (one controller for both axes).  Each axis' coefficients (:meth:`Linearisation.coefficients`)
    are rotated from the bearing's v-w axes into the rotor's x-y by ``sensors_axis_rotation`` ``θ`` as ROSS does
    (``K_xy = R^T diag(k_v, k_w) R``, ``R = [[cos θ, sin θ], [-sin θ, cos θ]]``): the v axis points along
    ``(cos θ, sin θ)`` in x-y, the w axis along ``(-sin θ, cos θ)`` (θ = 45°: the axes at ±45° to x).  ``frequency`` [rad/s]: where the coefficients are given (default
    ROSS's 1-10⁴ rad/s, 50 points).  ``kwargs`` go to ``BearingElement``.
    """
    rs = ross()
    omega = np.logspace(0, 4) if frequency is None else np.asarray(frequency, dtype=float)
    gains = dict(kp=kp, kd=kd, ki=ki, n_f=n_f, k_amp=k_amp, k_sense=k_sense)
    (kv, cv), (kw, cw) = v.coefficients(omega, **gains), w.coefficients(omega, **gains)
    c, s = np.cos(sensors_axis_rotation), np.sin(sensors_axis_rotation)
    r = np.array([[c, s], [-s, c]])
    inv = np.linalg.inv(r)
    kk = np.array([inv @ np.diag([a, b]) @ r for a, b in zip(kv, kw)])
    cc = np.array([inv @ np.diag([a, b]) @ r for a, b in zip(cv, cw)])
    return rs.BearingElement(n=n, frequency=omega, kxx=kk[:, 0, 0], kxy=kk[:, 0, 1], kyx=kk[:, 1, 0],
                             kyy=kk[:, 1, 1], cxx=cc[:, 0, 0], cxy=cc[:, 0, 1], cyx=cc[:, 1, 0], cyy=cc[:, 1, 1],
                             tag=tag, **kwargs)
