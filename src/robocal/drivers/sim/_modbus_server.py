"""The pymodbus server under the simulated PLC (:mod:`robocal.drivers.sim.modbus_plc`).

With :mod:`robocal.drivers._modbus_client`, the only place that imports pymodbus (pinned
``>=3.16,<3.17``). Moved here from :mod:`robocal.protocols.modbus` (ADR 0038).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Coroutine
from typing import Any

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from robocal.errors import TransportError

__all__ = ["HOLDING_FCS", "WRITE_FCS", "ExcCodes", "ModbusSimServer", "SimAction"]

#: ``action(function_code, start_address, address, count, registers, set_values)``,
#: pymodbus' SimDevice hook; return an :class:`ExcCodes` member to refuse the request.
SimAction = Callable[
    [int, int, int, int, list[int], list[int] | list[bool] | None],
    Coroutine[Any, Any, ExcCodes | None],
]

HOLDING_FCS = frozenset({3, 6, 16, 22, 23})
WRITE_FCS = frozenset({6, 16, 22, 23})


class ModbusSimServer:
    """A real pymodbus ``ModbusTcpServer`` on one ``SimDevice`` with separate HR and IR blocks.

    Parameters
    ----------
    holding_size, input_size : int
        Registers from address 0 in each area.
    action : SimAction
        The PLC logic hook, called before the server reads or writes the block.
    device_id : int
        Device id served.
    """

    def __init__(
        self, *, holding_size: int, input_size: int, action: SimAction, device_id: int = 1
    ) -> None:
        bits = [SimData(0, count=16, values=False, datatype=DataType.BITS)]
        self._device = SimDevice(
            id=device_id,
            simdata=(
                bits,
                [SimData(0, count=16, values=False, datatype=DataType.BITS)],
                [SimData(0, count=holding_size, values=0, datatype=DataType.REGISTERS)],
                [SimData(0, count=max(1, input_size), values=0, datatype=DataType.REGISTERS)],
            ),
            action=action,
        )
        self._server: ModbusTcpServer | None = None
        self.host = "127.0.0.1"
        self.port = 0

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> int:
        """Listen on ``host:port`` (0 picks a free port); return the bound port."""
        self._server = ModbusTcpServer(self._device, address=(host, port))
        await self._server.serve_forever(background=True)
        transport = self._server.transport
        if transport is None:
            raise TransportError(f"Modbus server on {host}:{port} did not start")
        # pymodbus keeps the asyncio.Server as its transport; its socket holds the bound port.
        self.host = host
        self.port = int(transport.sockets[0].getsockname()[1])  # type: ignore[attr-defined]
        return self.port

    async def stop(self) -> None:
        """Stop serving and drop client connections; idempotent."""
        server, self._server = self._server, None
        if server is not None:
            with contextlib.suppress(Exception):
                await server.shutdown()
