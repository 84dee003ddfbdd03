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

:func:`encoder` and :func:`decoder` are the in-process transport's codec: per message type,
generated struct calls that give the bytes of :func:`zero_padding` (rclpy's serialization) and
the message of rclpy's deserialization, several times faster (comment above them).
"""

from __future__ import annotations

import array
import importlib
import struct
from typing import Any

import numpy as np

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


# ---------------------------------------------------------------------- codec
# The in-process transport's serializer and deserializer, generated per message type: what
# rclpy's (C) conversion and rmw_serialize give, in a few struct calls instead of a C
# conversion that looks every field up by name and checks every message's class name (~30 us
# for a PoseStamped), and without the padding walk: :func:`encoder` writes DDS's bytes
# (zero_padding's) directly. :func:`decoder` builds the message rclpy's deserializer builds
# (the same field values and types: floats, ints, bools, str, array.array for a sequence of
# numbers, a numpy array for an array of numbers, lists for the rest) without its constructor
# and setters. A type with a field kind neither handles (bounded strings and sequences,
# char, wide strings, sequences of booleans or octets) raises CdrError: the caller keeps
# rclpy's.

_CODES = {'boolean': '?', 'octet': 'c', 'int8': 'b', 'uint8': 'B', 'int16': 'h', 'uint16': 'H',
          'int32': 'i', 'uint32': 'I', 'float': 'f', 'int64': 'q', 'uint64': 'Q', 'double': 'd'}
#: array.array type codes (and numpy dtypes) of sequences (and arrays) of numbers, as
#: rosidl_generator_py stores them
_ARRAY_CODES = {'int8': 'b', 'uint8': 'B', 'int16': 'h', 'uint16': 'H', 'int32': 'i',
                'uint32': 'I', 'float': 'f', 'int64': 'q', 'uint64': 'Q', 'double': 'd'}
_HEADER = b'\x00\x01\x00\x00'  # little-endian CDR, no options
_U32 = struct.Struct('<I')
_ENCODERS: dict[type, Any] = {}
_DECODERS: dict[type, Any] = {}


class Fallback(Exception):  # noqa: N818 (a signal, not an error: rclpy's path then)
    """A value the generated encoder does not convert as rclpy would (the caller serializes
    with rclpy)."""


def _run_structs(typenames: list[str]) -> tuple[struct.Struct, ...]:
    """The struct of a run of primitives for each start offset modulo 8 (alignment gaps as
    zero pad bytes)."""
    out = []
    for start in range(8):
        fmt, pos = '<', start
        for name in typenames:
            size = _SIZES[name]
            gap = -pos % size
            fmt += 'x' * gap + _CODES[name]
            pos += gap + size
        out.append(struct.Struct(fmt))
    return tuple(out)


def _pad(out: bytearray, alignment: int) -> None:
    gap = -(len(out) - 4) % alignment
    if gap:
        out += bytes(gap)


#: A string's CDR bytes after its alignment (length, UTF-8 up to the first NUL, NUL), per
#: string: a rig sends the same few (frame ids, joint names, marker namespaces) ~25 times a tick.
_STR_BYTES: dict[str, bytes] = {}
_STR_CACHE_MAX = 4096


def _put_str(out: bytearray, s: str) -> None:
    data = _STR_BYTES.get(s)
    if data is None:
        raw = s.encode()
        nul = raw.find(b'\x00')  # (rosidl's String assign copies up to the first NUL)
        if nul >= 0:
            raw = raw[:nul]
        data = _U32.pack(len(raw) + 1) + raw + b'\x00'
        if len(_STR_BYTES) < _STR_CACHE_MAX and type(s) is str:
            _STR_BYTES[s] = data
    _pad(out, 4)
    out += data


def _put_strs(out: bytearray, seq: Any) -> None:
    _pad(out, 4)
    out += _U32.pack(len(seq))
    for s in seq:
        _put_str(out, s)


def _put_array(out: bytearray, value: Any, code: str, size: int) -> None:
    if type(value) is not array.array or value.typecode != code:
        raise Fallback
    _pad(out, 4)
    out += _U32.pack(len(value))
    if len(value):
        _pad(out, size)
        out += value.tobytes()


def _put_ndarray(out: bytearray, value: Any, dtype: Any, count: int, size: int) -> None:
    if type(value) is not np.ndarray or value.dtype != dtype or value.shape != (count,):
        raise Fallback
    _pad(out, size)
    out += value.tobytes()


def _get_str(data: bytes, pos: int) -> tuple[str, int]:
    pos += -(pos - 4) % 4
    n = _U32.unpack_from(data, pos)[0]
    pos += 4
    raw = data[pos:pos + n - 1]
    nul = raw.find(b'\x00')
    if nul >= 0:
        raw = raw[:nul]
    return raw.decode('utf-8', 'replace'), pos + n


def _get_strs(data: bytes, pos: int) -> tuple[list[str], int]:
    pos += -(pos - 4) % 4
    n = _U32.unpack_from(data, pos)[0]
    pos += 4
    out = []
    for _ in range(n):
        s, pos = _get_str(data, pos)
        out.append(s)
    return out, pos


def _get_array(data: bytes, pos: int, code: str, size: int) -> tuple[array.array, int]:
    pos += -(pos - 4) % 4
    n = _U32.unpack_from(data, pos)[0]
    pos += 4
    value = array.array(code)
    if n:
        pos += -(pos - 4) % size
        value.frombytes(data[pos:pos + n * size])
        pos += n * size
    return value, pos


def _get_ndarray(data: bytes, pos: int, dtype: Any, count: int, size: int) -> tuple[Any, int]:
    pos += -(pos - 4) % size
    return np.frombuffer(data, dtype, count, pos).copy(), pos + count * size


def _fields(msg_type: type) -> list[tuple[str, Any]]:
    names = list(getattr(msg_type, '_fields_and_field_types', {}))
    slots = list(getattr(msg_type, 'SLOT_TYPES', ()))
    if len(names) != len(slots):
        raise CdrError(f'expected a message type, found {msg_type!r}')
    return list(zip(names, slots, strict=True))


def _uniform(msg_type: type) -> str | None:
    """The one primitive of a message made of primitives of one kind (Point: 'double'), else
    None."""
    kinds = set()
    for _, slot in _fields(msg_type):
        if type(slot).__name__ != 'BasicType' or slot.typename not in _ARRAY_CODES:
            return None
        kinds.add(slot.typename)
    return kinds.pop() if len(kinds) == 1 else None


class _Gen:
    """Python source of an encoder or a decoder (module comment above)."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self.ns: dict[str, Any] = {'array': array, 'np': np, 'struct': struct,
                                   'Fallback': Fallback,
                                   '_pad': _pad, '_put_str': _put_str, '_put_strs': _put_strs,
                                   '_put_array': _put_array, '_put_ndarray': _put_ndarray,
                                   '_get_str': _get_str, '_get_strs': _get_strs,
                                   '_get_array': _get_array, '_get_ndarray': _get_ndarray,
                                   '_U32': _U32}
        self.run: list[tuple[str, str]] = []  # (typename, expression or target)
        self.names = 0

    def const(self, value: Any) -> str:
        self.names += 1
        name = f'_k{self.names}'
        self.ns[name] = value
        return name

    def var(self) -> str:
        self.names += 1
        return f'v{self.names}'


def _slot_kind(slot: Any) -> str:
    kind = type(slot).__name__
    if kind == 'BasicType':
        if slot.typename not in _CODES:
            raise CdrError(f'expected a primitive the codec knows, found {slot.typename}')
        return 'basic'
    if kind == 'UnboundedString':
        return 'string'
    if kind == 'NamespacedType':
        return 'message'
    if kind == 'Array':
        return 'array'
    if kind == 'UnboundedSequence':
        return 'sequence'
    raise CdrError(f'expected a field kind the codec knows, found {kind}')


def _enc_flush(g: _Gen, indent: str) -> None:
    if not g.run:
        return
    structs = g.const(_run_structs([t for t, _ in g.run]))
    values = ', '.join(e for _, e in g.run)
    g.lines.append(f'{indent}out += {structs}[(len(out) - 4) & 7].pack({values})')
    g.run.clear()


def _enc_fields(g: _Gen, msg_type: type, expr: str, indent: str, depth: int) -> None:
    fields = _fields(msg_type)
    if not fields:
        g.run.append(('uint8', '0'))  # an empty message: one byte
    for name, slot in fields:
        _enc_value(g, slot, f'{expr}._{name}', indent, depth)


def _enc_value(g: _Gen, slot: Any, expr: str, indent: str, depth: int) -> None:
    kind = _slot_kind(slot)
    if kind == 'basic':
        g.run.append((slot.typename, f'({expr} is True)' if slot.typename == 'boolean'
                      else expr))
        return
    if kind == 'message':
        _enc_fields(g, _message_class(slot), expr, indent, depth)
        return
    _enc_flush(g, indent)
    if kind == 'string':
        g.lines.append(f'{indent}_put_str(out, {expr})')
        return
    inner = slot.value_type
    inner_kind = _slot_kind(inner)
    if kind == 'array':
        if inner_kind == 'basic' and inner.typename in _ARRAY_CODES:
            dtype = g.const(np.dtype(_ARRAY_CODES[inner.typename]))
            g.lines.append(f'{indent}_put_ndarray(out, {expr}, {dtype}, {slot.size}, '
                           f'{_SIZES[inner.typename]})')
            return
        if inner_kind == 'basic':
            raise CdrError(f'expected an array of numbers, found one of {inner.typename}')
        item = f'e{depth}'
        g.lines.append(f'{indent}if len({expr}) != {slot.size}:')
        g.lines.append(f'{indent}    raise Fallback')
        g.lines.append(f'{indent}for {item} in {expr}:')
        _enc_value(g, inner, item, indent + '    ', depth + 1)
        _enc_flush(g, indent + '    ')
        return
    # an unbounded sequence
    if inner_kind == 'basic':
        if inner.typename not in _ARRAY_CODES:
            raise CdrError(f'expected a sequence of numbers, found one of {inner.typename}')
        code = _ARRAY_CODES[inner.typename]
        g.lines.append(f'{indent}_put_array(out, {expr}, {code!r}, {_SIZES[inner.typename]})')
        return
    if inner_kind == 'string':
        g.lines.append(f'{indent}_put_strs(out, {expr})')
        return
    if inner_kind != 'message':
        raise CdrError(f'expected a sequence of numbers, strings or messages, found {inner}')
    seq, item = g.var(), f'e{depth}'
    g.lines.append(f'{indent}{seq} = {expr}')
    g.lines.append(f'{indent}_pad(out, 4)')
    g.lines.append(f'{indent}out += _U32.pack(len({seq}))')
    element = _message_class(inner)
    uniform = _uniform(element)
    if uniform is not None:  # Point[], ColorRGBA[]: one pack of all the numbers
        names = ', '.join(f'{item}._{n}' for n, _ in _fields(element))
        values = g.var()
        g.lines.append(f'{indent}if {seq}:')
        g.lines.append(f'{indent}    {values} = [x for {item} in {seq} for x in ({names},)]')
        g.lines.append(f'{indent}    _pad(out, {_SIZES[uniform]})')
        g.lines.append(f"{indent}    out += struct.pack('<%d{_CODES[uniform]}' % "
                       f'len({values}), *{values})')
        return
    g.lines.append(f'{indent}for {item} in {seq}:')
    _enc_fields(g, element, item, indent + '    ', depth + 1)
    _enc_flush(g, indent + '    ')


def encoder(msg_type: type) -> Any:
    """``encode(msg) -> bytes``: ``zero_padding(rclpy serialize(msg))`` (module comment), cached
    per type; ``encode`` raises :class:`Fallback` (or a struct error) for a value it does not
    convert as rclpy would.

    Raises:
        CdrError: a field kind the codec does not handle.
    """
    cached = _ENCODERS.get(msg_type)
    if cached is not None:
        return cached
    g = _Gen()
    g.lines.append('def encode(m):')
    g.lines.append(f'    out = bytearray({_HEADER!r})')
    _enc_fields(g, msg_type, 'm', '    ', 0)
    _enc_flush(g, '    ')
    g.lines.append('    return bytes(out)')
    exec('\n'.join(g.lines), g.ns)  # (source generated from the type above)
    result = g.ns['encode']
    _ENCODERS[msg_type] = result
    return result


def _dec_flush(g: _Gen, indent: str) -> None:
    if not g.run:
        return
    structs = g.const(_run_structs([t for t, _ in g.run]))
    s = g.var()
    targets = ', '.join(t for _, t in g.run)
    g.lines.append(f'{indent}{s} = {structs}[(pos - 4) & 7]')
    g.lines.append(f'{indent}{targets}, = {s}.unpack_from(data, pos)')
    g.lines.append(f'{indent}pos += {s}.size')
    g.run.clear()


def _dec_new(g: _Gen, msg_type: type, var: str, indent: str) -> None:
    cls = g.const(msg_type)
    check = g.const(msg_type()._check_fields)
    g.lines.append(f'{indent}{var} = {cls}.__new__({cls})')
    g.lines.append(f'{indent}{var}._check_fields = {check}')


def _dec_fields(g: _Gen, msg_type: type, var: str, indent: str, depth: int) -> None:
    """Fill the new message ``var`` from the bytes."""
    fields = _fields(msg_type)
    if not fields:
        g.run.append(('uint8', '_'))
    for name, slot in fields:
        _dec_value(g, slot, f'{var}._{name}', indent, depth)


def _dec_value(g: _Gen, slot: Any, target: str, indent: str, depth: int) -> None:
    kind = _slot_kind(slot)
    if kind == 'basic':
        g.run.append((slot.typename, target))
        return
    if kind == 'message':
        element = _message_class(slot)
        var = g.var()
        _dec_new(g, element, var, indent)
        g.lines.append(f'{indent}{target} = {var}')
        _dec_fields(g, element, var, indent, depth)
        return
    _dec_flush(g, indent)
    if kind == 'string':
        g.lines.append(f'{indent}{target}, pos = _get_str(data, pos)')
        return
    inner = slot.value_type
    inner_kind = _slot_kind(inner)
    if kind == 'array':
        if inner_kind == 'basic' and inner.typename in _ARRAY_CODES:
            dtype = g.const(np.dtype(_ARRAY_CODES[inner.typename]))
            g.lines.append(f'{indent}{target}, pos = _get_ndarray(data, pos, {dtype}, '
                           f'{slot.size}, {_SIZES[inner.typename]})')
            return
        if inner_kind == 'basic':
            raise CdrError(f'expected an array of numbers, found one of {inner.typename}')
        items = g.var()
        g.lines.append(f'{indent}{items} = []')
        g.lines.append(f'{indent}for _ in range({slot.size}):')
        _dec_item(g, inner, inner_kind, items, indent + '    ', depth)
        g.lines.append(f'{indent}{target} = {items}')
        return
    if inner_kind == 'basic':
        if inner.typename not in _ARRAY_CODES:
            raise CdrError(f'expected a sequence of numbers, found one of {inner.typename}')
        g.lines.append(f'{indent}{target}, pos = _get_array(data, pos, '
                       f'{_ARRAY_CODES[inner.typename]!r}, {_SIZES[inner.typename]})')
        return
    if inner_kind == 'string':
        g.lines.append(f'{indent}{target}, pos = _get_strs(data, pos)')
        return
    if inner_kind != 'message':
        raise CdrError(f'expected a sequence of numbers, strings or messages, found {inner}')
    count, items = g.var(), g.var()
    g.lines.append(f'{indent}pos += -(pos - 4) % 4')
    g.lines.append(f'{indent}{count} = _U32.unpack_from(data, pos)[0]')
    g.lines.append(f'{indent}pos += 4')
    g.lines.append(f'{indent}{items} = []')
    element = _message_class(inner)
    uniform = _uniform(element)
    if uniform is not None:  # Point[], ColorRGBA[]: one unpack of all the numbers
        names = _fields(element)
        size, per = _SIZES[uniform], len(names)
        values, k, var = g.var(), g.var(), g.var()
        g.lines.append(f'{indent}if {count}:')
        g.lines.append(f'{indent}    pos += -(pos - 4) % {size}')
        g.lines.append(f"{indent}    {values} = struct.unpack_from('<%d{_CODES[uniform]}' % "
                       f'({count} * {per}), data, pos)')
        g.lines.append(f'{indent}    pos += {count} * {per * size}')
        g.lines.append(f'{indent}    for {k} in range(0, {count} * {per}, {per}):')
        _dec_new(g, element, var, indent + '        ')
        fields = ', '.join(f'{var}._{n}' for n, _ in names)
        g.lines.append(f'{indent}        {fields}, = {values}[{k}:{k} + {per}]')
        g.lines.append(f'{indent}        {items}.append({var})')
    else:
        g.lines.append(f'{indent}for _ in range({count}):')
        _dec_item(g, inner, inner_kind, items, indent + '    ', depth)
    g.lines.append(f'{indent}{target} = {items}')


def _dec_item(g: _Gen, inner: Any, inner_kind: str, items: str, indent: str,
              depth: int) -> None:
    """The loop body that appends one decoded element to the list ``items``."""
    if inner_kind == 'message':
        element = _message_class(inner)
        var = g.var()
        _dec_new(g, element, var, indent)
        _dec_fields(g, element, var, indent, depth + 1)
        _dec_flush(g, indent)
        g.lines.append(f'{indent}{items}.append({var})')
    elif inner_kind == 'string':
        s = g.var()
        g.lines.append(f'{indent}{s}, pos = _get_str(data, pos)')
        g.lines.append(f'{indent}{items}.append({s})')
    else:
        raise CdrError(f'expected an array of numbers, strings or messages, found {inner}')


def decoder(msg_type: type) -> Any:
    """``decode(data) -> msg``: the ``msg_type`` rclpy's deserializer gives for the CDR
    ``data`` (module comment), cached per type.

    Raises:
        CdrError: a field kind the codec does not handle.
    """
    cached = _DECODERS.get(msg_type)
    if cached is not None:
        return cached
    g = _Gen()
    g.lines.append('def decode(data):')
    g.lines.append('    if data[:2] != b"\\x00\\x01":')
    g.lines.append('        raise Fallback')
    g.lines.append('    pos = 4')
    _dec_new(g, msg_type, 'm', '    ')
    _dec_fields(g, msg_type, 'm', '    ', 0)
    _dec_flush(g, '    ')
    g.lines.append('    return m')
    exec('\n'.join(g.lines), g.ns)  # (source generated from the type above)
    result = g.ns['decode']
    _DECODERS[msg_type] = result
    return result
