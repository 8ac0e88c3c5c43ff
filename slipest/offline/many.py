"""Many logs at once: one worker call per log, in parallel processes or on a Dask cluster, one table.

:func:`run_many` calls ``worker(log, options)`` (a module-level function
that returns the log's table rows and reports its own errors in them, e.g.
:func:`slipest.offline.replay.replay_rows`) for every log:

* by default in worker processes on this machine
  (:class:`concurrent.futures.ProcessPoolExecutor`, ``jobs`` of them,
  started by the ``forkserver`` method where the platform has it, so
  no thread state of the caller is forked); ``jobs=1`` runs in this process;
* with ``scheduler`` (a Dask scheduler address, ``tcp://host:8786``) on that
  existing cluster through ``dask.distributed`` (an optional extra:
  ``pip install 'slipest[dask]'``): the same worker function, submitted
  with ``Client.submit``; the cluster's workers need slipest installed and
  the logs at the same paths.

Progress goes to a tqdm bar on stderr.  A log whose worker fails anyway (a
worker process that died, a task the cluster lost) gets an error row with
what happened; the other logs go on (a dead process takes the logs it was
given with it: they are run again, one process each).  The rows come back in the order of
the logs.  :func:`write_table` writes them as CSV or JSON lines.
"""

from __future__ import annotations

import json
import math
import multiprocessing
import os
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from typing import Callable, Sequence

from slipest.extras import import_extra

__all__ = ["run_many", "save_table", "write_table", "format_cell", "is_table"]


def is_table(path, columns: Sequence[str]) -> bool:
    """Whether the file ``path`` is a table this module wrote with these ``columns`` (its first line is
    their CSV header, or a JSON line with exactly these keys): a command's own earlier output."""
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            first = fh.readline().strip()
    except OSError:
        return False
    if first == ",".join(columns):
        return True
    try:
        rec = json.loads(first)
    except ValueError:
        return False
    return isinstance(rec, dict) and list(rec) == list(columns)


def _error_row(log, exc: BaseException, columns) -> dict:
    row = dict.fromkeys(columns, "")
    row.update(log=str(log), verdict="error", error=f"{type(exc).__name__}: {exc}")
    return row


def _share_cores(threads: int) -> None:
    """Worker-process start: the compiled parallel loops (numba) use this many threads, so that
    ``jobs`` processes share the cores instead of each taking all of them."""
    import numba

    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))


def _context():
    methods = multiprocessing.get_all_start_methods()
    return multiprocessing.get_context("forkserver" if "forkserver" in methods else "spawn")


def _bar(total: int, desc: str, progress: bool):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="log", file=sys.stderr, disable=not progress, leave=False,
                mininterval=0.5)


def run_many(worker: Callable, logs: Sequence[str], options, *, columns: Sequence[str], jobs: int | None = None,
             scheduler: str | None = None, progress: bool = True, desc: str = "logs",
             connect_timeout: float = 10.0) -> list[dict]:
    """``worker(log, options)`` for every log (see the module docstring); the rows, in log order.

    ``columns``: the table's columns (for the rows of logs whose worker failed).  ``jobs``: worker
    processes (None: the machine's cores, at most one per log).  ``scheduler``: a Dask scheduler's
    address (then ``jobs`` is ignored); :class:`~slipest.extras.MissingExtra` without dask.distributed,
    ``OSError`` when the scheduler cannot be reached within ``connect_timeout`` seconds."""
    logs = [str(log) for log in logs]
    results: list[list[dict] | None] = [None] * len(logs)
    if not logs:
        return []
    if scheduler:
        _run_dask(worker, logs, options, columns, scheduler, progress, desc, results, connect_timeout)
    else:
        jobs = min(jobs or os.cpu_count() or 1, len(logs))
        if jobs <= 1:
            with _bar(len(logs), desc, progress) as bar:
                for i, log in enumerate(logs):
                    try:
                        results[i] = worker(log, options)
                    except Exception as exc:  # a worker that did not report its own error: its row says it
                        results[i] = [_error_row(log, exc, columns)]
                    bar.update()
        else:
            _run_pool(worker, logs, options, columns, jobs, progress, desc, results)
    return [row for rows in results for row in rows]


def _pool(jobs: int) -> ProcessPoolExecutor:
    threads = max(1, (os.cpu_count() or 1) // jobs)
    return ProcessPoolExecutor(max_workers=jobs, mp_context=_context(), initializer=_share_cores, initargs=(threads,))


def _run_pool(worker, logs, options, columns, jobs, progress, desc, results) -> None:
    """The logs in ``jobs`` worker processes.  A worker process that dies (a crash in compiled code, the
    out-of-memory killer) breaks the pool and every log still in it; those logs are then run again,
    each in a process of its own, so that only the one that kills its process gets an error row."""
    broken = []
    with _bar(len(logs), desc, progress) as bar:
        with _pool(jobs) as pool:
            futures = {pool.submit(worker, log, options): i for i, log in enumerate(logs)}
            for fut in as_completed(futures):
                i = futures[fut]
                try:
                    results[i] = fut.result()
                except BrokenProcessPool:
                    broken.append(i)
                    continue
                except Exception as exc:  # a worker that did not report its own error: its row says it
                    results[i] = [_error_row(logs[i], exc, columns)]
                bar.update()
        for i in sorted(broken):
            with _pool(1) as alone:
                try:
                    results[i] = alone.submit(worker, logs[i], options).result()
                except BrokenProcessPool:
                    results[i] = [_error_row(logs[i], RuntimeError("its worker process died (twice: once with "
                                                                   "other logs, once alone)"), columns)]
                except Exception as exc:
                    results[i] = [_error_row(logs[i], exc, columns)]
            bar.update()


def _run_dask(worker, logs, options, columns, scheduler, progress, desc, results, connect_timeout) -> None:
    distributed = import_extra("distributed", "dask", "running on a Dask cluster")
    try:
        client = distributed.Client(scheduler, timeout=f"{connect_timeout}s")
    except (OSError, TimeoutError) as exc:
        raise OSError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
    with client:
        futures = {client.submit(worker, log, options, pure=False): i for i, log in enumerate(logs)}
        with _bar(len(logs), desc, progress) as bar:
            for fut in distributed.as_completed(list(futures)):
                i = futures[fut]
                try:
                    results[i] = fut.result()
                except Exception as exc:  # a task the cluster lost, or a worker that raised
                    results[i] = [_error_row(logs[i], exc, columns)]
                bar.update()


def format_cell(v) -> str:
    """One table value as CSV text: floats with 6 significant digits, NaN as ``nan``."""
    if isinstance(v, bool):
        return "1" if v else "0"
    if isinstance(v, float):
        return "nan" if v != v else f"{v:.6g}"
    return str(v)


def write_table(rows: Sequence[dict], columns: Sequence[str], stream, fmt: str = "csv") -> None:
    """The rows as CSV (a header line, then one line per row; text fields quoted when needed) or as
    JSON lines (NaN as null)."""
    if fmt == "jsonl":
        for row in rows:
            rec = {c: (None if isinstance(row.get(c), float) and not math.isfinite(row[c]) else row.get(c))
                   for c in columns}
            stream.write(json.dumps(rec, allow_nan=False) + "\n")
        return
    import csv

    w = csv.writer(stream, lineterminator="\n")
    w.writerow(columns)
    for row in rows:
        w.writerow([format_cell(row.get(c, "")) for c in columns])


def save_table(rows: Sequence[dict], columns: Sequence[str], output: str, fmt: str = "csv") -> None:
    """:func:`write_table` to the file ``output`` (``"-"``: stdout)."""
    if output == "-":
        write_table(rows, columns, sys.stdout, fmt)
        return
    with open(output, "w", encoding="utf-8", newline="\n") as out:
        write_table(rows, columns, out, fmt)
