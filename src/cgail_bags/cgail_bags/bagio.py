"""Reading and writing rosbag2 MCAP bags with rosbags (no rosbag2/ros2cli here).

* :class:`BagWriter` writes raw CDR messages to a rosbag2 (version 9, MCAP storage) directory,
  storing each topic's offered QoS profiles in ``metadata.yaml`` exactly as rosbag2 does
  (``offered_qos_profiles``) and free-form ``custom_data`` (e.g. ``condition: cgail``).
  :meth:`BagWriter.flush` closes the pending MCAP chunk and flushes it to disk.
* :class:`JazzyWriter` is rosbags' ``Writer`` stamping ``ros_distro: jazzy`` (what rosbag2 on
  Jazzy writes) instead of ``ros_distro: rosbags``, in ``metadata.yaml`` and in the MCAP file's
  ``rosbag2`` metadata record alike. Every bag this workspace writes goes through it.
* :func:`open_bag` / :func:`iter_raw` read a bag directory or a bare ``.mcap`` file and turn
  every failure of a missing, truncated or corrupt bag into one :class:`BagError` naming the
  path and the problem.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path
import struct
from typing import Any

from rosbags.interfaces import Connection, Qos
from rosbags.rosbag2 import (
    CompressionFormat,
    CompressionMode,
    Reader,
    ReaderError,
    StoragePlugin,
    Writer,
    WriterError,
)
from rosbags.typesys import get_typestore, Stores
from rosbags.typesys.store import Typestore
import yaml

from cgail_bags.errors import BagError

#: Type store of every bag written and read here.
TYPESTORE: Typestore = get_typestore(Stores.ROS2_JAZZY)
#: ``ros_distro`` of every bag written here: the distribution the messages belong to.
ROS_DISTRO = 'jazzy'

#: Exceptions the rosbags reader raises on broken files (wrapped into BagError).
_READ_ERRORS = (ReaderError, struct.error, EOFError, KeyError, IndexError, ValueError,
                UnicodeDecodeError, AssertionError, OSError, TypeError, OverflowError,
                MemoryError)


def _with_distro(info_yaml: str) -> str:
    """The ``rosbag2_bagfile_information`` YAML text with ``ros_distro`` set to ``jazzy``."""
    info = yaml.safe_load(info_yaml)
    info['ros_distro'] = ROS_DISTRO
    return yaml.safe_dump(info, default_flow_style=False, sort_keys=False).strip()


class JazzyWriter(Writer):
    """rosbags' ``Writer`` that records ``ros_distro: jazzy`` instead of ``rosbags``.

    rosbags hard-codes ``ros_distro: rosbags`` into the metadata it writes at :meth:`close`:
    into ``metadata.yaml`` and into the MCAP ``rosbag2`` metadata record (which readers of a
    bare ``.mcap`` use). Both are rewritten to name the distribution, as ``ros2 bag record`` on
    Jazzy does; everything else stays as rosbags wrote it, so rosbags' ``Reader`` (and rosbag2)
    read the bag as before.
    """

    def close(self) -> None:
        """Close the storage, writing both metadata copies with ``ros_distro: jazzy``."""
        storage = self.storage
        if storage is not None:
            close_storage = storage.close

            def close_with_distro(version: int, metadata: str) -> None:
                close_storage(version, _with_distro(metadata))

            storage.close = close_with_distro  # type: ignore[method-assign]
        super().close()
        doc = yaml.safe_load(self.metapath.read_text())
        doc['rosbag2_bagfile_information']['ros_distro'] = ROS_DISTRO
        tmp = self.metapath.with_suffix('.yaml.tmp')
        tmp.write_text(yaml.safe_dump(doc, default_flow_style=False, sort_keys=False))
        tmp.replace(self.metapath)


class BagWriter:
    """Write raw CDR messages into a new rosbag2 MCAP bag directory.

    Not thread-safe: one thread (the recorder's writer thread) owns it.

    Args:
        path: Bag directory to create; must not exist.
        custom_data: ``metadata.yaml`` custom_data entries (strings).
        compress: zstd-compress each MCAP chunk (rosbag2's ``storage`` compression mode, which
            rosbag2, rosbags, the ``mcap`` package and Foxglove read transparently).
    """

    def __init__(self, path: Path | str, custom_data: dict[str, str] | None = None, *,
                 compress: bool = False) -> None:
        self.path = Path(path)
        try:
            self._writer = JazzyWriter(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
            if compress:
                self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
            for key, value in (custom_data or {}).items():
                self._writer.set_custom_data(key, str(value))
            self._writer.open()
        except WriterError as exc:
            raise BagError(f'{self.path}: cannot create bag ({exc})') from None
        self._connections: dict[str, Connection] = {}
        self.count = 0

    def add_topic(self, topic: str, msgtype: str, qos: Sequence[Qos] = ()) -> None:
        """Declare a topic (``msgtype`` like ``geometry_msgs/msg/PoseStamped``) and its QoS."""
        if topic in self._connections:
            return
        try:
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=TYPESTORE, offered_qos_profiles=list(qos))
        except (WriterError, KeyError) as exc:
            raise BagError(f'{self.path}: cannot add topic {topic} of type {msgtype} '
                           f'(expected a ROS 2 Jazzy message type; {exc})') from None

    def has_topic(self, topic: str) -> bool:
        """Whether :meth:`add_topic` was called for ``topic``."""
        return topic in self._connections

    def write(self, topic: str, timestamp_ns: int, data: bytes | memoryview) -> None:
        """Append one serialized (CDR) message received at ``timestamp_ns``."""
        conn = self._connections.get(topic)
        if conn is None:
            raise BagError(f'{self.path}: topic {topic} was not added before writing')
        self._writer.write(conn, int(timestamp_ns), bytes(data))
        self.count += 1

    def flush(self) -> None:
        """Move buffered messages to the file (close the pending MCAP chunk, fsync-free flush).

        rosbags keeps the open chunk in memory; closing it and flushing the file bounds what
        a hard kill can lose. The summary/index is still written only by :meth:`close`.
        """
        storage = self._writer.storage
        if storage is None:
            return
        chunk = getattr(storage, 'chunk', None)
        if chunk is not None and chunk.bio.tell() and hasattr(storage, 'close_chunk'):
            storage.close_chunk()
        bio = getattr(storage, 'bio', None)
        if bio is not None:
            bio.flush()

    def close(self) -> None:
        """Write the MCAP summary and ``metadata.yaml``; idempotent."""
        if self._writer.storage is not None:
            self._writer.close()

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _describe(path: Path, exc: BaseException) -> str:
    detail = str(exc) or type(exc).__name__
    if not path.exists():
        return f'{path}: no such bag (expected a rosbag2 directory or an .mcap file)'
    hint = ''
    if path.is_dir() and not (path / 'metadata.yaml').exists():
        detail = 'metadata.yaml is missing'
        hint = ('; a recording that was killed can be recovered with '
                '`python -m cgail_bags.recover`')
    return (f'{path}: truncated or corrupt bag, cannot read it '
            f'(expected a complete rosbag2 MCAP bag; {type(exc).__name__}: {detail}){hint}')


@contextmanager
def open_bag(path: Path | str) -> Iterator[Reader]:
    """Open a bag for reading; every read error inside the block becomes a :class:`BagError`.

    Args:
        path: rosbag2 directory (with ``metadata.yaml``) or a bare ``.mcap`` file.
    """
    bag = Path(path)
    try:
        reader = Reader(bag)
        reader.open()
    except _READ_ERRORS as exc:
        raise BagError(_describe(bag, exc)) from None
    try:
        yield reader
    except BagError:
        raise
    except _READ_ERRORS as exc:
        raise BagError(_describe(bag, exc)) from None
    finally:
        with suppress(*_READ_ERRORS):
            reader.close()


def bag_custom_data(reader: Reader) -> dict[str, str]:
    """The bag's ``metadata.yaml`` custom_data (empty for a bare .mcap file)."""
    meta = getattr(reader.storage, 'metadata', None)
    custom = getattr(meta, 'custom', None)
    return dict(custom or {})


def iter_raw(
    reader: Reader, topics: Sequence[str] | None = None, start_ns: int | None = None
) -> Iterator[tuple[Connection, int, bytes]]:
    """Raw messages ``(connection, log_time_ns, cdr_bytes)`` in log-time order.

    When the whole bag is read (no ``start_ns``), the number of messages of each connection is
    checked against the bag's index: a chunk whose records were damaged (read as nothing)
    raises :class:`BagError` at the end instead of silently losing messages.

    Args:
        reader: An open reader (from :func:`open_bag`).
        topics: Only these topics (None: all).
        start_ns: Skip messages logged before this time.
    """
    conns = [c for c in reader.connections if topics is None or c.topic in topics]
    if not conns:
        return
    counts = dict.fromkeys((c.id for c in conns), 0)
    for conn, timestamp, raw in reader.messages(connections=conns, start=start_ns):
        counts[conn.id] += 1
        yield conn, timestamp, raw
    if start_ns is None:
        for conn in conns:
            if conn.msgcount and counts[conn.id] != conn.msgcount:
                raise BagError(f'{reader.path}: truncated or corrupt bag, topic {conn.topic}: '
                               f'expected {conn.msgcount} messages (bag index), read '
                               f'{counts[conn.id]}')


def content_digest(path: Path | str) -> dict[str, tuple[int, str]]:
    """Per topic: the number of messages and a SHA-256 of their log times and CDR bytes, in
    log-time order. Two bags with equal digests hold the same messages, however their MCAP
    chunks were laid out (what a deterministic simulated session must reproduce)."""
    import hashlib

    digests: dict[str, Any] = {}
    counts: dict[str, int] = {}
    with open_bag(path) as reader:
        for conn, timestamp, raw in iter_raw(reader):
            h = digests.setdefault(conn.topic, hashlib.sha256())
            h.update(timestamp.to_bytes(8, 'little', signed=True))
            h.update(bytes(raw))
            counts[conn.topic] = counts.get(conn.topic, 0) + 1
    return {t: (counts[t], digests[t].hexdigest()) for t in sorted(digests)}
