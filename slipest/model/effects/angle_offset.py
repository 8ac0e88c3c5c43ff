"""``angle_offset``: encoder zero not at the true midstance, or a time skew (sampled sensor effect)."""

from __future__ import annotations

import math

from slipest.model.effects.base import Effect, FitParam, ParamSpec


class AngleOffset:
    """Encoder angle = true angle + ``offset`` [rad] ("sampled" stage)."""

    domain = "sampled"

    def __init__(self, offset: float):
        self.offset = float(offset)

    def apply(self, t, az, theta, rng):
        return az, theta + self.offset


class AngleOffsetEffect(Effect):
    """Encoder zero not at the true midstance: ``theta_log = theta + offset``.

    Equivalently a time skew ``offset / omega`` [s] between IMU and encoder
    (the encoder's angle reported ``offset/omega`` seconds early). Only a
    positive offset moves ``Da``'s window off the end of the stance, where
    the oscillation is largest; a negative one moves it into the quiet rigid
    half and changes ``Da`` little (the diagnosis sees both in the
    waveform). A positive offset brings the previous stance into the logged
    cycle.
    """

    name = "angle_offset"
    kind = "sampled"
    equation = "theta_log = theta + offset  (= time skew offset/omega)"
    description = ("offset between the encoder's zero and the true midstance, or equally a time skew "
                   "between IMU and encoder")
    params = (
        ParamSpec("offset", "rad", 0.18, (-0.15, 0.15), (0.12, 0.2), (-math.pi, math.pi),
                  "encoder angle minus true angle (a negative offset moves the Da window into the quiet "
                  "rigid half and changes Da little)", neutral=0.0),
    )
    fit_params = (FitParam("offset", "rad", -0.22, 0.22, off=0.0),)
    memory = True

    def stage(self, values):
        return AngleOffset(values["offset"])

    def angle_offset_at(self, values, omega):
        """``offset`` [rad], at any leg speed."""
        return float(values["offset"])

    def sense(self, x, values, ctx):
        return ctx.bin_average(x, values["offset"])
