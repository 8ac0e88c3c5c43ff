"""The IMU/encoder chain as composable stages (in the spirit of imusim).

A stream is built in two places (see :mod:`slipest.model.stream`):

* at the model step, on the continuous hub signal: stages that stand for
  physics or analog sensor behaviour (a hub transient, the IMU's bandwidth);
* at the IMU sample times: stages that stand for the digital sensor
  (noise, full-scale clipping, an encoder offset).

Every stage is an object with ``apply(t, az, theta, rng) -> (az, theta)``
over one chunk of the stream, keeping whatever state it needs between
chunks (a filter's memory), so a long run streams in bounded memory and
gives the same samples however it is chunked. Units: ``t`` [s], ``az``
[m/s^2] (the stage sees the specific force, gravity included, z up),
``theta`` [rad], unwrapped.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from slipest.units import G


class SensorStage(Protocol):
    """One composable piece of the sensor chain."""

    #: "continuous" (applied at the model step) or "sampled" (at IMU samples).
    domain: str

    def apply(
        self, t: np.ndarray, az: np.ndarray, theta: np.ndarray, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        """Return the modified ``(az, theta)`` for this chunk."""
        ...


class GaussianNoise:
    """White Gaussian accelerometer noise of standard deviation ``sigma_g`` [g]."""

    domain = "sampled"

    def __init__(self, sigma_g: float):
        if not sigma_g >= 0:
            raise ValueError(f"noise sigma={sigma_g} g must be >= 0")
        self.sigma = sigma_g * G

    def apply(self, t, az, theta, rng):
        if self.sigma == 0.0:
            return az, theta
        return az + rng.normal(0.0, self.sigma, size=az.shape), theta


def run_stages(stages, domain: str, t, az, theta, rng):
    """Apply every stage of the given domain, in order."""
    for stage in stages:
        if stage.domain == domain:
            az, theta = stage.apply(t, az, theta, rng)
    return az, theta
