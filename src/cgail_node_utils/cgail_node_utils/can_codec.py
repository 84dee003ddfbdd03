"""Pack and unpack the device nodes' CAN frames without cantools' general codec, bit for bit.

The PAM regulator bank and the sleeve driver exchange several frames per control tick, and
cantools' ``Message.encode`` / ``decode`` spend most of their time in generic machinery (the
strict check's name lookups, bitstruct formats, multiplexer handling). A :class:`FastCodec`
built from a cantools message whose signals are all little-endian integers (signed or not, with
or without a value table) packs the same bytes and unpacks the same values with plain shifts,
using the message's own conversion objects (``numeric_scaled_to_raw``, ``raw_to_scaled``) and
cantools' own strict bounds (``minimum - |scale| 1e-6``, ``maximum + |scale| 1e-6``, skipped for
a raw value in the value table). Where cantools would raise (a value out of range, a missing
or extra signal, a non-numeric value) :meth:`FastCodec.pack` returns None and the caller asks
cantools, so the errors stay cantools'. The packages' tests hold both equal.

Duck-typed over cantools' objects: this module imports neither cantools nor rclpy.
"""

from __future__ import annotations

from typing import Any


class FastCodec:
    """The fast codec of one cantools ``Message``; ``supported`` is False for a message it
    does not handle (big-endian or float signals, multiplexing, containers, signals without
    bounds), whose frames must go through cantools.

    Args:
        message: a ``cantools.database.can.Message``.
    """

    def __init__(self, message: Any) -> None:
        self.frame_id: int = message.frame_id
        self.length: int = message.length
        self.supported = False
        self._signals: tuple[tuple[str, int, int, int, bool, Any, float, float, Any], ...] = ()
        signals = []
        if getattr(message, 'is_container', False) or getattr(message, 'is_multiplexed',
                                                               lambda: False)():
            return
        for sig in message.signals:
            conv = sig.conversion
            if (sig.byte_order != 'little_endian' or conv.is_float or sig.minimum is None
                    or sig.maximum is None or sig.multiplexer_ids):
                return
            tol = abs(conv.scale) * 1e-6
            length = sig.length
            lo_raw = -(1 << (length - 1)) if sig.is_signed else 0
            hi_raw = (1 << (length - 1)) - 1 if sig.is_signed else (1 << length) - 1
            signals.append((sig.name, sig.start, length, (1 << length) - 1, sig.is_signed,
                            conv, sig.minimum - tol, sig.maximum + tol,
                            (lo_raw, hi_raw, conv.choices or {})))
        self._names = frozenset(s[0] for s in signals)
        self._signals = tuple(signals)
        self.supported = True

    def pack(self, values: dict[str, Any]) -> bytes | None:
        """The payload ``message.encode(values)`` returns (strict, scaled), or None where
        cantools must decide (it raises there)."""
        if not self.supported or values.keys() != self._names:
            return None
        word = 0
        for name, start, _, mask, _, conv, lo, hi, (lo_raw, hi_raw, choices) in self._signals:
            value = values[name]
            if not isinstance(value, (int, float)):
                return None
            raw = conv.numeric_scaled_to_raw(value)
            if not (lo <= value <= hi or raw in choices) or not lo_raw <= raw <= hi_raw:
                return None
            word |= (raw & mask) << start
        return word.to_bytes(self.length, 'little')

    def unpack(self, data: bytes) -> dict[str, float]:
        """The signals of ``data`` (``length`` bytes) as ``float`` of what
        ``message.decode(data, decode_choices=False)`` returns."""
        word = int.from_bytes(data, 'little')
        out = {}
        for name, start, length, mask, signed, conv, _, _, _ in self._signals:
            raw = (word >> start) & mask
            if signed and raw >> (length - 1):
                raw -= 1 << length
            out[name] = float(conv.raw_to_scaled(raw, False))
        return out
