"""Many logs at once: `slipest replay` and `slipest diagnose --per-log` over a folder, in worker processes
and on a real Dask LocalCluster, one table; a log that fails has its error in its row, the others go on."""

from __future__ import annotations

import csv
import io
import json
import math
import os

import pytest

from slipest.cli.main import main
from slipest.offline.diagnose import DIAGNOSE_COLUMNS
from slipest.offline.logs import detect_kind, expand_logs
from slipest.offline.many import run_many
from slipest.offline.replay import TABLE_COLUMNS, Replay, ReplayOptions, replay_rows
from tests.log_makers import can_frames, stream, write_bag, write_can_log, write_csv


@pytest.fixture(scope="module")
def drives(tmp_path_factory):
    """A folder as a rover team keeps it: CSV logs, a CAN log, a ROS 2 bag, a broken file, other files."""
    root = tmp_path_factory.mktemp("drives")
    (root / "day1").mkdir()
    (root / "day2").mkdir()
    s1, sc1 = stream(4, seed=1, slip=[0.2, 0.2, 0.3, 0.3])
    s2, sc2 = stream(4, seed=2, slip=[0.35, 0.35, 0.35, 0.35])
    write_csv(root / "day1" / "a.csv", s1, sc1)
    write_csv(root / "day2" / "b.csv", s2, sc2)
    write_can_log(root / "day2" / "bus.blf", can_frames({0: s1, 1: s2}))
    (root / "day2" / "broken.csv").write_text("t,az\n0,1\n")
    (root / "day1" / "notes.txt").write_text("not a log\n")
    if _have("rosbags"):
        write_bag(root / "day1" / "bag", s2, joints=("wheel_leg",))
    return root


def _have(module: str) -> bool:
    try:
        __import__(module)
    except ImportError:
        return False
    return True


def table(text: str) -> list[dict]:
    return list(csv.DictReader(io.StringIO(text)))


def test_a_folder_expands_to_its_logs_and_kinds_come_from_names_and_headers(drives):
    logs = [os.path.relpath(p, drives) for p in expand_logs([drives])]
    expected = ["day1/a.csv", "day2/b.csv", "day2/broken.csv", "day2/bus.blf"]
    if _have("rosbags"):
        expected.insert(0, "day1/bag")
    assert logs == expected  # sorted per folder, a bag directory counts as one log, notes.txt is no log
    assert [detect_kind(drives / p) for p in ("day1/a.csv", "day2/bus.blf")] == ["slipest", "can"]
    pcsv = write_can_log(drives / "pycan.csv", can_frames({0: stream(1, seed=4)[0]})[:20])
    assert detect_kind(pcsv) == "can"  # python-can's CSV, told by its header
    os.remove(pcsv)
    assert expand_logs([drives / "day1" / "a.csv", drives / "day1"], kinds=("slipest",)) == [
        str(drives / "day1" / "a.csv")]


def test_replay_table_in_worker_processes_one_row_per_log_and_wheel(drives, tmp_path, capsys):
    out = tmp_path / "table.csv"
    rc = main(["replay", str(drives), "-o", str(out), "--jobs", "2", "--truth", "--slip-topic", "/slip"])
    _, err = capsys.readouterr()
    assert rc == 1  # one log failed: its row says why, the others are there
    rows = table(out.read_text())
    assert tuple(rows[0]) == TABLE_COLUMNS
    by = {(os.path.relpath(r["log"], drives), r["wheel"]): r for r in rows}
    broken = by[("day2/broken.csv", "")]
    assert broken["verdict"] == "error" and "missing required column(s) theta" in broken["error"]
    assert broken["kind"] == "slipest"
    assert {k for k in by if k[0] == "day2/bus.blf"} == {("day2/bus.blf", "0"), ("day2/bus.blf", "1")}
    # each row is what a single replay of that log finds
    for key in [("day1/a.csv", ""), ("day2/b.csv", ""), ("day2/bus.blf", "1")]:
        with Replay(drives / key[0], ReplayOptions(truth=True)) as r:
            res = r.run()
        (single,) = [x for x in res.rows() if str(x["wheel"]) == key[1]]
        row = by[key]
        assert row["verdict"] == "ok" and int(row["cycles"]) == single["cycles"]
        assert int(row["estimated"]) == single["estimated"] >= 2
        assert float(row["mean_slip"]) == pytest.approx(single["mean_slip"], rel=1e-5)
        assert float(row["dphi"]) == pytest.approx(single["dphi"], rel=1e-5)
        assert float(row["slip_rmse"]) == pytest.approx(single["slip_rmse"], rel=1e-5) and single["slip_rmse"] < 0.1
    assert float(by[("day2/b.csv", "")]["mean_slip"]) == pytest.approx(0.35, abs=0.08)
    n_logs = 5 if _have("rosbags") else 4
    assert f"replay: {n_logs} logs" in err and "1 log(s) failed" in err and "broken.csv" in err


def test_replay_table_on_a_dask_local_cluster_equals_the_process_pool(drives, tmp_path, capsys):
    distributed = pytest.importorskip("distributed")
    logs = [str(drives / "day1" / "a.csv"), str(drives / "day2" / "bus.blf"), str(drives / "day2" / "broken.csv")]
    rc = main(["replay", *logs, "--format", "jsonl", "--jobs", "2", "--no-progress"])
    pool_out, _ = capsys.readouterr()
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        rc_dask = main(["replay", *logs, "--format", "jsonl", "--scheduler", cluster.scheduler_address])
        dask_out, err = capsys.readouterr()
        with distributed.Client(cluster) as client:
            ran_on = {w["id"] for w in client.scheduler_info()["workers"].values()}
            assert len(ran_on) == 2 and sum(client.run(lambda: 1).values()) == 2
    assert rc == rc_dask == 1
    pool_rows = [json.loads(line) for line in pool_out.splitlines()]
    dask_rows = [json.loads(line) for line in dask_out.splitlines()]
    strip = lambda rows: [{k: v for k, v in r.items() if k != "seconds"} for r in rows]  # noqa: E731
    assert strip(dask_rows) == strip(pool_rows) and len(dask_rows) == 4
    assert [r["log"] for r in dask_rows] == [logs[0], logs[1], logs[1], logs[2]]  # the order of the logs
    assert dask_rows[-1]["verdict"] == "error" and dask_rows[0]["verdict"] == "ok"
    assert dask_rows[0]["kS"] is not None and math.isfinite(dask_rows[0]["kS"])
    assert "replay" in err  # the progress bar


def test_an_unreachable_scheduler_is_a_clear_error(drives):
    pytest.importorskip("distributed")
    with pytest.raises(OSError, match="cannot reach the Dask scheduler at tcp://127.0.0.1:9"):
        run_many(replay_rows, [drives / "day1" / "a.csv"], ReplayOptions(), columns=TABLE_COLUMNS,
                 scheduler="tcp://127.0.0.1:9", progress=False, connect_timeout=1)


def dies_on_crash(log, options):
    """A worker whose process dies on logs named crash*: what a crash in compiled code does."""
    if os.path.basename(log).startswith("crash"):
        os._exit(3)
    return [{"log": log, "verdict": "ok", "pid": os.getpid()}]


def test_a_worker_process_that_dies_costs_only_its_own_log(tmp_path):
    logs = [str(tmp_path / n) for n in ("a.csv", "b.csv", "crash.csv", "c.csv", "d.csv")]
    rows = run_many(dies_on_crash, logs, None, columns=("log", "verdict", "error"), jobs=2, progress=False)
    assert [r["log"] for r in rows] == logs
    assert [r["verdict"] for r in rows] == ["ok", "ok", "error", "ok", "ok"]
    assert "worker process died" in rows[2]["error"]
    assert all(r["pid"] != os.getpid() for r in rows if r["verdict"] == "ok")  # in worker processes


def test_diagnose_per_log_writes_one_row_per_log(drives, tmp_path, capsys):
    out = tmp_path / "diag.csv"
    rc = main(["diagnose", "--per-log", str(drives), "-o", str(out), "--jobs", "2", "--quick", "--effects",
               "imu_saturation", "--no-progress"])
    _, err = capsys.readouterr()
    assert rc == 1
    rows = table(out.read_text())
    assert tuple(rows[0]) == DIAGNOSE_COLUMNS
    by = {os.path.relpath(r["log"], drives): r for r in rows}
    assert set(by) == {"day1/a.csv", "day2/b.csv", "day2/broken.csv"}  # CSV logs only
    for name, slip in (("day1/a.csv", 0.25), ("day2/b.csv", 0.35)):
        r = by[name]
        assert r["verdict"] in ("none", "imu_saturation", "unexplained") and r["error"] == ""
        assert int(r["cycles"]) >= 3 and float(r["mean_slip"]) == pytest.approx(slip, abs=0.06)
        assert 0.0 < float(r["dphi"]) < 1.0 and float(r["kS"]) > 0 and float(r["gap_nominal_mg"]) >= 0
        assert int(r["swap_steps"]) >= 0 and r["swap_offset_ms"] != ""  # the leg swaps read (NaN: no step)
    assert by["day2/broken.csv"]["verdict"] == "error" and "theta" in by["day2/broken.csv"]["error"]
    assert "diagnose: 3 logs:" in err and "error 1" in err
