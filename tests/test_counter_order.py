"""Frames a link sent or logged a few frames late are put back in counter order (CounterOrder, WheelStream, CAN
replay); frames in order pass unchanged, and a frame later than the window is lost as before."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipest.io.can_messages import IMU_SAMPLE, REORDER_FRAMES, frame_id
from slipest.io.counter_order import CounterOrder
from slipest.io.device_stream import WheelStream
from slipest.offline.replay import Replay
from tests.log_makers import can_frames, stream, write_can_log
from tests.test_wheel_stream_restarts import feed, feed_frames, late_frames

M = 256


def run(order: CounterOrder, seqs, splits=(10**9,)) -> list:
    """The counters ``order`` hands on for ``seqs`` split into calls of the sizes ``splits`` (cycled), then
    its flush; each frame's field is its arrival index."""
    out, i, k = [], 0, 0
    while i < len(seqs):
        j = min(len(seqs), i + splits[k % len(splits)])
        got, (idx,) = order.order(list(seqs[i:j]), (list(range(i, j)),))
        assert [seqs[a] for a in idx] == got  # each frame's fields travel with its counter
        out += got
        i, k = j, k + 1
    got, fields = order.flush()
    return out + got


def test_frames_in_order_pass_unchanged_and_at_once():
    order = CounterOrder(M, 4)
    seqs = [(250 + i) % M for i in range(600)]
    fields = (list(range(600)),)
    assert order.order(seqs, fields) == (seqs, fields)  # the same lists: nothing copied
    got, more = order.order([(250 + 600) % M], ([600],))
    assert got == [(250 + 600) % M] and more == ([600],) and len(order) == 0


@settings(max_examples=200, deadline=None)
@given(start=st.integers(0, M - 1), blocks=st.lists(st.integers(1, REORDER_FRAMES), min_size=1, max_size=80),
       seed=st.integers(0, 2**32 - 1), splits=st.lists(st.integers(1, 50), min_size=1, max_size=10))
def test_frames_shuffled_within_the_window_come_out_in_counter_order(start, blocks, seed, splits):
    """After a first frame (the order starts from it), blocks of up to ``window`` consecutive frames, each
    shuffled: no frame comes later than the window allows, so every one is put back, whatever the calls."""
    rng = np.random.default_rng(seed)
    n = 1 + sum(blocks)
    arrival, i = [0], 1
    for b in blocks:
        arrival += list(rng.permutation(np.arange(i, i + b)))
        i += b
    seqs = [(start + int(a)) % M for a in arrival]
    order = CounterOrder(M, REORDER_FRAMES)
    assert run(order, seqs, splits) == [(start + a) % M for a in range(n)]
    assert order.duplicates == 0 and len(order) == 0


def test_a_lost_frame_a_duplicate_and_a_restart_keep_the_arrival_order():
    """What the stage cannot mend it hands on in arrival order, as without it (the stream's rules see them)."""
    lost = [1, 2, 3, 5, 6, 7, 8, 9, 10, 11]  # 4 never came: given up once 4 frames wait for it
    assert run(CounterOrder(M, 4), lost) == lost
    dup = [1, 2, 3, 3, 4, 5]  # a duplicate of the last frame goes on at once: the stream drops it
    assert run(CounterOrder(M, 4), dup, (1,)) == dup
    restart = [100, 101, 102, 0, 1, 2, 3, 4]  # the counter started again: followed from its second frame on
    order = CounterOrder(M, 4)
    assert run(order, restart, (1,)) == restart and order.reordered == 0
    late = [1, 2, 4, 5, 6, 7, 3, 8]  # 3 came later than the window: given up, then handed on behind
    assert run(CounterOrder(M, 4), late) == [1, 2, 4, 5, 6, 7, 3, 8]


def test_a_held_duplicate_is_dropped():
    order = CounterOrder(M, 4)
    assert run(order, [1, 3, 3, 2, 4]) == [1, 2, 3, 4] and order.duplicates == 1 and order.reordered == 1


@pytest.mark.parametrize("bad", [(4, 1), (M, 0), (M, M // 4 + 1)])
def test_a_window_the_counter_cannot_tell_apart_is_refused(bad):
    with pytest.raises(ValueError, match="window"):
        CounterOrder(*bad)


@pytest.mark.parametrize("one_by_one", [False, True])
def test_can_frames_a_few_late_are_put_back_and_lose_nothing(one_by_one):
    cols, az, late = late_frames(6000, REORDER_FRAMES - 1)
    s_ = WheelStream(seq_modulus=M, time_modulus=0.65536, reorder_window=REORDER_FRAMES)
    s = feed_frames(s_, cols, one_by_one)
    c = s_.counters()
    assert c["reordered"] == len(late) and c["out_of_order"] == 0 and c["frames_lost"] == 0
    np.testing.assert_array_equal(s.az, az)  # every sample in its place, none a NaN


def test_a_frame_later_than_the_window_is_lost_as_without_it():
    cols, az, late = late_frames(6000, REORDER_FRAMES + 1)
    got = []
    for window in (0, REORDER_FRAMES):
        s_ = WheelStream(seq_modulus=M, time_modulus=0.65536, reorder_window=window)
        got.append(feed(s_, [cols], [cols[4]]))
        c = s_.counters()
        assert c["out_of_order"] == len(late) and c["frames_lost"] == len(late) and c["reordered"] == 0
    for f in ("t", "az", "theta", "filled"):
        np.testing.assert_array_equal(getattr(got[0], f), getattr(got[1], f))
    assert np.isnan(got[1].az[late]).all()


def test_a_can_log_with_swapped_frames_replays_as_the_log_in_order(tmp_path):
    """A logger that wrote every fourth frame of each wheel after the next one: every cycle estimated as from
    the log in order, none flagged for lost samples, and the summary says how many frames were put back."""
    s, _ = stream(n_cycles=6)
    frames = can_frames({0: s, 1: s})
    swapped = list(frames)
    n_swaps = 0
    for wheel in (0, 1):
        at = [i for i, m in enumerate(frames) if m.arbitration_id == frame_id(IMU_SAMPLE, wheel)]
        for k in range(1, len(at) - 1, 4):  # from the second: the first frame sets the order
            swapped[at[k]], swapped[at[k + 1]] = frames[at[k + 1]], frames[at[k]]
            n_swaps += 1
    runs = []
    for name, fr in (("order.blf", frames), ("swapped.blf", swapped)):
        got = []
        result = Replay(write_can_log(tmp_path / name, fr)).run(lambda wheel, e: got.append((wheel, e)))
        runs.append((got, result))
    (ref, _), (got, result) = runs
    assert len(got) == len(ref) >= 10
    assert [(w, e.slip, e.quality) for w, e in got] == [(w, e.slip, e.quality) for w, e in ref]
    assert all(e.quality == "ok" for _, e in got)
    n_put_back = sum(w.stream_counters["reordered"] for w in result.wheels.values())
    assert n_put_back == n_swaps and any(f"{n_swaps // 2} put back in order" in line for line in result.summary_lines())
