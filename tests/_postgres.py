"""A throw-away PostgreSQL server for tests: ``initdb`` in a temporary directory, ``pg_ctl``
on 127.0.0.1 and a free port, trust authentication, removed at the end.

The server binaries are looked up on PATH, with ``pg_config --bindir`` and in Debian's
``/usr/lib/postgresql/*/bin``; tests that need the server are skipped (with that reason) only
when none is found. PostgreSQL refuses to run as root: as root the cluster is owned by, and
run as, the ``postgres`` user (or ``nobody``) through ``runuser``.
"""

from __future__ import annotations

import contextlib
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

__all__ = ["PostgresServer", "find_bindir", "postgres_server"]


def find_bindir() -> Path | None:
    """The directory holding ``initdb`` and ``pg_ctl``, or None."""
    on_path = shutil.which("initdb")
    if on_path and shutil.which("pg_ctl"):
        return Path(on_path).parent
    pg_config = shutil.which("pg_config")
    if pg_config:
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            out = subprocess.run([pg_config, "--bindir"], capture_output=True, text=True,
                                 timeout=10, check=True).stdout.strip()
            if (Path(out) / "initdb").exists():
                return Path(out)
    found = sorted(Path("/usr/lib/postgresql").glob("*/bin/initdb"),
                   key=lambda p: int(p.parent.parent.name) if p.parent.parent.name.isdigit()
                   else 0)
    return found[-1].parent if found else None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class PostgresServer:
    """One cluster; :meth:`stop` and :meth:`start` restart it on the same port."""

    def __init__(self, bindir: Path) -> None:
        self.bindir = bindir
        self.root = Path(tempfile.mkdtemp(prefix="robocal-pg-"))
        self.data = self.root / "data"
        self.log = self.root / "server.log"
        self.port = 0
        self.user: str | None = None
        self.running = False
        if os.geteuid() == 0:
            for name in ("postgres", "nobody"):
                with contextlib.suppress(KeyError):
                    pw = pwd.getpwnam(name)
                    os.chown(self.root, pw.pw_uid, pw.pw_gid)
                    self.user = name
                    break
        os.chmod(self.root, 0o700)

    def _run(self, *args: str, timeout: float = 60.0) -> None:
        cmd = [str(self.bindir / args[0]), *args[1:]]
        if self.user is not None:
            cmd = ["runuser", "-u", self.user, "--", *cmd]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd="/")
        if res.returncode != 0:
            log = self.log.read_text() if self.log.exists() else ""
            raise RuntimeError(f"{' '.join(args[:2])} failed: {res.stderr}{res.stdout}\n{log}")

    def init(self) -> None:
        """``initdb`` (superuser ``robocal``, trust on local connections)."""
        self._run("initdb", "-D", str(self.data), "-U", "robocal", "--auth=trust", "-E",
                  "UTF8", "--no-sync", "--no-instructions")

    def start(self) -> None:
        """Start (on a new free port the first time, on the same one after :meth:`stop`)."""
        for attempt in range(5):
            if not self.port or attempt:
                self.port = _free_port()
            try:
                self._run("pg_ctl", "-D", str(self.data), "-l", str(self.log), "-w", "-t", "30",
                          "-o", f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1 "
                          "-c fsync=off -c full_page_writes=off", "start")
                self.running = True
                return
            except RuntimeError:
                if attempt == 4:
                    raise

    def stop(self, mode: str = "fast") -> None:
        """``pg_ctl stop`` (``immediate``: like a crash)."""
        self._run("pg_ctl", "-D", str(self.data), "-m", mode, "-w", "-t", "30", "stop")
        self.running = False

    def url(self, dbname: str = "postgres") -> str:
        """A libpq URI for ``dbname`` over TCP."""
        return f"postgresql://robocal@127.0.0.1:{self.port}/{dbname}"

    def new_database(self) -> str:
        """Create an empty database; return its URI."""
        import psycopg

        name = "t_" + uuid.uuid4().hex[:12]
        with psycopg.connect(self.url(), autocommit=True, connect_timeout=10) as conn:
            conn.execute(f"CREATE DATABASE {name}")
        return self.url(name)

    def close(self) -> None:
        """Stop (if running) and delete the cluster."""
        with contextlib.suppress(RuntimeError, subprocess.SubprocessError):
            self.stop("immediate")
        shutil.rmtree(self.root, ignore_errors=True)


@contextlib.contextmanager
def postgres_server() -> Iterator[PostgresServer | str]:
    """A running server, or the reason there is none (a string)."""
    bindir = find_bindir()
    if bindir is None:
        yield ("no PostgreSQL server binaries (initdb, pg_ctl): install Debian's "
               "'postgresql' package to run the fleet store tests")
        return
    server = PostgresServer(bindir)
    try:
        server.init()
        server.start()
        yield server
    finally:
        server.close()
