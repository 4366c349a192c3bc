"""A caller-owned scope for state that drivers built together share."""

from __future__ import annotations

import threading
from collections.abc import Callable, Hashable
from typing import TypeVar, cast

__all__ = ["DriverContext"]

T = TypeVar("T")


class DriverContext:
    """Resources shared by the drivers that one caller builds as a set.

    Whoever builds a set of drivers (the daemon's driver hub, a test, a script) creates a
    context and passes it to :func:`~robocal.drivers.load_robot_driver` and
    :func:`~robocal.drivers.load_tracker_driver`; a driver whose constructor takes a
    ``context`` keyword gets it, others are built as before. The mock robot and mock tracker
    keep their simulated world here, so a mock tracker measures where the mock robot of the
    same context is. Nothing is shared between contexts, and nothing outlives the context.

    >>> ctx = DriverContext()
    >>> ctx.shared("k", list) is ctx.shared("k", list)
    True
    >>> DriverContext().shared("k", list) is ctx.shared("k", list)
    False
    """

    def __init__(self) -> None:
        self._items: dict[Hashable, object] = {}
        self._lock = threading.Lock()

    def shared(self, key: Hashable, create: Callable[[], T]) -> T:
        """Return what is kept under ``key``, calling ``create()`` the first time.

        Keys should start with the owner's name (a module or driver kind) so that drivers
        do not collide.
        """
        with self._lock:
            if key not in self._items:
                self._items[key] = create()
            return cast(T, self._items[key])

    def __contains__(self, key: object) -> bool:
        with self._lock:
            return key in self._items

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)
