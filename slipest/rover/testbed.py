"""Testbed logs as the calibration sees them: per leg cycle, its feature row and its known slip (pure computation).

:func:`cycle_rows` runs a sample stream (``t`` [s], ``az`` [m/s^2],
``theta`` [rad], optional reference ``slip`` [-]) through the estimator's
own path (:class:`slipest.online.SlipEstimator`: segmenter, glitch filter,
noise estimate, features), so the rows are exactly those a replay of the
same samples gives the estimator. :class:`TestbedLog` holds one log's
estimated cycles: feature rows (:data:`slipest.features.FEATURE_NAMES`),
the reference slip, and which cycles a held-out check keeps out
(:meth:`TestbedLog.heldout_levels`: whole slip levels).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slipest.features import INDEX

#: Slip levels a single log needs for a held-out check of whole levels (fewer: held-out cycles share their levels
#: with the fit, which then tests nothing).
MIN_HELDOUT_LEVELS = 4
#: Least range of reference slips [-] over a log's estimated cycles: one slip level tells no slip from soil.
MIN_SLIP_RANGE = 0.05


def cycle_rows(t, az, theta, slip=None, n_legs: int = 4, model=None) -> dict:
    """The cycles of a stream that reached the estimator: ``cycle`` ``(n,)`` indices, ``features`` ``(n, F)``,
    ``slip_ref`` ``(n,)`` (NaN: none), and the estimator's own ``slip``, ``slip_std`` with ``model`` (default:
    the shipped surrogate), the soil unknown; ``flagged``: cycles without features (a fault, a partial cycle),
    by quality.

    A cycle the model cannot explain at all (quality ``"misfit"``) keeps its row, with ``slip`` and
    ``slip_std`` NaN: its features are sound, and they are what a calibration must learn from."""
    from slipest.online import SlipEstimator

    rows: list = []
    flagged: dict = {}
    est = SlipEstimator(n_legs=n_legs, model=model)

    def keep(e):
        if e.ok or e.quality == "misfit":
            rows.append((e.cycle, est.last_features.copy(), e.slip_ref, e.slip, e.slip_std))
        else:
            flagged[e.quality] = flagged.get(e.quality, 0) + 1

    est.on_estimate = keep
    chunk = (np.asarray(t, float), np.asarray(az, float), np.asarray(theta, float),
             None if slip is None else np.asarray(slip, float))
    for _ in est.iter_estimates([chunk]):
        pass
    n_feat = len(INDEX)
    return {"cycle": np.array([r[0] for r in rows], dtype=np.int64),
            "features": np.array([r[1] for r in rows]).reshape(-1, n_feat),
            "slip_ref": np.array([r[2] for r in rows], dtype=float),
            "slip": np.array([r[3] for r in rows], dtype=float),
            "slip_std": np.array([r[4] for r in rows], dtype=float), "flagged": flagged, "hints": dict(est.hints)}


def sample_rate(t) -> float:
    """A log's IMU sample rate [Hz]: 1 over the median of its positive finite time steps (NaN without one)."""
    dt = np.diff(np.asarray(t, dtype=float))
    dt = dt[np.isfinite(dt) & (dt > 0)]
    return 1.0 / float(np.median(dt)) if dt.size else float("nan")


@dataclass
class TestbedLog:
    """One testbed log's estimated cycles with a known slip.

    name: what messages call it; features ``(n, F)``; slip ``(n,)`` [-];
    cycle ``(n,)``: the cycles' indices in the log; flagged: cycles not
    estimated by quality; n_cycles: cycles in the log (estimated or not);
    rate: the IMU's sample rate [Hz] (median time step).
    """

    name: str
    features: np.ndarray
    slip: np.ndarray
    cycle: np.ndarray
    flagged: dict
    n_cycles: int
    rate: float

    @classmethod
    def from_samples(cls, name: str, t, az, theta, slip, n_legs: int = 4, model=None) -> "TestbedLog":
        """The log's cycles with a reference slip (ValueError naming the log when fewer than 8 remain, or when
        their reference slips span less than :data:`MIN_SLIP_RANGE`); ``model``: the estimator's (a rover
        model's sample correction applies)."""
        r = cycle_rows(t, az, theta, slip, n_legs, model)
        keep = np.isfinite(r["slip_ref"])
        n_all = len(r["cycle"]) + sum(r["flagged"].values())
        log = cls(name, r["features"][keep], r["slip_ref"][keep], r["cycle"][keep], r["flagged"], n_all,
                  sample_rate(t))
        if len(log) < 8:
            why = ", ".join(f"{k} {v}" for k, v in sorted(r["flagged"].items())) or "none flagged"
            hint = r["hints"].get("units") or r["hints"].get("degrees")
            raise ValueError(f"{name}: only {len(log)} estimated leg cycle(s) with a reference slip (of {n_all}; "
                             f"not estimated: {why}); calibration needs at least 8 per log"
                             + (f"; {hint}" if hint else ""))
        spread = float(np.ptp(log.slip))
        if spread < MIN_SLIP_RANGE:
            raise ValueError(f"{name}: the reference slip spans only {spread:.3g} over its {len(log)} estimated "
                             f"cycles (around {float(np.median(log.slip)):.3g}); calibration needs several slip "
                             f"levels in each log (at least {MIN_SLIP_RANGE:g} apart; a testbed run at 8 levels, say) "
                             "to tell the slip from the soil")
        return log

    def __len__(self) -> int:
        return len(self.slip)

    @property
    def omega(self) -> float:
        """Median leg speed of the log's cycles [rad/s]."""
        return float(np.median(self.features[:, INDEX["omega"]]))

    @property
    def noise_smooth(self) -> float:
        """Median smoothed noise of the log's cycles [g]."""
        return float(np.median(self.features[:, INDEX["noise_smooth"]]))

    @property
    def noise(self) -> float:
        """Median IMU noise of the log's cycles [g]."""
        return float(np.median(self.features[:, INDEX["noise"]]))

    def levels(self) -> np.ndarray:
        """The distinct reference slips (rounded to 1e-4) [-], increasing."""
        return np.unique(np.round(self.slip, 4))

    def heldout_levels(self, every: int = 3) -> np.ndarray:
        """Cycles whose slip level is held out: every ``every``-th interior level (2nd, 5th, ...) when the log
        has at least 4 levels, else every ``every``-th cycle. Boolean ``(n,)``."""
        lev = self.levels()
        if lev.size >= MIN_HELDOUT_LEVELS:
            out = lev[1:-1][::every]
            return np.isin(np.round(self.slip, 4), out)
        return np.arange(len(self)) % every == 1

    def subset(self, keep) -> "TestbedLog":
        keep = np.asarray(keep)
        return TestbedLog(self.name, self.features[keep], self.slip[keep], self.cycle[keep], self.flagged,
                          self.n_cycles, self.rate)


def finite_rows(features, columns) -> np.ndarray:
    """Rows whose modelled features are all finite (boolean)."""
    return np.all(np.isfinite(np.asarray(features)[:, columns]), axis=1)


__all__ = ["MIN_HELDOUT_LEVELS", "MIN_SLIP_RANGE", "TestbedLog", "cycle_rows", "finite_rows", "sample_rate"]
