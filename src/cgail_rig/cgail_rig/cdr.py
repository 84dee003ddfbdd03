"""The CDR that DDS would carry: rclpy's serialized bytes with their padding zeroed.

``rclpy.serialization.serialize_message`` (``rmw_serialize``) writes a message's fields into a
buffer it does not clear, sized by the middleware's estimate: the alignment gaps between fields
and the tail after the last one keep whatever the allocator left there, while DDS hands a
subscriber the same fields with zero gaps and no tail. A recorder's bag must not depend on
the allocator, so the lockstep executor's in-process transport (:mod:`cgail_rig.lockstep`)
passes a raw subscriber :func:`zero_padding` of the serialized message: the same bytes as a
raw take from DDS.

The walk follows classic CDR (XCDR1, little or big endian, as Fast DDS writes ROS 2 types): a
4-byte encapsulation header, then every field in order, a primitive aligned to its size
relative to the end of the header, a string as a uint32 length (with the terminating NUL) and
its bytes, a sequence as a uint32 count and its elements, an array as its elements, a nested
message as its fields, an empty message as one byte. Types it does not know (wide strings, long
double) raise :class:`CdrError`, and so do bytes that do not fit the walk: the caller then
falls back to DDS.
"""

from __future__ import annotations

import importlib
import struct
from typing import Any

# ops of a plan: (SKIP, alignment, bytes) primitives; (STRING,); (SEQ_PRIM, alignment, bytes
# per element): a sequence of primitives, or of messages of primitives of one size (Point[]);
# (SEQ_STRING,); (SEQ_PLAN, plan); (REPEAT, plan, count) for an array of strings or messages
SKIP, STRING, SEQ_PRIM, SEQ_STRING, SEQ_PLAN, REPEAT = range(6)

_SIZES = {'boolean': 1, 'octet': 1, 'char': 1, 'int8': 1, 'uint8': 1, 'int16': 2, 'uint16': 2,
          'int32': 4, 'uint32': 4, 'float': 4, 'int64': 8, 'uint64': 8, 'double': 8}
_PLANS: dict[type, tuple[tuple[Any, ...], ...]] = {}


class CdrError(ValueError):
    """A type or a buffer the padding walk cannot handle."""


def _message_class(namespaced: Any) -> type:
    module = importlib.import_module('.'.join(namespaced.namespaces))
    cls: type = getattr(module, namespaced.name)
    return cls


def _field_ops(slot: Any) -> list[tuple[Any, ...]]:
    # the classes of rosidl_parser.definition, by name (the messages' SLOT_TYPES)
    kind = type(slot).__name__
    if kind == 'BasicType':
        if slot.typename not in _SIZES:
            raise CdrError(f'expected a CDR primitive, found {slot.typename}')
        size = _SIZES[slot.typename]
        return [(SKIP, size, size)]
    if kind in ('UnboundedString', 'BoundedString'):
        return [(STRING,)]
    if kind == 'NamespacedType':
        return list(plan(_message_class(slot)))
    if kind == 'Array':
        inner = _field_ops(slot.value_type)
        if len(inner) == 1 and inner[0][0] == SKIP:
            return [(SKIP, inner[0][1], inner[0][2] * slot.size)]
        return [(REPEAT, tuple(inner), slot.size)]
    if kind in ('UnboundedSequence', 'BoundedSequence'):
        inner = _field_ops(slot.value_type)
        if len(inner) == 1 and inner[0][0] == SKIP:
            # (an element is a whole number of its alignment: the next one needs no gap)
            return [(SEQ_PRIM, inner[0][1], inner[0][2])]
        if inner == [(STRING,)]:
            return [(SEQ_STRING,)]
        return [(SEQ_PLAN, tuple(inner))]
    raise CdrError(f'expected a ROS 2 field type (no wide strings), found {kind}')


def plan(msg_type: type) -> tuple[tuple[Any, ...], ...]:
    """The walk of ``msg_type``'s CDR (cached): consecutive primitives of one size merged."""
    cached = _PLANS.get(msg_type)
    if cached is not None:
        return cached
    ops: list[tuple[Any, ...]] = []
    slots = list(getattr(msg_type, 'SLOT_TYPES', ()))
    for slot in slots or [None]:
        for op in _field_ops(slot) if slot is not None else [(SKIP, 1, 1)]:
            last = ops[-1] if ops else None
            if op[0] == SKIP and last is not None and last[0] == SKIP and last[1] == op[1]:
                ops[-1] = (SKIP, op[1], last[2] + op[2])
            else:
                ops.append(op)
    result = tuple(ops)
    _PLANS[msg_type] = result
    return result


def zero_padding(data: bytes, msg_type: type) -> bytes:
    """``data`` (a serialized ``msg_type``) with every alignment gap zeroed, cut after its
    last field (DDS's length; the estimate ``rmw_serialize`` allocates may be longer).

    Raises:
        CdrError: an unknown encapsulation or type, or bytes that do not fit ``msg_type``.
    """
    if len(data) < 4 or data[0] != 0 or data[1] not in (0, 1):
        raise CdrError(f'expected a CDR encapsulation header, found {data[:4].hex()}')
    out = bytearray(data)
    u32 = struct.Struct('<I' if data[1] == 1 else '>I').unpack_from
    end = _walk(out, 4, plan(msg_type), u32)
    if end > len(out):
        raise CdrError(f'expected at most {len(out)} bytes of {msg_type.__name__}, found '
                       f'fields up to byte {end}')
    return bytes(out[:end])


def _align(out: bytearray, pos: int, alignment: int) -> int:
    gap = -(pos - 4) % alignment
    if gap:
        out[pos:pos + gap] = bytes(gap)
    return pos + gap


def _length(out: bytearray, pos: int, u32: Any) -> tuple[int, int]:
    """The uint32 length (of a string or sequence) at the next 4-byte boundary, and the position
    after it."""
    pos = _align(out, pos, 4)
    return u32(out, pos)[0], pos + 4


def _walk(out: bytearray, pos: int, ops: tuple[tuple[Any, ...], ...], u32: Any) -> int:
    for op in ops:
        kind = op[0]
        if kind == SKIP:
            pos = _align(out, pos, op[1]) + op[2]
        elif kind == STRING:
            size, pos = _length(out, pos, u32)
            pos += size
        elif kind == SEQ_PRIM:
            count, pos = _length(out, pos, u32)
            if count:
                pos = _align(out, pos, op[1]) + count * op[2]
        elif kind == SEQ_STRING:
            count, pos = _length(out, pos, u32)
            for _ in range(count):
                size, pos = _length(out, pos, u32)
                pos += size
        elif kind == SEQ_PLAN:
            count, pos = _length(out, pos, u32)
            for _ in range(count):
                pos = _walk(out, pos, op[1], u32)
        else:  # REPEAT
            for _ in range(op[2]):
                pos = _walk(out, pos, op[1], u32)
        if pos > len(out):
            raise CdrError(f'expected the fields within {len(out)} bytes, found them past it')
    return pos
