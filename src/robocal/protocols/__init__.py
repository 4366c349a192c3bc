"""Wire protocols: async transports chosen by URL and sans-I/O codecs.

Nothing here imports numpy or scipy (an import-linter contract), so codecs can be reused and
tested without the numerical stack. :mod:`robocal.protocols.modbus` is not imported here; import it
explicitly.

Modules
-------
transport
    :class:`Transport`, :func:`open_transport` (``tcp://``, ``serial://``, ``socket://``,
    ``loop://``, ``rfc2217://``).
framing, lines
    :class:`LineFramer` (CR LF, maximum length, resync) and :class:`LineStream`.
ltp
    LTP/1 tracker line protocol codec.
fanuc_rmi
    FANUC RMI JSON packet codec and ErrorID table.
kuka_kvp
    KUKAVARPROXY message codec (framer, read/write requests, replies) and KRL value text.
emscon
    Leica emScon TPI binary packet codec (size-field framer, command and result structs).
session
    Sans-I/O request/reply matching: :class:`~robocal.protocols.session.Window` and the RMI,
    LTP/1 and emScon sessions (which reply answers which request, what is overdue).
modbus
    Modbus register map, value and table-block codecs (the pymodbus client is in
    :mod:`robocal.drivers`, the server in :mod:`robocal.drivers.sim`).
"""

from robocal.protocols import transport
from robocal.protocols.framing import CRLF, LineFramer
from robocal.protocols.lines import LineStream
from robocal.protocols.transport import *  # noqa: F403 (its __all__ is re-exported below)

__all__ = [
    "CRLF",
    "LineFramer",
    "LineStream",
]
__all__ += transport.__all__
