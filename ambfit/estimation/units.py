"""Parameters in the units people read and files hold: µm for gaps and origins, N·m²/A² for ``k`` (SI inside,
see STYLE.md), the contract's keys (DATA-CONTRACT.md section 2) and a value with its error to the precision the
error justifies.

Every estimate a person reads (the report's tables, the command line's tables, ``print(result)``) is written by
:func:`pm`: the std's first two significant digits decide the last digit shown, and a value too small or too
large for fixed decimals (``k`` ≈ 3e-6 N·m²/A²) shares one power of ten with its std, so the two read side by
side (``3.457e-06 ± 0.015e-06``) and never round to ``0.0000 ± 0.0000``.
"""

from __future__ import annotations

import numpy as np

HEAD = ("g_v0", "v0", "g_w0", "w0", "k_v", "k_w")
"""The six head parameters, in the contract's order (DATA-CONTRACT.md section 2): the effective gap and origin of
axis v, then of axis w [m], then the force constants of v and w [N m^2/A^2].  The one spelling of their names:
every list of them is made from this table and its slices below (the fit's parameter vector orders them gaps,
origins, force constants: :data:`ambfit.estimation.core.HEAD_NAMES`)."""

GEOMETRY = HEAD[:4]
"""The geometric head parameters, gap and origin of each axis [m] (a campaign follows these)."""

GAPS, ORIGINS, FORCE_CONSTANTS = HEAD[0:4:2], HEAD[1:4:2], HEAD[4:]
"""``(g_v0, g_w0)``, ``(v0, w0)`` and ``(k_v, k_w)``: each pair ordered by axis (v, w)."""

BY_AXIS = {ax: (GAPS[a], ORIGINS[a], FORCE_CONSTANTS[a]) for a, ax in enumerate(("v", "w"))}
"""Each axis' gap, origin and force constant: ``{"v": ("g_v0", "v0", "k_v"), "w": ("g_w0", "w0", "k_w")}``."""

CONTRACT_PARAMS = tuple((n, f"{n}_um", 1e6) for n in GEOMETRY) + tuple((n, f"{n}_Nm2_per_A2", 1.0)
                                                                        for n in FORCE_CONSTANTS)
"""Internal name, contract key (section 2) and the factor from SI to the contract's unit."""

DISPLAY = {n: ("µm", 1e6) for n in GEOMETRY} | {n: ("N·m²/A²", 1.0) for n in FORCE_CONSTANTS}
"""Display unit and the factor from SI of the head parameters (loads are in N, effect parameters in SI)."""

SI = {n: "m" for n in GEOMETRY} | {n: "N·m²/A²" for n in FORCE_CONSTANTS}
"""The SI unit of each head parameter, the unit of ``FitResult.value`` and ``Posterior.value``."""

FIXED_RANGE = (1e-3, 1e5)
"""Magnitudes printed with fixed decimals; outside it a value and its std share a power of ten."""


def display(name: str, value: float) -> tuple[float, str]:
    """A parameter in its display unit: ``(value, unit)`` (µm for gaps and origins, SI otherwise)."""
    unit, factor = DISPLAY.get(name, ("N" if name.startswith("load[") else "SI", 1.0))
    return value * factor, unit


def si_unit(name: str) -> str:
    """The SI unit of a parameter's value: ``m``, ``N·m²/A²``, ``N`` for a nuisance load, ``SI`` for an effect's
    parameter (its class docstring gives the unit)."""
    return SI.get(name, "N" if name.startswith("load[") else "SI")


def _layout(value: float, std: float, digits: int) -> tuple[int | None, int]:
    """``(exponent, decimals)``: the shared power of ten (None for fixed decimals) and the decimals of the mantissa
    that show ``digits`` significant digits of ``std``."""
    lead = int(np.floor(np.log10(std))) - (digits - 1)      # decimal position of the last shown digit
    scale = max(abs(value), std)
    if FIXED_RANGE[0] <= scale < FIXED_RANGE[1]:
        return None, max(0, -lead)
    exponent = int(np.floor(np.log10(scale)))
    return exponent, max(0, exponent - lead)


def _write(x: float, exponent: int | None, decimals: int) -> str:
    if exponent is None:
        return f"{x:.{decimals}f}"
    return f"{x / 10.0**exponent:.{decimals}f}e{exponent:+03d}"


def pm(value: float, std: float, digits: int = 2) -> str:
    """``value ± std`` to the precision the error justifies: ``digits`` significant digits of the std; a value
    outside ``FIXED_RANGE`` shares its power of ten with the std.

    >>> pm(774.49876, 1.40568), pm(32.7831, 0.3163), pm(3.45725e-06, 1.5095e-08)
    ('774.5 ± 1.4', '32.78 ± 0.32', '3.457e-06 ± 0.015e-06')
    >>> pm(1.5, float("nan")), pm(2.5e-07, 3e-09)
    ('1.5', '2.500e-07 ± 0.030e-07')
    """
    if not np.isfinite(value):
        return str(value)
    if not (np.isfinite(std) and std > 0):
        return f"{value:.6g}"
    exponent, decimals = _layout(value, std, digits)
    return f"{_write(value, exponent, decimals)} ± {_write(std, exponent, decimals)}"


def like(value: float, std: float, x: float, digits: int = 2) -> str:
    """``x`` written as :func:`pm` writes ``value`` (same decimals, same power of ten): an interval's ends beside
    its estimate.

    >>> like(3.45725e-06, 1.5095e-08, 3.4312e-06), like(774.49876, 1.40568, 771.912)
    ('3.431e-06', '771.9')
    """
    if not (np.isfinite(std) and std > 0 and np.isfinite(value)):
        return f"{x:.6g}"
    return _write(x, *_layout(value, std, digits))


def with_unit(name: str, value_si: float, std_si: float) -> tuple[str, str]:
    """A parameter's estimate in its display unit: ``("774.5 ± 1.4", "µm")`` from SI value and std."""
    v, unit = display(name, value_si)
    return pm(v, display(name, std_si)[0]), unit
