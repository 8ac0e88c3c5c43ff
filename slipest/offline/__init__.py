"""Work on what a rover recorded: replay logs through the estimator, diagnose them, many at once.

What a program needs, without :mod:`slipest.cli`::

    from slipest.offline.replay import Replay, ReplayOptions

    with Replay("drive.blf", ReplayOptions(truth=True)) as replay:      # or a .csv log, a ROS 2 bag
        result = replay.run(on_estimate=lambda wheel, est: print(wheel, est.cycle, est.slip))
    print("\\n".join(result.summary_lines()))

    from slipest.offline.many import run_many
    from slipest.offline.replay import TABLE_COLUMNS, replay_rows
    rows = run_many(replay_rows, ["a.blf", "b.mcap"], ReplayOptions(), columns=TABLE_COLUMNS)

Modules:

* :mod:`slipest.offline.logs`: which kind a log is (slipest CSV, python-can
  log, ROS 2 bag); the logs in a folder;
* :mod:`slipest.offline.replay`: :class:`~slipest.offline.replay.Replay`,
  one log through the estimator (a CAN log through the live runtime's own
  frames -> samples path); its summary and table rows;
* :mod:`slipest.offline.diagnose`: the sim-to-real diagnosis of log files,
  together or one at a time;
* :mod:`slipest.offline.many`: one worker call per log in worker processes
  or on a Dask cluster; the table;
* :mod:`slipest.offline.replay_plot`: the picture of a replay (matplotlib).

The readers are in :mod:`slipest.io` (:mod:`~slipest.io.log_csv`,
:mod:`~slipest.io.can_log`, :mod:`~slipest.io.rosbag`).
"""
