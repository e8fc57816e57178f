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
# # 02 · The solution space (the paper's Fig. 2) and the conditioning of designs
#
# At one rotor position Eq. 6 fixes only the ratio of the two gaps, so a whole line of
# (gap, origin) pairs fits.  Two positions that are close together compared with their
# distance from the effective origin give two nearly parallel lines: the long valley of the
# paper's Fig. 2.  Symmetric pairs about the effective origin make the lines cross steeply,
# which is why the paper moved to them; least squares can also use that one load is
# carried at every position.

# %%
import matplotlib.pyplot as plt

import ambfit
from ambfit import rig
from ambfit.estimation import conditioning
from ambfit.faces import plots
from ambfit.rig import protocol as P
from ambfit.studies.paper import fig2_data

# %% [markdown]
# ## The paper's setting: pairs at ±20 µm about the back-up bearing centre
# 13.3 and 53.3 µm from the effective origin (-33.3 µm), one unknown load per position.

# %%
first = fig2_data(seed=7)
space = conditioning.solution_space(first, "v", **conditioning.PAPER_FIG2)   # the paper's axes
ls = ambfit.fit(first)
print(f"g_v0 = {ls.value('g_v0') * 1e6:.0f} ± {ls.error('g_v0') * 1e6:.0f} µm, v0 = {ls.value('v0') * 1e6:.1f} ± "
      f"{ls.error('v0') * 1e6:.1f} µm, correlation {ls.corr[ls.names.index('g_v0'), ls.names.index('v0')]:+.3f}")

# %%
plots.plot_fig2_surface(space)
plt.show()

# %%
plots.plot_solution_space(space, result=ls)
plt.show()

# %% [markdown]
# The valley's direction is the weakest direction of the Fisher information:

# %%
d = conditioning.weakest_direction(ls, "v")
print(f"weakest direction (gap, origin) = {d.round(4)}: {d[1] / d[0]:+.3f} µm of origin per µm of gap")

# %% [markdown]
# ## Symmetric pairs about the effective origin, the same load at every position
# Ten iterations of the paper's Table 2 protocol after the search has centred the pairs:

# %%
centred = rig.simulate(rig.PAPER_RIG, P.paper_table2(iterations=10, center=(-33.3e-6, 11.3e-6)), seed=3).data
ls2 = ambfit.fit(centred)
plots.plot_solution_space(conditioning.solution_space(centred, "v", weights_at=ls2), result=ls2)
plt.show()

# %% [markdown]
# ## Designs compared by their Cramér-Rao bound
# Current-only and position-only designs cannot separate gap from origin when each position
# may carry its own load (unbounded, grey); the rich design is the best conditioned.

# %%
table = conditioning.compare_designs()
table.round(3)

# %%
plots.plot_design_comparison(table)
plt.show()
