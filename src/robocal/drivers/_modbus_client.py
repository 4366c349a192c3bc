"""The pymodbus client boundary of the ``modbus_plc`` driver (docs/protocols/modbus-plc.md).

With :mod:`robocal.drivers.sim._modbus_server`, the only place that imports pymodbus; the
pinned series is ``>=3.16,<3.17``. It maps our names (``device_id``, ``address``, ``count``)
onto pymodbus and turns its exceptions and exception replies into :mod:`robocal.errors`
types. The register map and value codecs are :mod:`robocal.protocols.modbus` (ADR 0038).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Awaitable, Callable, Sequence

import structlog
from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

from robocal.errors import TransportError, TransportTimeout, UnexpectedReply
from robocal.protocols.modbus import MAX_READ, MAX_WRITE

__all__ = ["ModbusClient"]

_log = structlog.get_logger(__name__)


class ModbusClient:
    """Async Modbus-TCP client; one request at a time, errors as :mod:`robocal.errors` types.

    Parameters
    ----------
    host, port : str, int
        Server address.
    device_id : int
        Modbus unit / device id.
    timeout : float
        Per-request timeout in seconds.
    """

    def __init__(self, host: str, port: int, *, device_id: int = 1, timeout: float = 2.0) -> None:
        self.host = host
        self.port = port
        self.device_id = device_id
        self.timeout = timeout
        self.url = f"modbus-tcp://{host}:{port}/{device_id}"
        self._client: AsyncModbusTcpClient | None = None
        self._lock = asyncio.Lock()

    @property
    def is_open(self) -> bool:
        """True while connected."""
        return self._client is not None and bool(self._client.connected)

    async def connect(self, *, timeout: float) -> None:
        """Connect; raise TransportError or TransportTimeout."""
        if self.is_open:
            return
        client = AsyncModbusTcpClient(
            self.host, port=self.port, timeout=self.timeout, retries=0, reconnect_delay=0
        )
        try:
            async with asyncio.timeout(timeout):
                ok = await client.connect()
        except TimeoutError as err:
            client.close()
            raise TransportTimeout(f"{self.url}: connect timed out") from err
        except (OSError, ModbusException) as err:
            client.close()
            raise TransportError(f"{self.url}: cannot connect: {err}") from err
        if not ok:
            client.close()
            raise TransportError(f"{self.url}: cannot connect")
        self._client = client

    async def close(self) -> None:
        """Close; idempotent and never raises."""
        client, self._client = self._client, None
        if client is not None:
            with contextlib.suppress(Exception):
                client.close()

    async def _call(self, what: str, fn: Callable[[AsyncModbusTcpClient], Awaitable[object]]):
        client = self._client
        if client is None or not client.connected:
            raise TransportError(f"{self.url}: not connected")
        task = asyncio.current_task()
        cancels = task.cancelling() if task is not None else 0
        loop = asyncio.get_running_loop()
        async with self._lock:
            try:
                for attempt in (1, 2):
                    started = loop.time()
                    try:
                        async with asyncio.timeout(self.timeout + 1.0):
                            rr = await fn(client)
                        break
                    except (TimeoutError, ModbusIOException):
                        # A timeout that fired long after it was due means the process or
                        # its loop stood still (SIGSTOP, a suspended VM): the reply may have
                        # come meanwhile, and pymodbus dropped it with the request. Every
                        # request here is idempotent (reads; writes of fixed values), so
                        # it is asked once more (ADR 0025).
                        overrun = loop.time() - started - self.timeout
                        if attempt == 2 or overrun < max(0.05, 0.25 * self.timeout):
                            raise
                        _log.info("modbus request repeated after a stall", what=what,
                                  stalled_s=round(overrun, 3))
                if task is not None and task.cancelling() > cancels:
                    # pymodbus waits with asyncio.wait_for, which on Python 3.11 drops a
                    # cancellation that arrives together with the reply (CPython gh-86296):
                    # honour it here, or a cancelled caller would run on.
                    raise asyncio.CancelledError
            except TimeoutError as err:
                raise TransportTimeout(f"{self.url}: {what} timed out") from err
            except ModbusIOException as err:
                raise TransportTimeout(f"{self.url}: {what}: {err}") from err
            except ConnectionException as err:
                raise TransportError(f"{self.url}: {what}: {err}") from err
            except ModbusException as err:
                raise TransportError(f"{self.url}: {what}: {err}") from err
        if rr.isError():  # type: ignore[attr-defined]
            code = getattr(rr, "exception_code", None)
            raise UnexpectedReply(f"{self.url}: {what}: Modbus exception code {code}")
        return rr

    async def _read(self, fc: int, address: int, count: int) -> list[int]:
        out: list[int] = []
        # the ignores below: mypy cannot type a lambda with default arguments
        # (python/mypy#15459); the defaults bind the loop values (ruff B023)
        while count > 0:
            n = min(count, MAX_READ)
            start = address
            if fc == 3:
                rr = await self._call(
                    f"read HR {start}+{n}",
                    lambda c, s=start, n=n: c.read_holding_registers(  # type: ignore[misc]
                        s, count=n, device_id=self.device_id
                    ),
                )
            else:
                rr = await self._call(
                    f"read IR {start}+{n}",
                    lambda c, s=start, n=n: c.read_input_registers(  # type: ignore[misc]
                        s, count=n, device_id=self.device_id
                    ),
                )
            regs = list(rr.registers)
            if len(regs) != n:
                raise UnexpectedReply(f"{self.url}: asked for {n} registers, got {len(regs)}")
            out += regs
            address += n
            count -= n
        return out

    async def read_holding(self, address: int, count: int) -> list[int]:
        """Read ``count`` holding registers (FC3, split into legal requests)."""
        return await self._read(3, address, count)

    async def read_input(self, address: int, count: int) -> list[int]:
        """Read ``count`` input registers (FC4, split into legal requests)."""
        return await self._read(4, address, count)

    async def write_registers(self, address: int, values: Sequence[int]) -> None:
        """Write holding registers (FC16, split into legal requests)."""
        values = list(values)
        for i in range(0, len(values), MAX_WRITE):
            chunk = values[i : i + MAX_WRITE]
            start = address + i
            await self._call(
                f"write HR {start}+{len(chunk)}",
                # mypy cannot type a lambda with default arguments (python/mypy#15459)
                lambda c, s=start, v=chunk: c.write_registers(  # type: ignore[misc]
                    s, v, device_id=self.device_id
                ),
            )

    async def write_register(self, address: int, value: int) -> None:
        """Write one holding register (FC6)."""
        await self._call(
            f"write HR {address}",
            lambda c: c.write_register(address, value, device_id=self.device_id),
        )
