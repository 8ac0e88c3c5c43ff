"""`slipest replay` on what a rover records: python-can log files and ROS 2 bags, written here with
python-can's writers and rosbags; a CAN log's replay against `slipest can` listening to the same frames
played onto a real (socketcand) bus by can.player."""

from __future__ import annotations

import csv
import io
import math
import subprocess
import sys
import time

import can
import numpy as np
import pytest

from slipest.cli.estimate_output import parse_rows
from slipest.cli.main import main
from slipest.io.can_messages import TIME_MOD_PERIOD, decode
from slipest.online import ESTIMATE_FIELDS, SlipEstimator
from tests.cli_support import slipest_in_process
from tests.hil_support import PY, Stopping, can_server, slipest_cmd, socketcand_args
from tests.log_makers import can_frames, stream, with_references, write_bag, write_can_log, write_csv

PERIOD = 2 * math.pi / (4 * 0.63)


def replay(args, capsys):
    rc = main(["replay", *map(str, args)])
    out, err = capsys.readouterr()
    return rc, out, err


def rows_by_key(text: str, wheel: bool = True) -> dict:
    rows = list(csv.DictReader(io.StringIO(text)))
    return {((int(r["wheel"]),) if wheel else ()) + (int(r["cycle"]),): r for r in rows}


# --- python-can log files ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def two_wheels():
    s0, _ = stream(5, seed=11)
    s1, _ = stream(5, seed=12, slip=[0.1, 0.2, 0.3, 0.4, 0.4])
    return {0: s0, 3: s1}


def _offline(s):
    """The estimates of one wheel's samples as its frames carry them (decoded, time unwrapped by hand)."""
    from slipest.io.can_messages import encode_imu

    dec = [decode(encode_imu(0, i, s.az[i], s.theta[i], s.t[i])) for i in range(len(s.t))]
    t = np.cumsum(np.r_[dec[0].time_mod, np.mod(np.diff([d.time_mod for d in dec]), TIME_MOD_PERIOD)])
    est = SlipEstimator()
    return est.push_many(t, [d.az for d in dec], [d.theta for d in dec]) + est.finish()


@pytest.fixture(scope="module")
def two_wheels_offline(two_wheels):
    """Each wheel's offline estimates (_offline), computed once for the log formats' tests, which only read them."""
    return {wheel: _offline(s) for wheel, s in two_wheels.items()}


@pytest.mark.parametrize("suffix", [".blf", ".asc", ".log", ".trc", ".csv", ".asc.gz", ".mf4"])
def test_python_can_log_formats_replay_every_wheel(suffix, two_wheels, two_wheels_offline, tmp_path, capsys):
    if suffix == ".mf4":
        pytest.importorskip("asammdf", reason="the [mf4] extra is not installed (not in [test]: pyproject.toml "
                            "says why)")
    frames = can_frames(two_wheels, unknown_every=400)
    log = write_can_log(tmp_path / f"drive{suffix}", frames)
    rc, out, err = replay([log], capsys)
    assert rc == 0, err
    rows = rows_by_key(out)
    assert out.splitlines()[0] == "wheel," + ",".join(ESTIMATE_FIELDS)
    for wheel in two_wheels:
        expected = two_wheels_offline[wheel]
        got = [rows[(wheel, e.cycle)] for e in expected]
        assert [r["quality"] for r in got] == [e.quality for e in expected]
        assert sum(e.quality == "ok" for e in expected) >= 3
        for r, e in zip(got, expected):
            if e.quality == "ok":
                assert float(r["slip"]) == pytest.approx(e.slip, abs=2e-6)
                assert float(r["dphi"]) == pytest.approx(e.dphi, abs=2e-6)
        assert math.isnan(float(got[1]["slip_ref"]))  # the reference reaches the rows only when asked
    ours = sum(decode(m) is not None for m in frames)
    assert f"{len(frames)} CAN frames read" in err and f"{ours} ours, {len(frames) - ours} other IDs" in err
    assert "wheel 0:" in err and "wheel 3:" in err and "5 leg cycles: 5 estimated" in err


def test_truth_and_a_lost_frame_in_a_can_log(two_wheels, tmp_path, capsys):
    lost = int(2.6 * PERIOD / 1e-3)  # a sample inside cycle 2's feature window
    log = write_can_log(tmp_path / "drive.blf", can_frames(two_wheels, drop={3: [lost]}))
    rc, out, err = replay([log, "--truth", "--wheel", "3"], capsys)
    assert rc == 0, err
    rows = rows_by_key(out)
    assert {w for w, _ in rows} == {3}  # --wheel
    # one lost frame (1 ms) is bridged: the cycle is estimated from the rest, and says so
    assert rows[(3, 2)]["quality"] == "repaired" and rows[(3, 2)]["n_repaired"] == "1"
    assert math.isfinite(float(rows[(3, 2)]["slip"]))
    assert "1 lost frames filled" in err
    s = two_wheels[3]
    ok = [r for r in rows.values() if r["quality"] == "ok"]
    assert len(ok) >= 3
    for r in ok:  # the SlipReference frames reach the rows: the slip imposed during the cycle's window
        assert float(r["slip_ref"]) == pytest.approx(s.slip[int((int(r["cycle"]) + 0.75) * PERIOD / 1e-3)], abs=1e-4)
    assert "truth: wheel 3: slip RMSE" in err


def test_a_can_log_python_can_cannot_parse_is_named_with_its_frame(two_wheels, tmp_path, capsys):
    good = write_can_log(tmp_path / "drive.log", can_frames({0: two_wheels[0]})[:50])
    lines = open(good).read().splitlines()
    lines[9] = "garbage"
    bad = tmp_path / "bad.log"
    bad.write_text("\n".join(lines) + "\n")
    rc, out, err = replay([bad], capsys)
    assert rc == 2 and "bad.log" in err and "frame 10" in err  # the rows before it are out already
    rc, out, err = replay([tmp_path / "drive.xyz", "--log-format", "can"], capsys)
    assert rc == 2 and "suffix" in err


def test_a_can_log_reference_outside_0_1_is_refused_when_learnt_from_and_skipped_otherwise(tmp_path, capsys):
    """A SlipReference of -0.2 or 1.5 in a CAN log: --use-reference and --truth refuse the log as they refuse such
    a CSV (check_reference_slip), naming the file and the frame's time; a plain replay skips and counts them as
    `slipest can` does, beside the invalid ones."""
    s, _ = stream(4, seed=11, slip=[0.1, 0.2, 0.3, 0.4])
    log = write_can_log(tmp_path / "drive.blf", with_references(can_frames({0: s}), {1: -0.2, 2: 1.5}))
    with can.LogReader(log) as reader:  # the time the log holds for the frame (a BLF's, from its start)
        when = next(m.timestamp for m in reader if getattr(decode(m), "slip", 0.0) < 0)
    for flag in ("--use-reference", "--truth"):
        rc, err = slipest_in_process(capsys, "replay", log, flag)
        assert rc == 2 and f"{log}: slip -0.2 at t = {when:.3f} s is outside [0, 1)" in err, err
        assert "SlipReference frame(s) so" in err and "Traceback" not in err
    rc, out, err = replay([log], capsys)
    assert rc == 0 and "2 references outside [0, 1) skipped" in err, err


# --- against a live run over a real bus ---------------------------------------------------------------


def test_a_can_log_replays_to_the_rows_slipest_can_printed_live(two_wheels, tmp_path, capsys):
    """can.player plays a recording (10x faster than driven) onto the CAN server while `slipest can`
    listens; `slipest replay` of the same file must print the same rows, to the digit."""
    lost = int(2.6 * PERIOD / 1e-3)
    log = write_can_log(tmp_path / "drive.blf", can_frames(two_wheels, time_scale=10.0, drop={0: [lost]},
                                                           unknown_every=300))
    # the CAN server in its own process (not a thread of this one: its GIL and its garbage collector, after
    # the rest of the suite, held 35,000 frames up to 3x longer)
    with Stopping() as procs:
        server, port = can_server()
        procs.add(server)
        est = procs.add(slipest_cmd("can", *socketcand_args(port), "--no-publish", "--idle-timeout", "2",
                                    "--duration", "90"))
        est.wait_err("listening on CAN bus", timeout=60)
        player = subprocess.run([PY, "-m", "can.player", "-i", "socketcand", "-c", "vcan0", "--bus-kwargs",
                                 "host=127.0.0.1", f"port={port}", "--", log], capture_output=True, text=True,
                                timeout=90)
        assert player.returncode == 0, player.stderr
        assert est.wait(60) == 0, est.stderr
    live = {(int(r["wheel"]), int(r["cycle"])): r for r in parse_rows(est.lines, ("wheel",))}
    rc, out, err = replay([log], capsys)
    assert rc == 0, err
    replayed = rows_by_key(out)
    assert len(live) >= 10 and set(replayed) == set(live)
    assert replayed == live  # every column of every row
    assert live[(0, 2)]["quality"] == "repaired" and sum(r["quality"] == "ok" for r in live.values()) >= 7


# --- ROS 2 bags -----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def drive():
    return stream(6, seed=5, slip=[0.15, 0.15, 0.3, 0.3, 0.45, 0.45])


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_ros2_bags_estimate_as_the_same_samples_in_a_csv(storage, drive, tmp_path, capsys):
    pytest.importorskip("rosbags")
    s, sc = drive
    bag = write_bag(tmp_path / "bag", s, storage=storage)
    csv_log = write_csv(tmp_path / "drive.csv", s, sc)
    rc, out, err = replay([bag, "--joint", "wheel_leg", "--slip-topic", "/slip", "--truth"], capsys)
    assert rc == 0, err
    from_bag = rows_by_key(out, wheel=False)
    rc, out, err_csv = replay([csv_log, "--truth"], capsys)
    from_csv = rows_by_key(out, wheel=False)
    ok = [k for k, r in from_csv.items() if r["quality"] == "ok"]
    assert len(ok) >= 5
    for k in ok:  # the joint angle at 200 Hz, unwrapped and interpolated onto the IMU's 1 kHz stamps
        assert from_bag[k]["quality"] == "ok"
        # the last cycle ends at the last sample: the bag's IMU samples after the last 200 Hz joint stamp
        # cannot be given an angle, so its stream ends up to 5 ms earlier, and that cycle lacks up to 5 of its
        # 2493 samples (its slip moved by 5e-6, 1.1e-5 since the estimate is sharpened: under 2e-4 of its std)
        last = k == max(from_csv)
        assert float(from_bag[k]["slip"]) == pytest.approx(float(from_csv[k]["slip"]),
                                                           abs=1e-3 * float(from_csv[k]["slip_std"]) if last else 1e-5)
        assert float(from_bag[k]["slip_ref"]) == pytest.approx(float(from_csv[k]["slip_ref"]), abs=1e-9)
        assert float(from_bag[k]["t_end"]) == pytest.approx(1.7e9 + float(from_csv[k]["t_end"]),
                                                            abs=5e-3 if last else 1e-5)
    assert "ROS 2 bag:" in err and "of 'wheel_leg'" in err and "truth: slip RMSE" in err
    rmse = lambda e: float(e.split("truth: slip RMSE ")[1].split(",")[0])  # noqa: E731
    assert rmse(err) == pytest.approx(rmse(err_csv), abs=1e-4)


def test_ros2_bag_errors_name_what_is_missing(drive, tmp_path, capsys):
    pytest.importorskip("rosbags")
    s, _ = drive
    bag = write_bag(tmp_path / "mcapbag", s, storage="mcap")
    rc, out, err = replay([bag], capsys)  # two joints in the messages, none named
    assert rc == 2 and "steer, wheel_leg" in err and "name the wheel-leg joint" in err
    rc, out, err = replay([bag, "--joint", "wheel_leg", "--imu-topic", "/hub/imu"], capsys)
    assert rc == 2 and "no topic '/hub/imu'" in err and "/imu (sensor_msgs/msg/Imu)" in err
    rc, out, err = replay([bag, "--joint", "knee"], capsys)
    assert rc == 2 and "joint 'knee'" in err and "wheel_leg" in err
    rc, out, err = replay([bag, "--joint", "wheel_leg", "--truth"], capsys)
    assert rc == 2 and "--slip-topic" in err
    zero = write_bag(tmp_path / "zero", s, zero_stamps=True, joints=("wheel_leg",))
    rc, out, err = replay([zero], capsys)
    assert rc == 2 and "zero header stamps" in err and "--bag-time" in err
    rc, out, err = replay([zero, "--bag-time"], capsys)
    assert rc == 0 and int(err.split("leg cycles: ")[1].split(" estimated")[0]) >= 4


def test_a_hole_in_the_joint_states_is_not_estimated_across(drive, tmp_path, capsys):
    pytest.importorskip("rosbags")
    s, _ = drive
    hole = ((2 + 0.55) * PERIOD, (2 + 0.75) * PERIOD)  # inside cycle 2's feature window
    bag = write_bag(tmp_path / "bag", s, joints=("wheel_leg",), joint_hole=hole)
    rc, out, err = replay([bag], capsys)
    assert rc == 0, err
    rows = rows_by_key(out, wheel=False)
    assert rows[(2,)]["quality"] in ("nan", "gap") and rows[(3,)]["quality"] == "ok"  # flagged, not estimated
    n_hole = int(err.split("outside the joint states left out, ")[1].split(" ")[0])
    assert n_hole == pytest.approx((hole[1] - hole[0]) / 1e-3, abs=12)


def test_without_rosbags_a_bag_names_the_extra(drive, tmp_path):
    pytest.importorskip("rosbags")
    s, _ = drive
    bag = write_bag(tmp_path / "bag", s, joints=("wheel_leg",))
    code = ("import sys; sys.modules['rosbags'] = None\n"
            "from slipest.cli.main import main; sys.exit(main(['replay', sys.argv[1]]))")
    p = subprocess.run([sys.executable, "-c", code, bag], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "pip install 'slipest[ros]'" in p.stderr and p.stdout == ""


# --- the picture of a replay ----------------------------------------------------------------------------


def test_replay_plot_shows_slip_band_reference_dphi_soil_and_flagged_cycles(two_wheels, tmp_path, capsys):
    pytest.importorskip("matplotlib")
    from slipest.offline.replay import Replay, ReplayOptions
    from slipest.offline.replay_plot import plt, replay_figure

    lost = int(2.6 * PERIOD / 1e-3)  # 20 frames (20 ms) lost in cycle 2's window: a hole, the cycle flagged
    log = write_can_log(tmp_path / "drive.blf", can_frames(two_wheels, drop={0: list(range(lost, lost + 20))}))
    png = tmp_path / "drive.png"
    rc, out, err = replay([log, "--plot", png], capsys)
    assert rc == 0 and f"wrote {png}" in err
    img = plt.imread(png)
    assert img.shape[0] > 600 and img.shape[1] > 1000
    assert float(np.mean(img[..., :3] < 0.9)) > 0.02  # not blank
    series = {}
    with Replay(log, ReplayOptions(carry_reference=True)) as r:
        r.run(lambda w, e: series.setdefault(w, []).append(e))
    fig = replay_figure(series)
    try:
        slip_ax = fig.axes[0]
        labels = slip_ax.get_legend_handles_labels()[1]
        assert labels[:2] == ["slip estimate", "95% band"] and "reference slip" in labels
        assert "flagged: nan 1" in labels
        assert [ax.get_ylabel() for ax in fig.axes[:6:2]] == ["slip [-]", "dphi = phiS - phiD [rad]", "kS [N/m]"]
        assert slip_ax.get_title() == "wheel 0" and fig.axes[1].get_title() == "wheel 3"
        band = slip_ax.collections[0].get_paths()[0].vertices[:, 1]
        est0 = [e for e in series[0] if e.ok]
        lo, hi = min(e.slip - 1.96 * e.slip_std for e in est0), max(e.slip + 1.96 * e.slip_std for e in est0)
        assert band.min() == pytest.approx(lo) and band.max() == pytest.approx(hi)
    finally:
        plt.close(fig)


def test_plots_without_matplotlib_name_the_extra_and_the_core_never_imports_it(tmp_path):
    s, sc = stream(4, seed=3, slip=[0.2, 0.2, 0.3, 0.3])
    log = write_csv(tmp_path / "drive.csv", s, sc)
    blocked = "import sys; sys.modules['matplotlib'] = None\nfrom slipest.cli.main import main\n"
    run = lambda *a: subprocess.run([sys.executable, "-c", blocked + f"sys.exit(main({list(a)!r}))"],  # noqa: E731
                                    capture_output=True, text=True, timeout=300)
    p = run("replay", str(log))
    assert p.returncode == 0 and p.stdout.startswith("cycle,") and len(p.stdout.splitlines()) >= 4, p.stderr
    p = run("replay", str(log), "--plot", str(tmp_path / "x.png"))
    assert p.returncode == 2 and "pip install 'slipest[plot]'" in p.stderr and p.stdout == ""
    t0 = time.monotonic()
    p = run("diagnose", str(log), "--plots", str(tmp_path / "png"), "--no-progress")
    assert p.returncode != 0 and "pip install 'slipest[plot]'" in p.stderr and "slipest diagnose" in p.stderr
    assert time.monotonic() - t0 < 60 and not (tmp_path / "png").exists()  # refused before fitting
    # every module but the drawing ones imports without matplotlib, and none of them loads it
    code = ("import pkgutil, importlib, sys, slipest\n"
            "skip = {'slipest.plotting', 'slipest.offline.replay_plot', 'slipest.diagnosis.plots'}\n"
            "names = [m.name for m in pkgutil.walk_packages(slipest.__path__, 'slipest.') if m.name not in skip]\n"
            "[importlib.import_module(n) for n in names]\n"
            "print(len(names), 'matplotlib' in sys.modules)")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    n, loaded = p.stdout.split()
    assert p.returncode == 0 and int(n) > 50 and loaded == "False", p.stderr
