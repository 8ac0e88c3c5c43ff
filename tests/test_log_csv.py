"""Tests of slipest.io.log_csv: the CSV log format, on real files."""

import io
import math
import os
import re

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from slipest.io.log_csv import (
    DEFAULT_DECIMALS,
    LogFormatError,
    LogMetadata,
    LogReader,
    LogWriter,
    _fixed_point,
    _to_array,
    read_log,
)

# half a unit of the last written decimal, plus float64 rounding of the value
TOL = {c: 0.5 * 10.0 ** -d * (1 + 1e-9) for c, d in DEFAULT_DECIMALS.items()}


def sample_arrays(n=5000, seed=0, t0=0.0):
    rng = np.random.default_rng(seed)
    t = t0 + np.cumsum(rng.uniform(0.0009, 0.0011, n))
    az = 9.81 + rng.normal(0, 20, n)
    theta = -0.3 + 0.63 * (t - t0) + rng.normal(0, 1e-3, n)
    slip = rng.uniform(-1, 1, n)
    return t, az, theta, slip


def assert_close(got, want, col):
    np.testing.assert_allclose(got, want, rtol=0, atol=TOL[col] + 1e-15 * np.nanmax(np.abs(want)))


def write_text(path, text):
    with open(path, "w", encoding="utf-8", newline="") as f:
        f.write(text)
    return str(path)


# ---------------------------------------------------------------------------
# round trip
# ---------------------------------------------------------------------------


def test_round_trip_with_metadata(tmp_path):
    t, az, theta, slip = sample_arrays(20000)
    path = tmp_path / "run.csv"
    with LogWriter(path, ("t", "az", "theta", "slip"), metadata={"nL": 4, "slip": 0.25, "kS": 1000}) as w:
        for i in range(0, t.size, 3000):  # in chunks, as a recorder would
            w.write(t[i : i + 3000], az[i : i + 3000], theta[i : i + 3000], slip=slip[i : i + 3000])
        assert w.rows_written == t.size
    log = read_log(path)
    assert len(log) == t.size
    assert log.columns == ("t", "az", "theta", "slip")
    assert_close(log.t, t, "t")
    assert_close(log.az, az, "az")
    assert_close(log.theta, theta, "theta")
    assert_close(log.slip, slip, "slip")
    assert log.metadata == {"nL": "4", "slip": "0.25", "kS": "1000"}
    assert log.metadata.n_legs == 4
    assert log.metadata.slip == 0.25
    assert log.metadata.get_float("kS") == 1000.0
    assert log.n_skipped == 0 and log.bad_rows == []


def test_file_text_is_plain_fixed_point(tmp_path):
    path = tmp_path / "a.csv"
    with LogWriter(path, metadata={"nL": 4}, comments=["rover A, run 3"]) as w:
        w.write([0.0, 0.001, 3599.999], [9.81, -0.5, np.nan], [0.0, -1e-9, 2268.123456789])
    assert path.read_text() == (
        "# nL=4\n"
        "# rover A, run 3\n"
        "t,az,theta\n"
        "0.000000,9.810000,0.0000000\n"
        "0.001000,-0.500000,0.0000000\n"
        "3599.999000,nan,2268.1234568\n"
    )


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.floats(min_value=0, max_value=1e7, allow_nan=False),
            st.one_of(
                st.floats(min_value=-1e4, max_value=1e4),
                st.sampled_from([math.nan, math.inf, -math.inf]),
            ),
            st.floats(min_value=-1e6, max_value=1e6, allow_nan=False),
        ),
        min_size=0,
        max_size=60,
    )
)
def test_round_trip_property(rows):
    arr = np.array(rows, dtype=np.float64).reshape(-1, 3)
    buf = io.StringIO()
    LogWriter(buf).write_array(arr)
    log = read_log(io.StringIO(buf.getvalue()))
    assert len(log) == arr.shape[0]
    for j, col in enumerate(("t", "az", "theta")):
        got, want = getattr(log, col), arr[:, j]
        fin = np.isfinite(want)
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
        np.testing.assert_array_equal(got[np.isinf(want)], want[np.isinf(want)])
        np.testing.assert_allclose(got[fin], want[fin], rtol=1e-15, atol=TOL[col])


def test_large_values_round_trip(tmp_path):
    """Epoch timestamps (1.7e9 s) keep their microseconds."""
    t, az, theta, _ = sample_arrays(3000, t0=1.7e9)
    path = tmp_path / "epoch.csv"
    with LogWriter(path) as w:
        w.write(t, az, theta)
    log = read_log(path)
    np.testing.assert_allclose(log.t, t, rtol=0, atol=5.1e-7)
    assert np.all(np.diff(log.t) > 0)
    assert_close(log.az, az, "az")


def test_reader_values_equal_python_float(tmp_path):
    """Values are exactly float(text), whether the block is checked at once
    or line by line (the comment at the end sends it line by line)."""
    rng = np.random.default_rng(5)
    fields = []
    for _ in range(3000):
        x = rng.normal(0, 10.0 ** rng.integers(-3, 6))
        fmt = rng.choice(["%.6f", "%.3f", "%.10g", "%r", "%.2e", "%d"])
        fields.append(fmt % (int(x) if fmt == "%d" else x))
    fields += ["nan", "NaN", "-0.0", "5.", "-.25", "0007", "1e3", "+4.5", " 3.25 ", "inf"]
    lines = [f"{i}.0,{f},0.5" for i, f in enumerate(fields)]
    want = np.array([float(f) for f in fields])
    for tail in ("", "# end\n"):
        path = write_text(tmp_path / "mix.csv", "t,az,theta\n" + "\n".join(lines) + "\n" + tail)
        log = read_log(path)
        np.testing.assert_array_equal(log.az, want)
        np.testing.assert_array_equal(np.signbit(log.az), np.signbit(want))


_TOKEN = st.text(alphabet="0123456789.-naN", min_size=1, max_size=18)


def _py_float(tok):
    try:
        return float(tok)
    except ValueError:
        return None


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(_TOKEN, _TOKEN), min_size=1, max_size=30))
def test_any_token_is_read_as_float_or_reported(tmp_path_factory, rows):
    """Whatever the text, the reader returns exactly float(text), or names the
    first line float() cannot read; never a silently wrong number."""
    path = tmp_path_factory.mktemp("tok") / "tok.csv"
    lines = [f"{i},{a},{b}" for i, (a, b) in enumerate(rows)]
    path.write_text("t,az,theta\n" + "\n".join(lines) + "\n")
    parsed = [(_py_float(a), _py_float(b)) for a, b in rows]
    bad = [i for i, (a, b) in enumerate(parsed) if a is None or b is None]
    if bad:
        with pytest.raises(LogFormatError) as ei:
            read_log(path)
        assert ei.value.line == bad[0] + 2
        log = read_log(path, skip_bad=True)
        assert log.n_skipped == len(bad)
        assert [b.line for b in log.bad_rows] == [i + 2 for i in bad[:20]]
    else:
        log = read_log(path)
        want = np.array(parsed, dtype=np.float64).reshape(-1, 2)
        got = np.column_stack([log.az, log.theta])
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(np.signbit(got), np.signbit(want))


# The number grammar (issue 13): plain decimal or exponent notation, nan, inf.
_NUMBER = re.compile(r"[+-]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|nan|inf)", re.IGNORECASE | re.ASCII)


def _ref_number(tok):
    """The reference reading of a field: float(text) if the grammar allows it, else None."""
    core = tok.strip(" \t")
    return float(core) if _NUMBER.fullmatch(core) else None


@pytest.mark.parametrize(
    "tok",
    ["-1.5", ".5", "5.", "-.25", "1e-3", "+2E+05", "1.e5", "0007", "nan", "NaN", "-nan", "+NAN", "inf", "-Inf",
     "+INF", " 3.25\t", "1e400", "-1e-400"],
)
def test_number_grammar_accepts(tmp_path, tok):
    want = float(tok)
    for tail in ("", "# end\n"):
        log = read_log(write_text(tmp_path / "ok.csv", f"t,az,theta\n0,9.81,0\n1,{tok},0\n{tail}"))
        got = log.az[1]
        assert (math.isnan(got) and math.isnan(want)) or (got == want and math.copysign(1, got) == math.copysign(1, want))


@pytest.mark.parametrize(
    "tok",
    ["9_8", "1_000.5", "\uff11\uff12", "\u0663", "1\u0663", "0x1f", "infinity", "Infinity", "nan(1)", "1e", "1e+",
     "e5", ".", "-", "+", "--1", "+-1", "1.2.3", "3 .25", "1 2", "3\u00a0", "\u00a03", "\x0b3", "3\x0c", "1d3",
     "1.5f", "\u0131nf", "na", "nanan", "infe", "1nan", "nan1", "\u2212" + "1"],
)
def test_number_grammar_rejects(tmp_path, tok):
    """Python float() or numpy.loadtxt take several of these (9_8, infinity,
    Unicode digits and spaces): the log format does not."""
    for tail in ("", "# end\n"):
        path = write_text(tmp_path / "bad.csv", f"t,az,theta\n0,9.81,0\n1,9.81,{tok}\n2,9.8,0.1\n{tail}")
        with pytest.raises(LogFormatError) as ei:
            read_log(path)
        assert ei.value.line == 3
        assert ei.value.reason == f"column 'theta': {tok.strip(' ' + chr(9))!r} is not a number"
        log = read_log(path, skip_bad=True)
        assert log.n_skipped == 1 and list(log.t) == [0.0, 2.0]


_NASTY = st.sampled_from(
    list("0123456789") * 3 + list(".+-eE naNAiIfF\t_x,#") + ["nan", "inf", "INF", "infinity", "1e5", "\u00a0",
                                                             "\u0663", "\uff11", "\x0b", ""]
)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.lists(_NASTY, min_size=0, max_size=8).map("".join), min_size=1, max_size=40), st.booleans())
def test_fields_follow_the_grammar_on_both_paths(tmp_path_factory, toks, comment_at_end):
    """Property: a row is read as float(text) iff each field follows the
    grammar, else it is named (line, column, value). Whether the block is
    checked at once (no comment) or line by line (a comment at the end), the
    result is the same."""
    d = tmp_path_factory.mktemp("g")
    lines = [f"{i},{tok},0.5" for i, tok in enumerate(toks)]
    text = "t,az,theta\n" + "\n".join(lines) + "\n" + ("# end\n" if comment_at_end else "")
    path = d / "g.csv"
    path.write_bytes(text.encode("utf-8"))
    want, bad = [], []
    for i, line in enumerate(lines):
        fields = line.split(",")
        if len(fields) != 3:
            bad.append((i + 2, "expected 3 fields"))
            continue
        tok = fields[1]
        if not tok.strip(" \t"):
            bad.append((i + 2, "empty field in required column 'az'"))
            continue
        v = _ref_number(tok)
        if v is None:
            bad.append((i + 2, f"column 'az': {tok.strip(' ' + chr(9))[:40]!r} is not a number"))
        else:
            want.append(v)
    if bad:
        with pytest.raises(LogFormatError) as ei:
            read_log(path)
        assert ei.value.line == bad[0][0] and ei.value.reason.startswith(bad[0][1])
    log = read_log(path, skip_bad=True, max_bad_reported=100)
    assert [(b.line, b.reason[: len(r)]) for b, (_, r) in zip(log.bad_rows, bad)] == bad
    assert log.n_skipped == len(bad)
    np.testing.assert_array_equal(log.az, np.array(want, dtype=np.float64))
    np.testing.assert_array_equal(np.signbit(log.az), np.signbit(np.array(want, dtype=np.float64)))
    assert log.comments == ([(len(lines) + 2, "end")] if comment_at_end else [])


def test_long_line_ending_in_newline_is_an_error(tmp_path):
    """A line over 1 MiB is refused even when its newline comes in the same read."""
    path = tmp_path / "long.csv"
    path.write_bytes(b"t,az,theta\n0,9.81,0\n" + b"7" * ((1 << 20) + 10) + b"\n1,9.81,0\n")
    for block in (1 << 16, 1 << 20, 4 << 20):
        with pytest.raises(LogFormatError) as ei:
            LogReader(path, block_bytes=block).read_all()
        assert ei.value.line == 3 and "longer than" in ei.value.reason
    with pytest.raises(LogFormatError, match="line 3: line longer than"):
        read_log(io.StringIO(path.read_text()))
    path.write_bytes(b"t,az,theta\n0,9.81,0\n1," + b"7" * ((1 << 20) - 8) + b",0\n")  # exactly 1 MiB
    assert len(read_log(path)) == 2


@st.composite
def _fixed_point_blocks(draw):
    """(block, ncols, well_formed): rows of '-?digits.digits' with one number
    of decimals per column, sometimes edited at one place."""
    ncols = draw(st.integers(1, 5))
    decs = draw(st.lists(st.integers(0, 9), min_size=ncols, max_size=ncols))
    nrows = draw(st.integers(1, 12))
    rows = []
    for _ in range(nrows):
        fields = []
        for d in decs:
            ip = draw(st.text("0123456789", min_size=0 if d else 1, max_size=7))
            fp = draw(st.text("0123456789", min_size=d, max_size=d))
            fields.append(draw(st.sampled_from(["", "-"])) + ip + "." + fp)
        rows.append(",".join(fields))
    text = "\n".join(rows) + "\n"
    edit = draw(st.one_of(st.none(), st.tuples(st.integers(0, len(text) - 1), st.sampled_from(list(".-,\n07") + [""]))))
    if edit is not None:
        i, c = edit
        text = text[:i] + c + text[i + 1 :] if draw(st.booleans()) else text[:i] + c + text[i:]
    return text.encode("ascii"), ncols, edit is None


@settings(max_examples=400, deadline=None)
@given(_fixed_point_blocks())
@example((b"1.5,2.25\n1..,5\n", 2, False))  # row 2: a short field whose point would be the previous field's
@example((b"-9223372036854775808.,1.\n", 2, True))  # the int64 minimum, 19 digits
@example((b"-0.000,-.0,-0.\n", 3, True))  # negative zeros
@example((b".-0,0.\n", 2, False))  # a minus inside a field, after its point: no number (CI, 2026-11-23)
def test_fixed_point_path_equals_loadtxt_path(case):
    """The fast path for fixed-point blocks gives bit for bit (sign of zero
    included) what numpy.loadtxt gives, or declines; it does not decline a
    well-formed block of at most 15 digits per field."""
    block, ncols, well_formed = case
    fast = _fixed_point(block, ncols)
    lines = block.decode("ascii").split("\n")[:-1]
    try:
        ref = _to_array(lines, ncols)
    except ValueError:
        ref = None
    if fast is not None:
        assert ref is not None and ref.shape == fast.shape
        np.testing.assert_array_equal(fast.view(np.uint64), ref.view(np.uint64))
    elif well_formed:
        assert max(len(f.replace("-", "").replace(".", "")) for f in block.decode().replace("\n", ",").split(",")[:-1]) > 15


def test_writer_output_takes_the_fixed_point_path():
    t, az, theta, slip = sample_arrays(2000)
    buf = io.BytesIO()
    with LogWriter(buf, ("t", "az", "theta", "slip")) as w:
        w.write(t, -az, theta, slip=slip)
    block = buf.getvalue().split(b"\n", 1)[1]
    fast = _fixed_point(block, 4)
    assert fast is not None
    np.testing.assert_array_equal(fast, _to_array(block.decode().split("\n")[:-1], 4))


def test_endless_line_is_an_error_not_a_memory_hog(tmp_path):
    path = tmp_path / "garbage.csv"
    path.write_bytes(b"t,az,theta\n0,9.81,0\n" + b"7" * (3 << 20))
    with pytest.raises(LogFormatError) as ei:
        LogReader(path, block_bytes=1 << 16).read_all()
    assert ei.value.line == 3 and "longer than" in ei.value.reason


def test_utf8_bom_is_ignored(tmp_path):
    path = tmp_path / "bom.csv"
    path.write_bytes(b"\xef\xbb\xbf# nL=4\nt,az,theta\n0,9.81,0\n")
    log = read_log(path)
    assert log.metadata.n_legs == 4 and len(log) == 1


# ---------------------------------------------------------------------------
# header, columns, comments
# ---------------------------------------------------------------------------


def test_column_order_and_extra_columns(tmp_path):
    text = (
        "# nL=6\n"
        "theta,label,t,slip,current,az\n"
        "0.1,start,0.0,0.2,1.5,9.8\n"
        "0.2,cruise,0.01,0.21,1.25,9.9\n"
    )
    path = write_text(tmp_path / "order.csv", text)
    log = read_log(path)
    np.testing.assert_array_equal(log.t, [0.0, 0.01])
    np.testing.assert_array_equal(log.az, [9.8, 9.9])
    np.testing.assert_array_equal(log.theta, [0.1, 0.2])
    np.testing.assert_array_equal(log.slip, [0.2, 0.21])
    assert log.columns == ("theta", "label", "t", "slip", "current", "az")
    assert log.extras == {}
    assert log.metadata.n_legs == 6
    with LogReader(path, extra_columns=["current"]) as r:
        assert r.extra_names == ("label", "current")
        log2 = r.read_all()
    np.testing.assert_array_equal(log2.extras["current"], [1.5, 1.25])
    # a non-numeric extra column cannot be parsed as numbers
    with pytest.raises(LogFormatError, match="line 3.*'label'"):
        read_log(path, extra_columns=True)
    with pytest.raises(LogFormatError, match="not in the header"):
        LogReader(path, extra_columns=["voltage"])


def test_extra_columns_written_and_read(tmp_path):
    t, az, theta, slip = sample_arrays(500)
    current = np.linspace(0, 3, 500)
    path = tmp_path / "x.csv"
    with LogWriter(path, ("t", "az", "theta", "slip", "current"), decimals={"current": 3}) as w:
        w.write(t, az, theta, slip=slip, current=current)
    log = read_log(path, extra_columns=True)
    np.testing.assert_allclose(log.extras["current"], current, atol=5e-4)
    assert log.slip is not None and read_log(path).extras == {}


def test_no_slip_column_gives_none(tmp_path):
    path = tmp_path / "noslip.csv"
    with LogWriter(path) as w:
        w.write([0.0], [9.81], [0.0])
    log = read_log(path)
    assert log.slip is None and len(log) == 1


def test_comments_and_blank_lines_anywhere(tmp_path):
    text = (
        "# nL=4\n"
        "\n"
        "# operator: Ada\n"
        "# slip = 0.3\n"
        "t,az,theta\n"
        "0.0,9.81,0.0\n"
        "\n"
        "# bump hit here\n"
        "0.001,9.9,0.001\n"
        "0.002,9.7,0.002\n"
    )
    path = write_text(tmp_path / "c.csv", text)
    log = read_log(path)
    np.testing.assert_array_equal(log.t, [0.0, 0.001, 0.002])
    assert log.metadata == {"nL": "4", "slip": "0.3"}
    assert log.metadata.lines == {"nL": 1, "slip": 4}
    assert log.comments == [(1, "nL=4"), (3, "operator: Ada"), (4, "slip = 0.3"), (8, "bump hit here")]


def test_comments_blank_lines_and_text_columns_in_a_big_file(tmp_path):
    """Comments, blank lines, empty optional fields and text in an ignored
    column, scattered over many read blocks: every value and line number right."""
    t, az, theta, slip = sample_arrays(30000, seed=3)
    lines = ["t,az,theta,slip,label"]
    want_comments = []
    for i in range(t.size):
        if i % 7001 == 5:
            lines.append(f"# note {i}")
            want_comments.append((len(lines), f"note {i}"))
        if i % 9001 == 7:
            lines.append("")
        sl = "" if i % 5003 == 11 else f"{slip[i]:.7f}"
        label = "stop" if i % 3 == 0 else "4.5"
        lines.append(f"{t[i]:.6f},{az[i]:.6f},{theta[i]:.7f},{sl},{label}")
    path = write_text(tmp_path / "mixed.csv", "\n".join(lines) + "\n")
    for block in (1 << 20, 5000):
        log = LogReader(path, block_bytes=block).read_all()
        assert log.comments == want_comments
        assert_close(log.t, t, "t")
        assert_close(log.az, az, "az")
        empty = np.arange(t.size) % 5003 == 11
        assert np.isnan(log.slip[empty]).all()
        assert_close(log.slip[~empty], slip[~empty], "slip")
        with pytest.raises(LogFormatError, match="line 2: column 'label': 'stop' is not a number"):
            LogReader(path, extra_columns=True, block_bytes=block).read_all()


def test_writer_comment_between_rows(tmp_path):
    path = tmp_path / "wc.csv"
    with LogWriter(path) as w:
        w.write([0.0], [9.81], [0.0])
        w.comment("paused by operator")
        w.write([1.0], [9.81], [0.5])
    log = read_log(path)
    assert len(log) == 2 and log.comments == [(3, "paused by operator")]


def test_crlf_line_endings(tmp_path):
    path = write_text(tmp_path / "w.csv", "# nL=4\r\nt,az,theta\r\n0.0,9.81,0.0\r\n0.001,9.82,0.001\r\n")
    log = read_log(path)
    np.testing.assert_array_equal(log.az, [9.81, 9.82])
    assert log.metadata.n_legs == 4


def test_last_line_without_newline(tmp_path):
    path = write_text(tmp_path / "nonl.csv", "t,az,theta\n0.0,9.81,0.0\n0.001,9.82,0.001")
    np.testing.assert_array_equal(read_log(path).theta, [0.0, 0.001])


def test_nan_values_pass_through(tmp_path):
    path = write_text(tmp_path / "n.csv", "t,az,theta,slip\n0.0,nan,0.0,0.1\n0.001,NaN,0.001,\n0.002,9.8,nan,nan\n")
    log = read_log(path)
    assert np.isnan(log.az[:2]).all() and log.az[2] == 9.8
    assert np.isnan(log.theta[2])
    assert log.slip[0] == 0.1 and np.isnan(log.slip[1:]).all()  # empty optional field: NaN
    assert log.n_skipped == 0


# ---------------------------------------------------------------------------
# errors
# ---------------------------------------------------------------------------


GOOD = "0.0,9.81,0.0\n"


@pytest.mark.parametrize(
    "bad, reason",
    [
        ("0.001,9.81\n", "expected 3 fields"),
        ("0.001,9.81,0.1,7\n", "expected 3 fields"),
        ("0.001,abc,0.1\n", "column 'az': 'abc' is not a number"),
        ("0.001,9.8.1,0.1\n", "column 'az'"),
        ("0.001,,0.1\n", "empty field in required column 'az'"),
        (",9.81,0.1\n", "empty field in required column 't'"),
        ("0.001,9.81,0x1f\n", "column 'theta'"),
    ],
)
def test_malformed_row_error_names_file_line_reason(tmp_path, bad, reason):
    text = "# nL=4\n# note\nt,az,theta\n" + GOOD * 4 + "\n" + bad + GOOD * 3
    path = write_text(tmp_path / "bad.csv", text)
    with pytest.raises(LogFormatError) as ei:
        read_log(path)
    err = ei.value
    assert isinstance(err, ValueError)
    assert err.line == 9  # 2 comments + header + 4 rows + 1 blank line, then the bad one
    assert reason in err.reason
    assert str(err).startswith(f"{path}, line 9: ")


def test_skip_bad_counts_and_reports(tmp_path):
    rows = [GOOD] * 10
    rows[2] = "0.1,x,0.1\n"
    rows[5] = "0.1,9.8\n"
    rows[7] = "0.1,,0.1\n"
    path = write_text(tmp_path / "skip.csv", "t,az,theta\n" + "".join(rows))
    log = read_log(path, skip_bad=True)
    assert len(log) == 7
    assert log.n_skipped == 3
    assert [b.line for b in log.bad_rows] == [4, 7, 9]
    assert "not a number" in log.bad_rows[0].reason
    assert "expected 3 fields" in log.bad_rows[1].reason
    assert "empty field" in log.bad_rows[2].reason
    r = LogReader(path, skip_bad=True, max_bad_reported=1)
    assert len(r.read_all()) == 7 and r.n_skipped == 3 and len(r.bad_rows) == 1


def test_bad_row_far_into_a_big_file_has_right_line_number(tmp_path):
    """Several read blocks: the block holding the bad row is checked line by
    line and the line named; the rows around it are unchanged."""
    t, az, theta, _ = sample_arrays(60000)
    path = tmp_path / "big.csv"
    with LogWriter(path, metadata={"nL": 4}) as w:
        w.write(t, az, theta)
    lines = path.read_text().splitlines(keepends=True)
    bad_line = 2 + 45678  # 1 comment + header, then row 45678 (1-based)
    lines[bad_line - 1] = "12.5,9.81,oops\n"
    path.write_text("".join(lines))
    for block in (1 << 20, 10000):
        with pytest.raises(LogFormatError) as ei:
            LogReader(path, block_bytes=block).read_all()
        assert ei.value.line == bad_line and "'theta'" in ei.value.reason
        r = LogReader(path, skip_bad=True, block_bytes=block)
        log = r.read_all()
        assert len(log) == 59999 and r.bad_rows[0].line == bad_line
        np.testing.assert_allclose(log.t[45676:45680], np.delete(t, 45677)[45676:45680], atol=1e-6)


def test_missing_required_column(tmp_path):
    path = write_text(tmp_path / "m.csv", "# nL=4\nt,theta,slip\n0,0,0\n")
    with pytest.raises(LogFormatError) as ei:
        read_log(path)
    assert ei.value.line == 2 and "missing required column(s) az" in str(ei.value)
    assert str(path) in str(ei.value)


def test_header_problems(tmp_path):
    with pytest.raises(LogFormatError, match="no header"):
        read_log(write_text(tmp_path / "empty.csv", ""))
    with pytest.raises(LogFormatError, match="no header"):
        read_log(write_text(tmp_path / "comments.csv", "# nL=4\n\n"))
    with pytest.raises(LogFormatError, match="duplicate column"):
        read_log(write_text(tmp_path / "dup.csv", "t,az,theta,az\n"))


def test_bad_metadata_value_names_line(tmp_path):
    path = write_text(tmp_path / "meta.csv", "# slip=0.1\n# nL=four\nt,az,theta\n")
    log = read_log(path)
    with pytest.raises(LogFormatError) as ei:
        log.metadata.n_legs
    assert ei.value.line == 2 and "nL='four'" in str(ei.value)
    assert LogMetadata({"nL": "3"}).n_legs == 3
    assert LogMetadata({}).n_legs is None


def test_not_utf8_is_an_error_with_line(tmp_path):
    path = tmp_path / "bin.csv"
    path.write_bytes(b"t,az,theta\n0.0,9.81,0.0\n0.1,\xff\xfe,0.1\n")
    with pytest.raises(LogFormatError) as ei:
        read_log(path)
    assert ei.value.line == 3


# ---------------------------------------------------------------------------
# chunks, streams, empty logs
# ---------------------------------------------------------------------------


def test_chunked_iteration_equals_whole_read(tmp_path):
    t, az, theta, slip = sample_arrays(50000, seed=2)
    path = tmp_path / "ch.csv"
    with LogWriter(path, ("t", "az", "theta", "slip")) as w:
        w.write(t, az, theta, slip=slip)
    whole = read_log(path)
    for chunk_rows, block in ((65536, 1 << 20), (4096, 4 << 20), (1000, 7777), (1, 100000)):
        r = LogReader(path, block_bytes=block)
        chunks = list(r.iter_chunks(chunk_rows))
        sizes = [len(c) for c in chunks]
        assert all(s == chunk_rows for s in sizes[:-1]) and 0 < sizes[-1] <= chunk_rows
        assert sum(sizes) == len(whole) == r.n_rows
        for col in ("t", "az", "theta", "slip"):
            np.testing.assert_array_equal(np.concatenate([getattr(c, col) for c in chunks]), getattr(whole, col))
        r.close()


def test_reader_can_iterate_only_once(tmp_path):
    path = tmp_path / "once.csv"
    with LogWriter(path) as w:
        w.write([0.0], [9.81], [0.0])
    r = LogReader(path)
    assert len(list(r.iter_chunks())) == 1
    with pytest.raises(RuntimeError, match="only once"):
        r.read_all()
    r.close()


def test_write_to_stdout(capsys):
    w = LogWriter(__import__("sys").stdout, metadata={"nL": 4})
    w.write([0.0, 0.001], [9.81, 9.8], [0.0, 0.00063])
    w.flush()
    w.close()  # does not close stdout
    out = capsys.readouterr().out
    assert out == "# nL=4\nt,az,theta\n0.000000,9.810000,0.0000000\n0.001000,9.800000,0.0006300\n"
    log = read_log(io.StringIO(out))
    np.testing.assert_array_equal(log.az, [9.81, 9.8])


def test_binary_streams(tmp_path):
    buf = io.BytesIO()
    with LogWriter(buf) as w:
        w.write([1.0], [2.0], [3.0])
    assert not buf.closed
    log = read_log(io.BytesIO(buf.getvalue()))
    assert (log.t[0], log.az[0], log.theta[0]) == (1.0, 2.0, 3.0)
    with open(tmp_path / "b.csv", "wb") as f:
        f.write(buf.getvalue())
    with open(tmp_path / "b.csv", "rb") as f:
        assert len(read_log(f)) == 1


def test_empty_log_header_only(tmp_path):
    path = tmp_path / "empty.csv"
    LogWriter(path, ("t", "az", "theta", "slip"), metadata={"nL": 4}).close()
    assert path.read_text() == "# nL=4\nt,az,theta,slip\n"
    log = read_log(path)
    assert len(log) == 0 and log.t.shape == (0,) and log.slip.shape == (0,)
    assert log.metadata.n_legs == 4
    assert list(LogReader(path).iter_chunks()) == []


# ---------------------------------------------------------------------------
# writer behaviour
# ---------------------------------------------------------------------------


def test_writer_never_overwrites_by_accident(tmp_path):
    path = tmp_path / "keep.csv"
    with LogWriter(path) as w:
        w.write([0.0], [9.81], [0.0])
    before = path.read_text()
    with pytest.raises(FileExistsError):
        LogWriter(path)
    assert path.read_text() == before
    with LogWriter(path, overwrite=True) as w:
        w.write([5.0], [9.81], [0.0])
    assert read_log(path).t[0] == 5.0


def test_flush_makes_rows_readable_before_close(tmp_path):
    """What a live recorder relies on: flushed rows are on disk even if the
    process dies before close()."""
    path = tmp_path / "live.csv"
    w = LogWriter(path, metadata={"nL": 4})
    t, az, theta, _ = sample_arrays(1000)
    w.write(t[:600], az[:600], theta[:600])
    w.flush(fsync=True)
    log = read_log(path)  # another reader, while the writer is still open
    assert len(log) == 600
    w2 = LogWriter(tmp_path / "auto.csv", flush_each_write=True)
    w2.write(t[:10], az[:10], theta[:10])
    assert len(read_log(tmp_path / "auto.csv")) == 10
    w.close()
    w2.close()


def test_writer_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="must include"):
        LogWriter(tmp_path / "a.csv", ("t", "az"))
    assert not os.path.exists(tmp_path / "a.csv")
    with pytest.raises(ValueError, match="duplicate"):
        LogWriter(io.StringIO(), ("t", "az", "theta", "t"))
    with pytest.raises(ValueError, match="invalid column name"):
        LogWriter(io.StringIO(), ("t", "az", "theta", "a,b"))
    with pytest.raises(ValueError, match="invalid metadata key"):
        LogWriter(tmp_path / "b.csv", metadata={"n L": 4})
    assert not os.path.exists(tmp_path / "b.csv")  # nothing created on a bad call
    with pytest.raises(ValueError, match="one line"):
        LogWriter(io.StringIO(), metadata={"note": "a\nb"})
    w = LogWriter(io.StringIO(), ("t", "az", "theta", "slip"))
    with pytest.raises(ValueError, match="missing column"):
        w.write([0.0], [1.0], [2.0])
    with pytest.raises(ValueError, match="not in the header"):
        w.write([0.0], [1.0], [2.0], slip=[0.1], speed=[1.0])
    with pytest.raises(ValueError, match="shape"):
        w.write([0.0, 1.0], [1.0], [2.0], slip=[0.1])
    with pytest.raises(ValueError, match="shape"):
        w.write_array(np.zeros((3, 3)))
    w.close()
    with pytest.raises(ValueError, match="closed"):
        w.write([0.0], [1.0], [2.0], slip=[0.1])


def _written_field(x, d):
    """What the log holds for x at d decimals: '%.<d>f', minus sign dropped when it reads as zero."""
    text = "%.*f" % (d, x)
    return text[1:] if text.startswith("-") and float(text) == 0 else text


@settings(max_examples=100, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.floats(allow_nan=True, allow_infinity=True),
            st.floats(min_value=-1e-6, max_value=1e-6),
            st.sampled_from([0.0, -0.0, 0.5, -0.5, 1.5, -2.5, 5e-8, -5e-8, 4.9999999e-7, -4.9999999e-7]),
        ),
        min_size=0,
        max_size=40,
    ),
    st.integers(0, 9),
)
def test_writer_text_is_percent_f_per_column(values, d):
    """Each field is '%.<d>f' of its value (t 6, az 6, theta 7 decimals, the
    extra column d), never '-0.000'."""
    x = np.array(values, dtype=np.float64)
    buf = io.StringIO()
    with LogWriter(buf, ("t", "az", "theta", "x"), decimals={"x": d}) as w:
        w.write(x, -x, x, x=x)
    rows = buf.getvalue().splitlines()
    assert rows[0] == "t,az,theta,x"
    want = [",".join(_written_field(v, k) for v, k in ((a, 6), (-a, 6), (a, 7), (a, d))) for a in values]
    assert rows[1:] == want


def test_writer_default_decimals_per_column():
    buf = io.StringIO()
    with LogWriter(buf, ("t", "az", "theta", "slip", "current")) as w:
        w.write([1 / 3], [2 / 3], [-1 / 3], slip=[1 / 7], current=[-2 / 7])
    assert buf.getvalue().splitlines()[1] == "0.333333,0.666667,-0.3333333,0.1428571,-0.2857143"


def test_writer_formats_special_values(tmp_path):
    buf = io.StringIO()
    with LogWriter(buf) as w:
        w.write([0.0, 1.0, 2.0], [np.inf, -np.inf, -0.0], [-1.5, 1e-12, -1e-12])
    rows = buf.getvalue().splitlines()[1:]
    assert rows == ["0.000000,inf,-1.5000000", "1.000000,-inf,0.0000000", "2.000000,0.000000,0.0000000"]
    assert not any(math.isnan(x) for x in read_log(io.StringIO(buf.getvalue())).az)
