"""Declarative file schemas: a file table is a frozen dataclass whose fields say how each key
is checked; :func:`load` turns the first problem into one :class:`ConfigError` (ADR 0045).

No dependency beyond the standard library, so that ``kinematics`` (numpy only, ADR 0001) and
the lean ``fit``/``predict`` start (no pydantic, ADR 0015) can use it::

    @dataclass(frozen=True, kw_only=True)
    class Joint:
        a_mm: float = key(number)              # required
        sign: int = key(sign, default=1)       # optional
        def __post_init__(self) -> None: ...   # cross-key checks: fail(message, key=...)

Unknown keys are refused first, with the keys allowed at that place; then the keys in the
order declared. The key of the error is a dotted path with 1-based list positions
(``joints[2].a_mm``).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, NoReturn, TypeVar

from robocal.errors import ConfigError

T = TypeVar("T")
Check = Callable[[Any], Any]


class Invalid(ConfigError):
    """A refused value: ``message`` as the user reads it, ``path`` below the checked place.
    :func:`load` turns it into a plain ConfigError naming the source and the key path."""

    def __init__(self, message: str, path: tuple[str | int, ...] = ()):
        super().__init__(message)
        self.message = message
        self.path = path


def fail(message: str, *, key: str | None = None) -> NoReturn:
    """Refuse a value; ``key`` names the offending key from a table's cross-key check."""
    raise Invalid(message, () if key is None else (key,))


def key(check: Check | None = None, default: Any = dataclasses.MISSING, *,
        factory: Callable[[], Any] | Any = dataclasses.MISSING,
        missing: str = "required key is missing") -> Any:
    """A key of a file table: ``check`` parses its value (returns it or calls :func:`fail`),
    ``default``/``factory`` make it optional (not checked), ``missing`` is the message when
    a required key is absent."""
    return dataclasses.field(default=default, default_factory=factory,
                             metadata={"check": check, "missing": missing})


def parse(cls: type[T], data: Any) -> T:
    """``data`` (a mapping) as the table ``cls``; raise :class:`Invalid`."""
    if not isinstance(data, dict):
        raise Invalid("must be a table")
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(str(k) for k in set(data) - set(fields))
    if unknown:
        raise Invalid(f"unknown key (allowed: {', '.join(sorted(fields))})", (unknown[0],))
    values = {}
    for name, f in fields.items():
        if name not in data:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise Invalid(f.metadata["missing"], (name,))
            continue
        check = f.metadata.get("check")
        values[name] = data[name] if check is None else _below(name, check, data[name])
    return cls(**values)


def _below(where: str | int, check: Check, value: Any) -> Any:
    try:
        return check(value)
    except Invalid as err:
        raise Invalid(err.message, (where, *err.path)) from None


def table(cls: type[T]) -> Callable[[Any], T]:
    """Check of a nested table."""
    return lambda v: parse(cls, v)


def list_of(check: Callable[..., Any], *, numbered: bool = False
            ) -> Callable[[Any], list[Any]]:
    """Check of a list whose items pass ``check`` (call it on a list only); ``numbered``:
    ``check(item, number)`` with the item's 1-based number."""
    def items(v: Any) -> list[Any]:
        if not numbered:
            return [_below(i, check, item) for i, item in enumerate(v)]
        return [_below(i, functools.partial(lambda x, n: check(x, n), n=i + 1), item)
                for i, item in enumerate(v)]

    return items


def load(cls: type[T], data: Any, source: str) -> T:
    """``data`` as the table ``cls``; raise one :class:`ConfigError` naming ``source`` and
    the key."""
    try:
        return parse(cls, data)
    except Invalid as err:
        path = "".join(f"[{p + 1}]" if isinstance(p, int) else f".{p}" for p in err.path)
        raise ConfigError(err.message, source=source, key=path.lstrip(".") or None) from None
