"""Effects of the measurement chain: what the current and position sensors report differs from the physical
quantity (an offset, a gain mismatch, a gain error).

Each is a pair of maps, ``sense`` (physical -> reading, which the virtual rig applies) and its
inverse ``unsense`` (reading -> physical, the ``physical`` stage of a fit).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from ambfit.physics.stages import Effect, _ax


class CurrentOffset(Effect):
    """Additive offset of the current channels: reading = physical + offset [A].

    ``top`` and ``bottom`` are ``(v, w)`` offsets.  The paper calibrates its DAQ to
    0.1 % of 3 A, i.e. offsets of a few mA; 2-15 mA covers an uncalibrated Hall
    sensor or shunt amplifier.
    """

    top: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(0.005))
    bottom: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(-0.005))
    name: ClassVar[str] = "current_offset"
    RANGES: ClassVar = {"top": (0.004, 0.015), "bottom": (0.004, 0.015)}
    SIGNED: ClassVar = ("top", "bottom")
    UNITS: ClassVar = {"top": "A", "bottom": "A"}

    def sense(self, axis, i_top, i_bottom, x, y):
        return i_top + _ax(self.top, axis), i_bottom + _ax(self.bottom, axis), x, y

    def unsense(self, axis, i_top, i_bottom, x, y):
        return i_top - _ax(self.top, axis), i_bottom - _ax(self.bottom, axis), x, y


class CurrentGain(Effect):
    """Gain mismatch between the top and bottom current channels.

    reading_top = (1 + mismatch/2) i_top, reading_bottom = (1 - mismatch/2) i_bottom.
    0.2-2 % is the spread of shunt resistors and amplifier gains (paper: DAQ
    calibrated to 0.1 %).
    """

    mismatch: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(0.01))
    name: ClassVar[str] = "current_gain"
    RANGES: ClassVar = {"mismatch": (0.003, 0.02)}
    SIGNED: ClassVar = ("mismatch",)
    UNITS: ClassVar = {"mismatch": "-"}

    def sense(self, axis, i_top, i_bottom, x, y):
        e = _ax(self.mismatch, axis) / 2.0
        return i_top * (1.0 + e), i_bottom * (1.0 - e), x, y

    def unsense(self, axis, i_top, i_bottom, x, y):
        e = _ax(self.mismatch, axis) / 2.0
        return i_top / (1.0 + e), i_bottom / (1.0 - e), x, y


class PositionGain(Effect):
    """Gain error of the position sensors: reading = (1 + gain_error) * physical.

    ``gain_error`` is ``(v, w)``.  Eddy-current probes drift 0.5-3 % with target
    material and temperature; the paper's micrometer calibration is good to 0.25 %.
    A gain error rescales the identified gap and origin (it is absorbed).
    """

    gain_error: jnp.ndarray = eqx.field(default_factory=lambda: jnp.asarray(0.02))
    name: ClassVar[str] = "position_gain"
    RANGES: ClassVar = {"gain_error": (0.01, 0.04)}
    SIGNED: ClassVar = ("gain_error",)
    UNITS: ClassVar = {"gain_error": "-"}

    def sense(self, axis, i_top, i_bottom, x, y):
        return i_top, i_bottom, x * (1.0 + _ax(self.gain_error, axis)), y * (1.0 + _ax(self.gain_error, 1 - axis))

    def unsense(self, axis, i_top, i_bottom, x, y):
        return i_top, i_bottom, x / (1.0 + _ax(self.gain_error, axis)), y / (1.0 + _ax(self.gain_error, 1 - axis))
