"""One log stream: library (stdlib) records beside structlog's as JSON lines with the same
keys, journald priority prefixes exactly when the stream is the journal, and the rate limit
over both."""

from __future__ import annotations

import io
import json
import logging
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TextIO

import pytest
import structlog
from pymodbus.logging import Log as PymodbusLog

from robocal.daemon import logging as robocal_logging
from robocal.daemon.logging import RateLimiter, configure_logging, journal_priorities
from tests._clock import ManualClock

KEYS = {"timestamp", "level", "logger", "event"}


@pytest.fixture
def configure(monkeypatch: pytest.MonkeyPatch) -> Iterator[Callable[..., None]]:
    """``configure_logging`` for one test; the process's logging is put back afterwards."""
    root = logging.getLogger()
    saved = (list(root.handlers), root.level, logging.getLogger("robocal").level,
             structlog.get_config())
    monkeypatch.setattr(robocal_logging, "_installed", None)
    monkeypatch.delenv("JOURNAL_STREAM", raising=False)
    yield configure_logging
    handlers, level, robocal_level, config = saved
    root.handlers[:] = handlers
    root.setLevel(level)
    logging.getLogger("robocal").setLevel(robocal_level)
    structlog.configure(**config)


@pytest.fixture
def out(tmp_path: Path) -> Iterator[TextIO]:
    """A real file (it has a device and an inode) to log to."""
    with (tmp_path / "daemon.log").open("w+", encoding="utf-8") as f:
        yield f


def _lines(stream: TextIO) -> list[str]:
    stream.flush()
    stream.seek(0)
    return stream.read().splitlines()


def _journal_id(stream: TextIO) -> str:
    st = os.fstat(stream.fileno())
    return f"{st.st_dev}:{st.st_ino}"


def _log_each_level() -> None:
    log = structlog.get_logger("robocal.test")
    log.debug("robocal debug")
    log.info("robocal info")
    logging.getLogger("pymodbus.logging").warning("modbus warning")
    logging.getLogger("aiohttp.server").error("aiohttp error")
    logging.getLogger("asyncio").critical("asyncio critical")


def test_library_records_are_json_lines_beside_structlog(configure, out):
    configure("info", "json", stream=out)
    structlog.get_logger("robocal.daemon.test").info("robocal event", campaign="c1")
    PymodbusLog.warning("Failed to connect {} (test_logging)", "plc:502")
    logging.getLogger("pymodbus.logging").debug("frame dump")  # libraries: warning and up
    structlog.get_logger("robocal.daemon.test").debug("not at info")
    try:
        raise ConnectionResetError("peer went away")
    except ConnectionResetError:
        logging.getLogger("asyncio").exception("Exception in callback %s", "_read_ready")
    lines = _lines(out)
    assert len(lines) == 3, lines
    docs = [json.loads(line) for line in lines]
    assert all(d.keys() >= KEYS for d in docs), docs
    ours, modbus, loop = docs
    assert (ours["logger"], ours["level"], ours["event"], ours["campaign"]) == (
        "robocal.daemon.test", "info", "robocal event", "c1")
    assert (modbus["logger"], modbus["level"], modbus["event"]) == (
        "pymodbus.logging", "warning", "Failed to connect plc:502 (test_logging)")
    assert (loop["logger"], loop["level"], loop["event"]) == (
        "asyncio", "error", "Exception in callback _read_ready")
    assert loop["exception"][0]["exc_type"] == "ConnectionResetError"
    assert modbus["timestamp"].endswith("Z")


def test_tracebacks_leave_out_frame_locals(configure, out):
    """A frame's locals may be a secret (the auth middleware holds the bearer token)."""
    configure("info", "json", stream=out)

    def handler(token: str) -> None:
        got = f"Bearer {token}"
        raise RuntimeError(f"bug after checking {len(got)} bytes")

    for name in ("robocal.daemon.api", "aiohttp.server"):
        try:
            handler("s3cret-token")
        except RuntimeError:
            if name.startswith("robocal"):
                structlog.get_logger(name).exception("request failed")
            else:
                logging.getLogger(name).exception("Error handling request")
    lines = _lines(out)
    assert len(lines) == 2
    for line in lines:
        doc = json.loads(line)
        assert doc["exception"][0]["frames"][-1]["name"] == "handler"
        assert "s3cret" not in line


def test_console_format_carries_library_records_too(configure, out):
    configure("info", "console", stream=out)
    logging.getLogger("aiohttp.server").warning("slow handler")
    (line,) = _lines(out)
    assert "slow handler" in line and "aiohttp.server" in line and "warning" in line


@pytest.mark.parametrize("fmt", ["json", "console"])
def test_journal_priorities_when_journal_stream_names_the_stream(configure, out, monkeypatch,
                                                                 fmt):
    monkeypatch.setenv("JOURNAL_STREAM", _journal_id(out))
    configure("debug", fmt, stream=out)
    _log_each_level()
    lines = _lines(out)
    assert [line[:3] for line in lines] == ["<7>", "<6>", "<4>", "<3>", "<2>"], lines
    if fmt == "json":
        assert [json.loads(line[3:])["level"] for line in lines] == [
            "debug", "info", "warning", "error", "critical"]


@pytest.mark.parametrize("journal", [None, "other-file", "garbage", "12345"])
def test_no_priorities_unless_journal_stream_names_the_stream(configure, out, tmp_path,
                                                              monkeypatch, journal):
    if journal == "other-file":
        with (tmp_path / "elsewhere").open("w") as other:
            monkeypatch.setenv("JOURNAL_STREAM", _journal_id(other))
    elif journal is not None:
        monkeypatch.setenv("JOURNAL_STREAM", journal)
    configure("debug", "json", stream=out)
    _log_each_level()
    lines = _lines(out)
    assert len(lines) == 5
    assert all(line.startswith("{") for line in lines), lines


def test_journal_priorities_checks_device_and_inode(out, tmp_path):
    st = os.fstat(out.fileno())
    assert journal_priorities(out, {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"})
    assert not journal_priorities(out, {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino + 1}"})
    assert not journal_priorities(out, {"JOURNAL_STREAM": f"{st.st_dev + 1}:{st.st_ino}"})
    assert not journal_priorities(out, {})
    assert not journal_priorities(io.StringIO(), {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"})


def test_rate_limit_applies_to_library_and_structlog_records(configure, out):
    clock = ManualClock()
    configure("info", "json", stream=out, burst=3, window_s=10.0, clock=clock)
    modbus = logging.getLogger("pymodbus.logging")
    ours = structlog.get_logger("robocal.test")
    for i in range(10):  # one call site, different arguments: one event
        modbus.warning("no answer from unit %d", i)
        ours.error("accept failed", attempt=i)
    logging.getLogger("aiohttp.server").warning("other event")  # its own budget
    first = [json.loads(line) for line in _lines(out)]
    expected = [e for i in range(3) for e in (f"no answer from unit {i}", "accept failed")]
    assert [d["event"] for d in first] == [*expected, "other event"]
    assert not any("suppressed" in d for d in first)
    clock.advance(10.0)  # next window: the first record says what was dropped
    modbus.warning("no answer from unit %d", 10)
    ours.error("accept failed", attempt=10)
    again: list[dict[str, Any]] = [json.loads(line) for line in _lines(out)[len(first):]]
    assert [(d["logger"], d["suppressed"]) for d in again] == [
        ("pymodbus.logging", 7), ("robocal.test", 7)]


def test_configuring_again_replaces_the_handler(configure, out, tmp_path):
    configure("info", "json", stream=out)
    with (tmp_path / "second.log").open("w+", encoding="utf-8") as second:
        configure("info", "json", stream=second)
        logging.getLogger("pymodbus.logging").warning("only once")
        assert len(_lines(second)) == 1
    assert _lines(out) == []


def test_rate_limiter_counts_what_it_drops():
    lim = RateLimiter(burst=3, window_s=10.0)
    got = [lim.allow("k", now=float(i) * 0.01) for i in range(10)]
    assert got == [0, 0, 0, None, None, None, None, None, None, None]
    assert lim.allow("other", now=0.5) == 0
    assert lim.allow("k", now=11.0) == 7  # next window reports the 7 dropped
