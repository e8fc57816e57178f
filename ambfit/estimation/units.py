"""Parameters in the units people read and files hold: µm for gaps and origins, N·m²/A² for ``k`` (SI inside,
see STYLE.md), the contract's keys (DATA-CONTRACT.md section 2) and a value with its error to the precision the
error justifies."""

from __future__ import annotations

import numpy as np

CONTRACT_PARAMS = (("g_v0", "g_v0_um", 1e6), ("v0", "v0_um", 1e6), ("g_w0", "g_w0_um", 1e6), ("w0", "w0_um", 1e6),
                   ("k_v", "k_v_Nm2_per_A2", 1.0), ("k_w", "k_w_Nm2_per_A2", 1.0))
"""Internal name, contract key (section 2) and the factor from SI to the contract's unit."""

DISPLAY = {"g_v0": ("µm", 1e6), "g_w0": ("µm", 1e6), "v0": ("µm", 1e6), "w0": ("µm", 1e6),
           "k_v": ("N·m²/A²", 1.0), "k_w": ("N·m²/A²", 1.0)}
"""Display unit and the factor from SI of the head parameters (loads are in N, effect parameters in SI)."""


def display(name: str, value: float) -> tuple[float, str]:
    """A parameter in its display unit: ``(value, unit)`` (µm for gaps and origins, SI otherwise)."""
    unit, factor = DISPLAY.get(name, ("N" if name.startswith("load[") else "SI", 1.0))
    return value * factor, unit


def pm(value: float, std: float, digits: int = 2) -> str:
    """``value ± std`` to the precision the error justifies: ``digits`` significant digits of the std.

    >>> pm(774.49876, 1.40568), pm(32.7831, 0.3163), pm(3.45725e-06, 1.5095e-08)
    ('774.5 ± 1.4', '32.78 ± 0.32', '3.457e-06 ± 1.5e-08')
    >>> pm(1.5, float("nan"))
    '1.5'
    """
    if not np.isfinite(value):
        return str(value)
    if not (np.isfinite(std) and std > 0):
        return f"{value:.6g}"
    lead = int(np.floor(np.log10(std))) - (digits - 1)      # decimal position of the last shown digit
    scale = abs(value) if value != 0 else std
    if abs(scale) >= 1e-3 and abs(scale) < 1e5:
        decimals = max(0, -lead)
        return f"{value:.{decimals}f} ± {std:.{decimals}f}"
    exponent = int(np.floor(np.log10(abs(scale))))
    mantissa_decimals = max(0, exponent - lead)
    return f"{value:.{mantissa_decimals}e} ± {std:.{digits - 1}e}"
