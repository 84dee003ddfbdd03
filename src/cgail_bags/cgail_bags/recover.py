"""Recover the messages of an MCAP bag whose recorder was killed before closing it.

    cgail bag recover CRASHED_BAG -o RECOVERED_BAG

``cgail bag record`` closes its bag cleanly on SIGINT/SIGTERM. After a hard kill (SIGKILL, power
loss) the file has the chunks flushed so far (every ``--flush-period``) but no summary, index or
``metadata.yaml``, so readers refuse it. This tool scans the file's records from the start,
keeps every complete chunk's schemas, channels (with their ``offered_qos_profiles``) and
messages, stops at the first incomplete record, and writes them to a new, complete bag.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
import struct
import sys

from rosbags.interfaces import Qos
from rosbags.rosbag2.metadata import parse_qos

from cgail_bags.bagio import BagWriter
from cgail_bags.errors import BagError
from cgail_sim.cli_help import tool_parser

MAGIC = b'\x89MCAP0\r\n'
OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x03, 0x04, 0x05, 0x06


@dataclass(frozen=True)
class Recovered:
    """What :func:`recover_bag` found."""

    messages: int
    """Messages written to the new bag."""
    topics: tuple[str, ...]
    """Topics with at least a channel record."""
    complete: bool
    """The source ended with a valid record boundary (nothing cut mid-record)."""


def _records(data: memoryview) -> Iterator[tuple[int, memoryview]]:
    """(opcode, content) of each complete record; stops at the first incomplete one."""
    pos = 0
    while pos + 9 <= len(data):
        op = data[pos]
        (length,) = struct.unpack_from('<Q', data, pos + 1)
        end = pos + 9 + length
        if end > len(data):
            return
        yield op, data[pos + 9:end]
        pos = end


def _string(buf: memoryview, pos: int) -> tuple[str, int]:
    (n,) = struct.unpack_from('<I', buf, pos)
    return bytes(buf[pos + 4:pos + 4 + n]).decode(), pos + 4 + n


def _chunk_records(chunk: memoryview) -> memoryview:
    pos = 8 + 8 + 8 + 4  # start, end, uncompressed size, crc
    compression, pos = _string(chunk, pos)
    (size,) = struct.unpack_from('<Q', chunk, pos)
    records = chunk[pos + 8:pos + 8 + size]
    if compression == '':
        return records
    if compression == 'zstd':
        try:  # as rosbags does: the stdlib module on Python >= 3.14, else backports.zstd
            from compression import zstd  # type: ignore[import-not-found]
        except ImportError:
            from backports import zstd  # type: ignore[import-not-found,no-redef]
        return memoryview(zstd.decompress(bytes(records)))
    raise BagError(f'unsupported MCAP chunk compression {compression!r} (expected none or zstd)')


def _find_mcap(path: Path) -> Path:
    if path.is_file():
        return path
    files = sorted(path.glob('*.mcap')) if path.is_dir() else []
    if len(files) != 1:
        raise BagError(f'{path}: expected one .mcap file to recover, found {len(files)}')
    return files[0]


def recover_bag(source: Path | str, output: Path | str) -> Recovered:
    """Copy every complete chunk's messages of ``source`` into a new bag ``output``.

    Raises:
        BagError: Not an MCAP file, nothing recoverable, or the output exists.
    """
    mcap = _find_mcap(Path(source))
    data = memoryview(mcap.read_bytes())
    if bytes(data[:8]) != MAGIC:
        raise BagError(f'{mcap}: not an MCAP file (expected the MCAP magic at the start)')
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str, list[Qos]]] = {}
    messages: list[tuple[int, int, bytes]] = []
    consumed = 8
    try:
        for op, content in _records(data[8:]):
            consumed += 9 + len(content)
            if op != OP_CHUNK:
                continue
            for inner_op, rec in _records(_chunk_records(content)):
                if inner_op == OP_SCHEMA:
                    (sid,) = struct.unpack_from('<H', rec, 0)
                    schemas[sid] = _string(rec, 2)[0]
                elif inner_op == OP_CHANNEL:
                    cid, sid = struct.unpack_from('<HH', rec, 0)
                    topic, pos = _string(rec, 4)
                    _, pos = _string(rec, pos)  # message encoding (cdr)
                    (meta_len,) = struct.unpack_from('<I', rec, pos)
                    meta, mpos, qos = rec[pos + 4:pos + 4 + meta_len], 0, []
                    while mpos < len(meta):
                        key, mpos = _string(meta, mpos)
                        value, mpos = _string(meta, mpos)
                        if key == 'offered_qos_profiles':
                            qos = parse_qos(value)
                    channels[cid] = (topic, schemas[sid], qos)
                elif inner_op == OP_MESSAGE:
                    (cid,) = struct.unpack_from('<H', rec, 0)
                    (log_time,) = struct.unpack_from('<Q', rec, 6)
                    messages.append((cid, log_time, bytes(rec[22:])))
    except (struct.error, KeyError, UnicodeDecodeError) as exc:
        raise BagError(f'{mcap}: cannot recover, corrupt record ({type(exc).__name__}: '
                       f'{exc})') from None
    if not channels:
        raise BagError(f'{mcap}: nothing to recover (no complete chunk with a channel)')
    with BagWriter(output, custom_data={'recovered_from': str(mcap)}) as writer:
        for topic, msgtype, qos in channels.values():
            writer.add_topic(topic, msgtype, qos)
        for cid, log_time, payload in sorted(messages, key=lambda m: m[1]):
            if cid in channels:
                writer.write(channels[cid][0], log_time, payload)
        count = writer.count
    complete = consumed == len(data) or (consumed == len(data) - 8 and
                                         bytes(data[-8:]) == MAGIC)
    return Recovered(count, tuple(sorted(t for t, _, _ in channels.values())), complete)


def build_parser() -> argparse.ArgumentParser:
    """Command-line options of ``cgail bag recover``."""
    parser = tool_parser('bag recover', __doc__, details=True)
    parser.add_argument('bag', type=Path, help='crashed bag directory or .mcap file')
    parser.add_argument('-o', '--output', type=Path, required=True, help='new bag directory')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgail bag recover``; exit status 2 on failure."""
    args = build_parser().parse_args(argv)
    try:
        result = recover_bag(args.bag, args.output)
    except BagError as exc:
        print(f'cgail bag recover: error: {exc}', file=sys.stderr)
        return 2
    tail = '' if result.complete else ' (the source ends mid-record: that part is lost)'
    print(f'cgail bag recover: wrote {result.messages} messages on {len(result.topics)} topics to '
          f'{args.output}{tail}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
