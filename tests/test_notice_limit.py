"""NoticeLimiter: three notices of a kind at once, then one per ten seconds, the rest counted and summed up."""

from slipest.io.notice_limit import NOTICE_BURST, NOTICE_INTERVAL, NoticeLimiter


def test_a_kind_gets_a_burst_then_one_per_interval_and_the_rest_is_summed_up():
    now = [0.0]
    lim = NoticeLimiter(clock=lambda: now[0])
    said = [lim.admit(f"restart {i}", "restart") for i in range(10)]
    assert said[:NOTICE_BURST] == [f"restart {i}" for i in range(NOTICE_BURST)]
    assert said[NOTICE_BURST:] == [None] * (10 - NOTICE_BURST) and lim.suppressed == 10 - NOTICE_BURST
    assert lim.admit("late", "other kind") == "late"  # kinds are limited apart
    now[0] = NOTICE_INTERVAL
    assert lim.admit("restart 10", "restart") == f"restart 10 ({10 - NOTICE_BURST} more like it not shown)"
    assert lim.admit("restart 11", "restart") is None
    assert lim.left_out() == ["1 more like this not shown, the last: restart 11"] and lim.left_out() == []
