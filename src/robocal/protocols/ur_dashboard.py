"""Sans-I/O codec of the Universal Robots Dashboard server (TCP port 29999).

Text lines ending in LF each way; the server greets with ``Connected: Universal Robots
Dashboard Server`` and answers every command with exactly one line (e-Series 5.x wording,
``docs/protocols/universal-robots.md``). Commands are matched case-insensitively here, as
PolyScope does for its command words.
"""

from __future__ import annotations

from dataclasses import dataclass

from robocal.errors import UnexpectedReply

__all__ = [
    "DEFAULT_PORT",
    "GREETING",
    "Command",
    "parse_command",
    "parse_program_state",
    "parse_robot_mode",
    "parse_safety",
    "parse_true",
]

DEFAULT_PORT = 29999
GREETING = "Connected: Universal Robots Dashboard Server"
MAX_LINE = 4096

# Command words, longest first so "power on" wins over "power".
_COMMANDS = (
    "unlock protective stop", "close safety popup", "is in remote control",
    "get loaded program", "get serial number", "get robot model", "restart safety",
    "brake release", "close popup", "power off", "power on", "polyscopeversion",
    "programstate", "isprogramsaved", "safetystatus", "safetymode", "setuserrole",
    "robotmode", "addtolog", "shutdown", "running", "popup", "pause", "play", "stop",
    "load", "quit",
)


@dataclass(frozen=True, slots=True)
class Command:
    """A parsed dashboard command: its normalised word(s) and the argument text."""

    word: str
    argument: str


def parse_command(line: bytes | str) -> Command | None:
    """Return the command of a received line, or None when it is not one the server knows."""
    text = (line.decode("utf-8", errors="replace") if isinstance(line, bytes) else line).strip()
    low = text.lower()
    for word in _COMMANDS:
        if low == word or low.startswith(word + " "):
            return Command(word, text[len(word):].strip())
    return None


def encode(line: str) -> bytes:
    """One line for the wire (LF-terminated)."""
    if "\n" in line or "\r" in line:
        raise ValueError("a dashboard line must not contain CR or LF")
    return line.encode("utf-8") + b"\n"


def parse_true(reply: str) -> bool:
    """``true``/``false`` replies (``is in remote control``, ``running``)."""
    return "true" in reply.lower()


def parse_robot_mode(reply: str) -> str:
    """``Robotmode: RUNNING`` -> ``"RUNNING"``."""
    head, sep, mode = reply.partition(":")
    if not sep or head.strip().lower() != "robotmode":
        raise UnexpectedReply(f"not a robotmode reply: {reply!r}")
    return mode.strip().upper()


def parse_safety(reply: str) -> str:
    """``Safetystatus: NORMAL`` or ``Safetymode: NORMAL`` -> ``"NORMAL"``."""
    head, sep, mode = reply.partition(":")
    if not sep or head.strip().lower() not in ("safetystatus", "safetymode"):
        raise UnexpectedReply(f"not a safety reply: {reply!r}")
    return mode.strip().upper()


def parse_program_state(reply: str) -> tuple[str, str]:
    """``PLAYING calib.urp`` -> ``("PLAYING", "calib.urp")`` (program may be ``<unnamed>``)."""
    state, _, program = reply.strip().partition(" ")
    if state.upper() not in ("STOPPED", "PLAYING", "PAUSED"):
        raise UnexpectedReply(f"not a programState reply: {reply!r}")
    return state.upper(), program.strip()
