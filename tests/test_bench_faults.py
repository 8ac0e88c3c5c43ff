"""tools/bench_faults.py: its fault injector puts in what it says, its serial check catches a corrupted sample."""

from __future__ import annotations

import numpy as np

from firmware_sim.device import STATUS_NAMES
from slipest.units import G
from tools.bench_faults import against_send_log, injector


def _send_log(n: int, corrupted: list[int]) -> dict:
    """A device's send log of ``n`` IMU frames of wheel 0 at 1 kHz, ``corrupted`` ones marked so."""
    status = np.full(n, STATUS_NAMES.index("sent"), np.uint8)
    status[corrupted] = STATUS_NAMES.index("corrupted")
    return {"kind": np.ones(n, np.uint8), "wheel": np.zeros(n, np.uint8), "t_us": 5_000_000 + 1000 * np.arange(n),
            "az": 9.81 + 0.1 * np.sin(np.arange(n)), "status": status, "status_names": np.array(STATUS_NAMES)}


def test_the_serial_check_passes_a_clean_record_and_catches_what_should_not_reach_the_estimator():
    sent = _send_log(100, [10, 50])
    t = sent["t_us"] * 1e-6
    az = np.round(sent["az"].astype(np.float32).astype(float), 6)  # as the record writes it
    az[[10, 50]] = np.nan  # the corrupted frames: lost, NaN rows
    assert against_send_log(sent, 0, t, az) == {"sent": 100, "corrupted": 2, "used": 98, "from_corrupted": 0,
                                                "unknown": 0, "wrong": 0}
    bad = az.copy()
    bad[10] = 9.81  # a corrupted frame got through
    bad[20] += 1e-3  # a value other than the one sent
    assert against_send_log(sent, 0, t, bad) == {"sent": 100, "corrupted": 2, "used": 99, "from_corrupted": 1,
                                                 "unknown": 0, "wrong": 1}
    shifted = np.append(t, t[-1] + 0.0005)  # a row at a time the device never sent
    assert against_send_log(sent, 0, shifted, np.append(az, 9.81))["unknown"] == 1


def test_the_injector_puts_isolated_spikes_missing_rows_and_nans_in_the_shares_it_says():
    n_cycles, per = 2000, 100
    t = np.arange(n_cycles * per) * 1e-3
    az = np.full(t.size, G)
    cycle = np.repeat(np.arange(n_cycles), per)
    tally = dict.fromkeys(("cycles_faulted", "spikes", "rows_missing", "nan_samples"), 0)
    t2, az2, theta2 = injector(3, tally)(t, az, 0.6 * t, cycle)
    assert t2.size == theta2.size == t.size - tally["rows_missing"]
    dev = np.abs(az2 - G)
    spikes = np.flatnonzero(dev > 1.0)
    assert spikes.size == tally["spikes"] and np.all((dev[spikes] >= 3 * G) & (dev[spikes] <= 16 * G))
    assert np.isnan(az2).sum() == tally["nan_samples"]
    assert abs(tally["spikes"] / n_cycles - 0.3) < 0.05 and abs(tally["nan_samples"] / n_cycles - 0.15) < 0.05
    assert 1.0 <= tally["rows_missing"] / (0.3 * n_cycles) <= 3.0  # 1-3 rows in 30 % of the cycles
