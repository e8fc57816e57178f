# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 06 · The identified bearing in a rotor model (ROSS)
#
# A rotordynamicist does not need the bearing's gap and origin: she needs its current gain `k_i` [N/A] and
# position stiffness `k_s` [N/m] at the operating bias, with their uncertainty, in her rotor model.  Here a rig
# whose iron saturates is swept over four biases; the ideal law and the model with saturation are fitted; each
# is linearised at the operating bias (`ambfit.rotordynamics.linearise`, autodiff of the fitted force model,
# effects included); two identified bearings carry a small rotor in ROSS, and its Campbell diagram is drawn
# with bands from parameter draws (the posterior's for the ideal law, the fit's covariance for the saturating
# model).  Needs the optional extra: `pip install -e '.[ross]'`.

# %%
import os
import warnings

import matplotlib.pyplot as plt
import numpy as np

from ambfit import rig
from ambfit.estimation import bayes
from ambfit.estimation.fit import fit
from ambfit.physics.effects import Saturation
from ambfit.rig import protocol as P
from ambfit.rotordynamics import bearing_element, linearise, ross

FAST = os.environ.get("AMBFIT_FAST", "1") != "0"
rs = ross()                     # imported quietly (ROSS announces a missing REFPROP on import)

# %% [markdown]
# ## Identify: a bias sweep on a saturating rig

# %%
spec = rig.PAPER_RIG
data = rig.simulate(spec, P.rich(center=spec.centre), [Saturation(b_sat=1.0)], seed=2).data
ideal, sat = fit(data), fit(data, [Saturation()])
print(f"ideal law: χ²/dof {ideal.reduced_chi2:.0f};  with saturation: χ²/dof {sat.reduced_chi2:.2f}")

# %% [markdown]
# ## Linearise at the operating bias
# The ideal law, fitted to a saturating bearing, puts part of the bend into its gap and k; the model with
# saturation gives the coefficients the bearing has at 1.6 A.

# %%
BIAS = 1.6
lin = {name: {ax: linearise(model, ax, BIAS) for ax in "vw"} for name, model in (("ideal law", ideal),
                                                                                   ("with saturation", sat))}
for name, by_axis in lin.items():
    for ax, x in by_axis.items():
        print(f"{name:16s} {ax}: k_i = {x.k_i:.2f} ± {x.k_i_std:.2f} N/A,  k_s = {x.k_s / 1e3:.2f} ± "
              f"{x.k_s_std / 1e3:.2f} kN/m")

# %% [markdown]
# ## A small rotor on two identified bearings
# A steel shaft (0.48 m, 30 mm) with a disk in the middle, an AMB at each end, a PD controller (the same
# gains for both models: what differs is the bearing they see).

# %%
steel = rs.Material(name="steel_amb", rho=7810, E=211e9, G_s=81.2e9)
shaft = [rs.ShaftElement(L=0.08, idl=0.0, odl=0.03, material=steel, shear_effects=True, rotary_inertia=True,
                         gyroscopic=True) for _ in range(6)]
disk = rs.DiskElement.from_geometry(n=3, material=steel, width=0.03, i_d=0.03, o_d=0.2)
CONTROLLER = {"kp": 1.0e4, "kd": 6.0}
speeds = np.linspace(20, 1500, 6 if FAST else 16)                       # rad/s
frequency = np.logspace(1, 4, 60)


def campbell(v, w):
    bearings = [bearing_element(v, w, n, frequency=frequency, **CONTROLLER) for n in (0, 6)]
    with warnings.catch_warnings():           # (ROSS warns at speeds off its frequency grid; ours covers them)
        warnings.simplefilter("ignore")
        result = rs.Rotor(shaft, [disk], bearings).run_campbell(speeds, frequencies=4)
    return np.asarray(result.wd)                                     # [speed, mode] rad/s


# %% [markdown]
# ## Campbell diagram with bands
# Each model's band: its lowest modes over parameter draws (the ideal law's posterior, emcee; the saturating
# model's parameters drawn from its covariance), each draw linearised and put in the rotor again.

# %%
n_draws = 4 if FAST else 30
post = bayes.sample(data, ls=ideal, n_ensembles=2, n_steps=400 if FAST else 3000, max_steps=400 if FAST else 30000,
                    seed=1)
# each model linearised at the same parameter draws on both axes (same seed): the draws behind its errors
drawn = {name: {ax: linearise(model, ax, BIAS, draws=n_draws, seed=2) for ax in "vw"}
         for name, model in (("ideal law", post), ("with saturation", sat))}
curves = {}
for name in lin:
    centre = campbell(lin[name]["v"], lin[name]["w"])
    band = np.array([campbell(drawn[name]["v"].draw(j), drawn[name]["w"].draw(j)) for j in range(n_draws)])
    curves[name] = (centre, band.min(axis=0), band.max(axis=0))
ratio = {ax: lin["ideal law"][ax].k_i / lin["with saturation"][ax].k_i - 1 for ax in "vw"}
shift = curves["ideal law"][0] / curves["with saturation"][0] - 1
print("the ideal law's k_i above the saturating model's: " + ", ".join(f"{ax} {100 * r:+.1f} %" for ax, r in
                                                                       ratio.items()))
print(f"its modes above: {100 * shift.min():+.1f} to {100 * shift.max():+.1f} % over the speeds; lowest mode at "
      f"rest {curves['with saturation'][0][0, 0] / (2 * np.pi):.1f} Hz with saturation")

fig, ax = plt.subplots(figsize=(8, 5), layout="constrained")
for (name, (centre, low, high)), colour in zip(curves.items(), ("tab:blue", "tab:red")):
    for mode in range(centre.shape[1]):
        ax.plot(speeds, centre[:, mode] / (2 * np.pi), color=colour, lw=1.2, label=name if mode == 0 else None)
        ax.fill_between(speeds, low[:, mode] / (2 * np.pi), high[:, mode] / (2 * np.pi), color=colour, alpha=0.25)
ax.plot(speeds, speeds / (2 * np.pi), "k--", lw=0.8, label="1x running speed")
ax.set(xlabel="running speed [rad/s]", ylabel="damped natural frequency [Hz]",
       title=f"Campbell diagram: the rotor on two identified AMBs at {BIAS} A bias")
ax.legend()
plt.show()

# %% [markdown]
# The two models disagree on the bearing the rotor sees: fitted to a saturating bearing, the ideal law
# overstates both coefficients at the operating bias (the numbers above), and every mode the bearings carry
# (the cylindrical pair and the conical pair that gyroscopics split with speed) sits higher with it.  The bands
# from the parameters' uncertainty are thinner than the lines: these data determine each model's parameters
# well, and what moves the Campbell diagram is the choice of model, which is what `ambfit diagnose` decides.
