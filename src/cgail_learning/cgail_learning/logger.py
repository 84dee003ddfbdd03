"""Scalar logging to CSV and to TensorBoard event files, without the tensorboard package.

:class:`EventFileWriter` writes the TFRecord framing (length, masked CRC32C, payload, masked
CRC32C) of hand-encoded ``Event``/``Summary`` protobufs holding ``simple_value`` scalars, which
TensorBoard reads like any ``tf.summary.scalar`` output.
"""

from __future__ import annotations

import csv
from pathlib import Path
import socket
import struct
import time

_CRC_TABLE: list[int] = []
for _i in range(256):
    _c = _i
    for _ in range(8):
        _c = (_c >> 1) ^ 0x82F63B78 if _c & 1 else _c >> 1
    _CRC_TABLE.append(_c)


def crc32c(data: bytes) -> int:
    """CRC-32C (Castagnoli) of ``data``."""
    crc = 0xFFFFFFFF
    for b in data:
        crc = _CRC_TABLE[(crc ^ b) & 0xFF] ^ (crc >> 8)
    return crc ^ 0xFFFFFFFF


def _masked_crc(data: bytes) -> int:
    crc = crc32c(data)
    return (((crc >> 15) | (crc << 17)) + 0xA282EAD8) & 0xFFFFFFFF


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        if n:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _field_bytes(num: int, payload: bytes) -> bytes:
    return _varint((num << 3) | 2) + _varint(len(payload)) + payload


def encode_scalar_event(tag: str, value: float, step: int, wall_time: float) -> bytes:
    """Serialized ``Event{wall_time, step, summary{value{tag, simple_value}}}``."""
    val = _field_bytes(1, tag.encode()) + struct.pack('<Bf', (2 << 3) | 5, float(value))
    summary = _field_bytes(1, val)
    return (struct.pack('<Bd', (1 << 3) | 1, wall_time) + _varint((2 << 3) | 0) + _varint(step)
            + _field_bytes(5, summary))


class EventFileWriter:
    """Appends scalar events to ``events.out.tfevents.<time>.<host>`` in ``log_dir``."""

    def __init__(self, log_dir: Path) -> None:
        log_dir.mkdir(parents=True, exist_ok=True)
        self.path = log_dir / f'events.out.tfevents.{int(time.time())}.{socket.gethostname()}'
        self._f = self.path.open('wb')
        header = struct.pack('<Bd', (1 << 3) | 1, time.time()) + _field_bytes(
            3, b'brain.Event:2')
        self._write(header)

    def _write(self, data: bytes) -> None:
        length = struct.pack('<Q', len(data))
        self._f.write(length + struct.pack('<I', _masked_crc(length)) + data
                      + struct.pack('<I', _masked_crc(data)))

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        """Write one scalar."""
        self._write(encode_scalar_event(tag, value, step, time.time()))

    def close(self) -> None:
        """Flush and close the file."""
        self._f.close()


def read_event_scalars(path: Path) -> list[tuple[str, float, int]]:
    """Parse scalars back from an event file written by :class:`EventFileWriter` (tests)."""
    out = []
    data = path.read_bytes()
    pos = 0
    while pos < len(data):
        (n,) = struct.unpack_from('<Q', data, pos)
        rec = data[pos + 12:pos + 12 + n]
        (crc,) = struct.unpack_from('<I', data, pos + 12 + n)
        if crc != _masked_crc(rec):
            raise ValueError(f'corrupt record at byte {pos}: CRC mismatch')
        pos += 16 + n
        if b'brain.Event' in rec:
            continue
        step_at = 9
        step, i, shift = 0, step_at + 1, 0
        while True:
            b = rec[i]
            step |= (b & 0x7F) << shift
            i += 1
            shift += 7
            if not b & 0x80:
                break
        # skip summary field header + len + value field header + len + tag header
        i += 2
        i += 2
        tag_len = rec[i + 1]
        tag = rec[i + 2:i + 2 + tag_len].decode()
        (value,) = struct.unpack_from('<f', rec, i + 2 + tag_len + 1)
        out.append((tag, value, step))
    return out


class ScalarLogger:
    """Flat metric names (``losses/value_loss``) to a long-format CSV and an event file."""

    def __init__(self, log_dir: Path, tensorboard: bool = True,
                 resume_step: int | None = None) -> None:
        """``resume_step``: continue the CSV of a resumed run, dropping its rows past that step
        (logged after the checkpoint the run resumes from); the event file is a new one."""
        log_dir.mkdir(parents=True, exist_ok=True)
        path = log_dir / 'scalars.csv'
        kept: list[list[str]] = []
        if resume_step is not None and path.is_file():
            with path.open(newline='') as f:
                kept = [r for r in list(csv.reader(f))[1:]
                        if len(r) == 3 and r[0].isdigit() and int(r[0]) <= resume_step]
        self._csv_file = path.open('w', newline='')
        self._csv = csv.writer(self._csv_file)
        self._csv.writerow(['step', 'tag', 'value'])
        self._csv.writerows(kept)
        self._tb = EventFileWriter(log_dir) if tensorboard else None

    def log(self, step: int, scalars: dict[str, float]) -> None:
        """Write every scalar of ``scalars`` at ``step``."""
        for tag, value in scalars.items():
            self._csv.writerow([step, tag, f'{float(value):.8g}'])
            if self._tb is not None:
                self._tb.add_scalar(tag, float(value), step)
        self._csv_file.flush()

    def close(self) -> None:
        """Close the files."""
        self._csv_file.close()
        if self._tb is not None:
            self._tb.close()
