"""Writing files so that a reader never sees half of one; reading TOML files; JSON of numpy.

numpy is imported only where a value may be a numpy one, so that the daemon's configuration
reads its TOML file without loading numpy."""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING, Any

from robocal.errors import ConfigError, FileWriteError

if TYPE_CHECKING:
    from importlib.resources.abc import Traversable


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` via a temporary file in the same directory, then rename.

    The data are flushed to disk before the rename and the directory entry after it, so a
    power cut leaves the old file or the new one. On any error the temporary file is removed
    and ``path`` keeps its previous content (or stays absent). The temporary name is unique
    (``mkstemp``), so two writers never share one. Failures (``path`` a directory, no such
    folder, no permission, disk full) raise :class:`FileWriteError`, also an ``OSError``.
    """
    path = Path(path)
    if path.is_dir():
        raise FileWriteError("is a directory; name a file to write", source=str(path))
    try:
        fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as err:
        raise FileWriteError(f"cannot write: {err.strerror or err}", source=str(path)) from err
    tmp = Path(name)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        # mkstemp creates 0600; a written file gets the permissions an ordinary one would
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except OSError as err:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise FileWriteError(f"cannot write: {err.strerror or err}", source=str(path)) from err
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


def _umask() -> int:
    """The process umask, read without changing it (``os.umask`` would, for every thread)."""
    try:
        with open("/proc/self/status", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    return 0o022


def _fsync_dir(directory: Path) -> None:
    """Make a rename in ``directory`` durable (a no-op where directories cannot be opened)."""
    try:
        dfd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return
    try:
        os.fsync(dfd)
    except OSError:
        pass
    finally:
        os.close(dfd)


def json_default(o: Any) -> Any:
    """``json.dumps(default=...)`` for numpy scalars and arrays and paths."""
    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.floating | np.integer):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def read_text(path: str | Path, *, error: type[ConfigError] = ConfigError,
              encoding: str = "utf-8") -> str:
    """A text file's content; a missing or unreadable file is one ``error`` naming it."""
    try:
        return Path(path).read_text(encoding=encoding)
    except FileNotFoundError as err:
        raise error("file not found", source=str(path)) from err
    except (OSError, UnicodeDecodeError) as err:
        raise error(f"cannot read: {err}", source=str(path)) from err


def read_toml(path: str | Path | Traversable) -> dict[str, Any]:
    """Parse a TOML file or package resource (robot descriptions, cells, the daemon's
    configuration); raise :class:`ConfigError` naming the file and the problem."""
    src = str(path)
    try:
        # binary, as tomllib wants: it decodes UTF-8 itself
        with (Path(path) if isinstance(path, str) else path).open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError as err:
        raise ConfigError("file not found", source=src) from err
    except IsADirectoryError as err:
        raise ConfigError("is a directory, not a TOML file", source=src) from err
    except OSError as err:
        raise ConfigError(f"cannot read: {err}", source=src) from err
    except UnicodeDecodeError as err:
        raise ConfigError(f"not UTF-8 text: {err}", source=src) from err
    except (tomllib.TOMLDecodeError, RecursionError) as err:
        raise ConfigError(f"not valid TOML: {err or 'nested too deeply'}", source=src) from err


def private_dir(path: str | Path, mode: int = 0o750) -> Path:
    """Create ``path`` (and parents) if needed and take away permissions beyond ``mode``.

    An existing directory keeps its owner bits; group and other bits not in ``mode`` are
    removed (a 0755 state directory becomes 0750), whatever the caller's umask.
    """
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True, mode=mode)
    current = stat.S_IMODE(path.stat().st_mode)
    if current & ~mode & 0o077:
        os.chmod(path, current & (mode | 0o700))
    return path


def private_file(path: str | Path, mode: int = 0o600) -> None:
    """Create ``path`` empty if absent and set exactly ``mode`` (a database before SQLite
    opens it, so it never exists with the umask's wider permissions)."""
    path = Path(path)
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, mode)
    try:
        if stat.S_IMODE(os.fstat(fd).st_mode) != mode:
            os.fchmod(fd, mode)
    finally:
        os.close(fd)
