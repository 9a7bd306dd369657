"""A DataWriter's ``write`` for a flat message in one ``struct.pack``.

cyclonedds serialises a sample field by field through its Python IDL machinery: about
15 µs for a two-field ``Abh3Velocity``, and the bridge writes two of those per DP0 reply
of every unit (most of its worker's CPU on a small computer, docs/performance.md,
section 12). Every vendor message but the service's is a run of ``float64`` or of
``int32`` fields, whose CDR is the encapsulation header and the values packed back to
back: one ``struct.pack``, handed to the middleware as the bytes ``write`` would have
made (``ddspy_write``, what ``DataWriter.write`` calls after serialising).

A layout is trusted only after a probe: a sample of distinct values is serialised by
the IDL's own code with the writer's data representation and must come out byte for
byte as the pack does; a type with another layout (strings, sequences, nested structs,
padding between fields of different sizes), or a cyclonedds without ``ddspy_write``,
keeps ``DataWriter.write``.
"""

from __future__ import annotations

import operator
import struct
import typing
from typing import Any

from cyclonedds.core import DDSException
from cyclonedds.pub import DataWriter

from abh3_plugins.ros2.transport import Publish

try:  # the middleware's own write of serialised bytes (cyclonedds ≥ 0.10)
    from cyclonedds._clayer import ddspy_write  # type: ignore[import-not-found]
except ImportError:  # pragma: no cover - another cyclonedds: its write as it is
    ddspy_write = None

# IDL primitive → struct code: the sizes CDR gives them (little-endian, no padding
# within a run of one size)
_CODES = {"float64": "d", "float32": "f", "int32": "i", "uint32": "I", "int64": "q"}


def packed_write(writer: DataWriter[Any], typ: type) -> Publish:
    """``writer.write`` in one pack where ``typ``'s layout allows it and the probe agrees."""
    layout = _layout(typ)
    ref = getattr(writer, "_ref", None)
    if layout is None or ddspy_write is None or ref is None:
        return writer.write
    names, codes = layout
    pack = struct.Struct("<4s" + codes).pack
    probe = typ(**{name: i + 1 for i, name in enumerate(names)})  # ints are valid floats
    expected = _serialised(writer, probe)
    values = operator.attrgetter(*names) if len(names) > 1 else _one(names[0])
    header = expected[:4]
    if pack(header, *values(probe)) != expected:
        return writer.write
    write = ddspy_write

    def publish(sample: Any) -> None:
        if type(sample) is not typ:
            writer.write(sample)  # its own TypeError
            return
        try:
            data = pack(header, *values(sample))
        except struct.error:  # a value out of the field's range: cyclonedds's error, which
            writer.write(sample)  # names the field
            raise
        ret = write(ref, data)
        if ret < 0:
            raise DDSException(ret, f"Occurred while writing sample in {writer!r}")

    return publish


def _layout(typ: type) -> tuple[tuple[str, ...], str] | None:
    """The fields' names and struct codes, if every field is one primitive of one size."""
    try:
        hints = typing.get_type_hints(typ, include_extras=True)
    except Exception:  # a type our codes do not describe: the IDL's write
        return None
    names, codes = [], []
    for name, hint in hints.items():
        meta: tuple[object, ...] = getattr(hint, "__metadata__", ())
        code = _CODES.get(meta[0]) if len(meta) == 1 and isinstance(meta[0], str) else None
        if code is None:
            return None
        names.append(name)
        codes.append(code)
    if not names or len({struct.calcsize(c) for c in codes}) != 1:
        return None  # empty, or mixed sizes: padding the probe would have to find
    return tuple(names), "".join(codes)


def _serialised(writer: DataWriter[Any], sample: Any) -> bytes:
    """What ``writer.write`` hands the middleware for ``sample`` (its code, unexported)."""
    ser: bytes = sample.serialize(use_version_2=getattr(writer, "_use_version_2", None))
    return ser.ljust((len(ser) + 3) & ~3, b"\0")


def _one(name: str) -> typing.Callable[[Any], tuple[Any]]:
    get = operator.attrgetter(name)
    return lambda sample: (get(sample),)
