"""Reading an MCAP file whose writer never closed it: up to its last complete record.

A recording whose process was killed (SIGKILL, a power cut, the machine going down) ends where
the writer's last flush left it: no ``DataEnd``, no summary, no footer, perhaps half a record.
The ``mcap`` package's seeking reader starts at the footer and refuses such a file whole,
although everything before the cut is intact (:mod:`biris_hw.io.record.mcapfile` flushes after
every chunk). Here the file is walked record by record from its start -- opcode and length only,
a seek per record -- to the end of the last record that is wholly in the file; the package's
streaming reader (:class:`mcap.reader.NonSeekingReader`) then reads up to that offset and no
further, so the cut is a clean end, and a CRC error or a bad record before it is still an error
(a damaged file does not pass for a cut one). Its messages come in file order (the streaming
reader's log-time order sorts the whole file in memory, and yields nothing if the file then ends
in an error); :func:`time_ordered` puts them in log-time order through a bounded window, which is
exact for a recording, whose messages are out of order by at most a batch.
"""

from __future__ import annotations

import heapq
import io
import os
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, cast

from mcap.exceptions import EndOfFile
from mcap.opcode import Opcode
from mcap.reader import NonSeekingReader
from mcap.records import Channel, McapRecord, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import MCAP0_MAGIC

__all__ = ["WINDOW", "Cut", "cut_of", "ends_with_footer", "messages", "records", "time_ordered"]

_HEAD = 9
"""A record's opcode (1 byte) and length (8 bytes)."""

_FOOTER = _HEAD + 8 + 8 + 4
"""A footer record: summary start, summary offset start, summary CRC."""

WINDOW = 1024
"""Messages held back to put a file's messages in log-time order (see :func:`time_ordered`)."""

_WINDOW_BYTES = 16 << 20
"""...and at most this many bytes of them (a window of large scans)."""


@dataclass(frozen=True)
class Cut:
    """Where a file without its footer is read to: ``end``, the end of its last complete record
    (of ``size`` bytes), after ``chunks`` complete chunks."""

    end: int
    size: int
    chunks: int

    def describe(self, path: Path) -> str:
        """One sentence for a person: what the file is and how much of it plays."""
        lost = self.size - self.end
        rest = f"; the last {lost:,}, an unfinished record, are left out" if lost else ""
        return (
            f"{path} ends without a footer (its writer was stopped before it closed the file: "
            f"killed, or the machine went down); playing it up to its last complete chunk "
            f"({self.chunks} chunks, {self.end:,} of {self.size:,} bytes{rest})"
        )


def ends_with_footer(f: IO[bytes]) -> bool:
    """True if the file ends as a closed MCAP file does: a footer record and the magic."""
    size = f.seek(0, os.SEEK_END)
    if size < len(MCAP0_MAGIC) * 2 + _FOOTER:
        return False
    f.seek(size - _FOOTER - len(MCAP0_MAGIC))
    tail = f.read(_FOOTER + len(MCAP0_MAGIC))
    opcode, length = struct.unpack_from("<BQ", tail)
    return opcode == Opcode.FOOTER and length == _FOOTER - _HEAD and tail.endswith(MCAP0_MAGIC)


def cut_of(f: IO[bytes]) -> Cut | None:
    """The end of the last record wholly in the file (an MCAP file read from its start), or
    None if it does not begin as an MCAP file (its magic)."""
    size = f.seek(0, os.SEEK_END)
    f.seek(0)
    if f.read(len(MCAP0_MAGIC)) != MCAP0_MAGIC:
        return None
    pos = len(MCAP0_MAGIC)
    chunks = 0
    while True:
        f.seek(pos)
        head = f.read(_HEAD)
        if len(head) < _HEAD:
            break
        opcode, length = struct.unpack("<BQ", head)
        if length > size - pos - _HEAD:
            break  # the record the writer was writing when it stopped
        pos += _HEAD + length
        chunks += opcode == Opcode.CHUNK
        if opcode == Opcode.FOOTER:
            break
    return Cut(pos, size, chunks)


class _Prefix(io.BufferedIOBase):
    """The first ``end`` bytes of a binary stream, read straight through (the streaming reader
    calls ``read`` only); :attr:`pos` is how far it has been read."""

    def __init__(self, stream: IO[bytes], end: int) -> None:
        super().__init__()
        self._stream = stream
        self._end = end
        self.pos = 0

    def readable(self) -> bool:
        return True

    def read(self, size: int | None = -1) -> bytes:
        left = self._end - self.pos
        n = left if size is None or size < 0 else min(size, left)
        data = self._stream.read(n) if n > 0 else b""
        self.pos += len(data)
        return data


Item = tuple[Schema | None, Channel, Message]


def records(f: IO[bytes], cut: Cut) -> Iterator[McapRecord]:
    """Every record of the file up to ``cut.end`` (those of its chunks one by one), in file
    order; the end of the last complete record is a clean end.

    Raises what the reader raises on a damaged part before it (a record that does not parse).
    """
    f.seek(0)
    prefix = _Prefix(f, cut.end)
    try:
        yield from StreamReader(cast("IO[bytes]", prefix)).records
    except EndOfFile:
        if prefix.pos < cut.end:  # ended inside a record that claimed to be complete
            raise


def messages(f: IO[bytes], cut: Cut, topics: Iterable[str] | None = None) -> Iterator[Item]:
    """The messages of the file (on ``topics``) up to ``cut.end``, in file order, CRCs checked;
    the end of the last complete record is a clean end.

    Raises what the reader raises on a damaged part before it (a CRC error, a record that does
    not parse).
    """
    f.seek(0)
    prefix = _Prefix(f, cut.end)
    reader = NonSeekingReader(cast("IO[bytes]", prefix), validate_crcs=True)
    wanted = None if topics is None else list(topics)
    try:
        yield from reader.iter_messages(topics=wanted, log_time_order=False)
    except EndOfFile:
        if prefix.pos < cut.end:
            raise


def time_ordered(items: Iterable[Item], *, window: int = WINDOW) -> Iterator[Item]:
    """``items`` (messages read in file order) in log-time order, holding back at most
    ``window`` of them (and about 16 MB): exact when no message is more than a window out of
    place. What was held back is handed over before an error the reader raises is."""
    held: list[tuple[int, int, int, Item]] = []
    size = 0
    seq = 0
    failure: Exception | None = None
    try:
        for item in items:
            message = item[2]
            heapq.heappush(held, (message.log_time, seq, len(message.data), item))
            seq += 1
            size += len(message.data)
            while len(held) > window or size > _WINDOW_BYTES:
                _t, _s, n, out = heapq.heappop(held)
                size -= n
                yield out
    except Exception as exc:  # a damaged part: what came before it is played first
        failure = exc
    while held:
        yield heapq.heappop(held)[3]
    if failure is not None:
        raise failure
