"""LineFramer: CR LF framing, maximum length, resynchronisation."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from robocal.errors import FramingError, ProtocolError
from robocal.protocols import LineFramer


def drain(framer: LineFramer) -> list[bytes | str]:
    return [("ERR" if isinstance(x, FramingError) else x) for x in framer.lines()]


def test_encode_appends_crlf_and_rejects_embedded_line_ends():
    f = LineFramer(max_length=10)
    assert f.encode(b"1 HELLO") == b"1 HELLO\r\n"
    assert f.encode("abc") == b"abc\r\n"
    for bad in (b"a\r\nb", b"a\nb", b"a\rb", b"x" * 11):
        with pytest.raises(FramingError):
            f.encode(bad)


def test_lines_split_across_chunks_and_lf_only():
    f = LineFramer()
    f.feed(b"1 OK a=1\r")
    assert drain(f) == []
    f.feed(b"\n2 OK\n3 O")
    assert drain(f) == [b"1 OK a=1", b"2 OK"]
    f.feed(b"K\r\n")
    assert drain(f) == [b"3 OK"]
    assert f.buffered == 0


def test_overlong_complete_line_raises_once_and_resyncs():
    f = LineFramer(max_length=8)
    f.feed(b"123456789\r\nshort\r\n")
    assert drain(f) == ["ERR", b"short"]


def test_overlong_partial_line_is_discarded_until_next_line_end():
    f = LineFramer(max_length=8)
    f.feed(b"x" * 20)
    assert drain(f) == ["ERR"]
    f.feed(b"y" * 50)  # still the same bad line: no second error, nothing buffered
    assert drain(f) == []
    assert f.buffered == 0
    f.feed(b"yy\r\nok\r\n")
    assert drain(f) == [b"ok"]


def test_exactly_max_length_with_pending_cr_is_accepted():
    f = LineFramer(max_length=4)
    f.feed(b"abcd\r")
    assert drain(f) == []
    f.feed(b"\n")
    assert drain(f) == [b"abcd"]


def test_error_carries_recent_frames():
    f = LineFramer(max_length=4)
    f.feed(b"ok\r\ntoolong\r\n")
    items = list(f.lines())
    assert items[0] == b"ok"
    err = items[1]
    assert isinstance(err, FramingError)
    assert b"< ok" in err.last_frames


@given(st.lists(st.binary(max_size=40), max_size=30), st.integers(1, 64))
def test_arbitrary_bytes_only_raise_framing_errors(chunks, max_length):
    f = LineFramer(max_length=max_length)
    for chunk in chunks:
        f.feed(chunk)
        # drain: an error is raised once per over-long line, then reading continues
        for _ in range(len(chunk) + 2):
            try:
                if f.next_line() is None:
                    break
            except ProtocolError:
                continue
    assert f.buffered <= max_length + 1 or f.buffered == 0


@given(
    st.lists(
        st.binary(max_size=30).filter(lambda b: b"\n" not in b and b"\r" not in b), max_size=20
    ),
    st.data(),
)
def test_round_trip_with_arbitrary_chunking(lines, data):
    f = LineFramer(max_length=30)
    wire = b"".join(f.encode(line) for line in lines)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(wire)), max_size=10)))
    got: list[bytes] = []
    prev = 0
    for cut in [*cuts, len(wire)]:
        f.feed(wire[prev:cut])
        prev = cut
        got += [x for x in f.lines() if isinstance(x, bytes)]
    assert got == lines
