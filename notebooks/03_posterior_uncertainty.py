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
# # 03 · Posterior uncertainty
#
# Least squares gives a point and a covariance; the posterior (emcee, several independent
# ensembles, ArviZ diagnostics) says whether that Gaussian picture holds and gives credible
# intervals and a predictive force with its uncertainty, the paper's end goal.
# Fast mode (default) runs 2 ensembles x 1500 steps; `AMBFIT_FAST=0` runs 4 x 4000.

# %%
import os
from pathlib import Path

import matplotlib.pyplot as plt

import ambfit
from ambfit.data import read_csv
from ambfit.estimation import bayes
from ambfit.faces import plots

FAST = os.environ.get("AMBFIT_FAST", "1") != "0"
ROOT = Path.cwd() if (Path.cwd() / "data").exists() else Path.cwd().parent
ds = read_csv(ROOT / "data" / "paper_table2.csv")

# %%
ls = ambfit.fit(ds)
res = ambfit.sample(ds, n_ensembles=2 if FAST else 4, n_steps=1500 if FAST else 4000, max_steps=1500 if FAST else 30000,
                    seed=1, ls=ls)
print(res.message)
res.to_dataframe()

# %% [markdown]
# Posterior against least squares: means within a small fraction of a standard error and sds
# within a few per cent mean the likelihood is near-Gaussian for this design.

# %%
js = res.to_json()
for name, key in (("g_v0", "g_v0_um"), ("v0", "v0_um"), ("g_w0", "g_w0_um"), ("w0", "w0_um")):
    p = js["params"][key]
    print(f"{name}: posterior {p['value']:.2f} ± {p['std']:.2f}, least squares {ls.value(name) * 1e6:.2f} ± "
          f"{ls.error(name) * 1e6:.2f} µm, 94 % HDI {p['hdi_low']:.2f}-{p['hdi_high']:.2f}")

# %%
plots.plot_pair(res, result=ls)
plt.show()

# %% [markdown]
# ## The posterior on the paper's Fig. 2 map
# Draws of (gap, origin) follow the ellipse of least squares here; for the paper's first
# iteration (notebook 02) they spread along the valley.

# %%
from ambfit.estimation import conditioning

d = res.draws.reshape(-1, res.draws.shape[-1])
samples = d[:, [res.names.index("g_v0"), res.names.index("v0")]]
plots.plot_solution_space(conditioning.solution_space(ds, "v", weights_at=ls), result=ls, samples=samples)
plt.show()

# %% [markdown]
# ## Predictive force with uncertainty
# The force at the rig's operating point (1.4 A bias, the measured currents of the first
# reading) from every draw, with and without the reading noise.

# %%
row = ds.frame[ds.frame["axis"] == "v"].iloc[0]
for sig in (0.0, 0.6e-3):
    f = bayes.force_predictive(res, "v", row["i_top_A"], row["i_bottom_A"], row["v_um"] * 1e-6, sigma_i=sig)
    print(f"sigma_i = {sig * 1e3:.1f} mA: F_v = {f['mean'][0]:.4f} ± {f['sd'][0]:.4f} N "
          f"(94 %: {f['q03'][0]:.4f}-{f['q97'][0]:.4f}); load recorded {row['load_N']:.4f} N")
