"""One MCAP file being written, that stays a valid file whatever happens to the disk under it.

The ``mcap`` package's :class:`~mcap.writer.Writer` does the format; this class adds what a
recording needs around it: channels registered by topic on first use (ros2msg schemas, CDR
messages), one lock for the threads that write, and a defined outcome when writing fails (a full
disk, a device removed). The writer keeps messages in a chunk in memory and writes the chunk when
it is full; after every write that reached the file the stream is flushed and its end recorded as
the *good* offset, a record boundary with everything before it on disk. When a write fails the
file is cut back to that offset and closed with a ``DataEnd`` and a footer without summary: a
valid MCAP file that readers scan from the start (the summary, which only speeds reading up, is
what needed the space). The messages of the chunk that could not be written are lost, and
counted (:attr:`McapFile.lost`). On a normal close -- the end of a run, or Ctrl-C -- the summary
is written as usual.
"""

from __future__ import annotations

import errno
import os
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import IO, Any

from mcap.data_stream import RecordBuilder
from mcap.records import DataEnd, Footer
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer

from biris_hw._version import __version__
from biris_hw.errors import BirisError

__all__ = ["CHUNK_SIZE", "McapFile", "RecordError"]

CHUNK_SIZE = 1 << 20
"""Bytes of messages per chunk: large enough for zstd to do well, small enough to lose little."""


class RecordError(BirisError, OSError):
    """A recording's file cannot be written: an unwritable path (raised before anything is
    recorded) or a failure while writing (a full disk); in the latter case what was written
    before stays a valid MCAP file, and the message says how much was lost."""

    def __init__(self, message: str, err: int = errno.EIO) -> None:
        OSError.__init__(self, err, message)

    def __str__(self) -> str:
        return str(self.strerror)


def _open_stream(path: Path) -> IO[bytes]:
    """The binary stream the writer writes to (tests replace it to make a disk fill up)."""
    return open(path, "wb")  # closed by McapFile.close


def _tail() -> bytes:
    """``DataEnd``, a footer that says "no summary", and the closing magic."""
    builder = RecordBuilder()
    DataEnd(data_section_crc=0).write(builder)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(builder)
    data: bytes = builder.end()  # type: ignore[no-untyped-call]
    return bytes(data) + MCAP0_MAGIC


class McapFile:
    """An MCAP file open for writing: ROS 2 profile, CDR messages, ros2msg schemas.

    ``overwrite=False`` refuses a file that exists (created exclusively, so a file that appears
    between a caller's own check and this one is refused too).

    Raises:
        RecordError: the file cannot be created (a folder that does not exist or is not
            writable, a name that is a folder, a file that exists and ``overwrite`` is False);
            nothing is left behind, and an existing file is untouched.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        chunk_size: int = CHUNK_SIZE,
        compression: CompressionType = CompressionType.ZSTD,
        overwrite: bool = True,
    ) -> None:
        self.path = Path(path)
        made = False
        try:
            if not overwrite:
                os.close(os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
                made = True
            self._stream = _open_stream(self.path)
        except FileExistsError as exc:
            raise RecordError(
                f"{self.path} exists: not overwritten (a recording is never replaced unasked)",
                errno.EEXIST,
            ) from exc
        except OSError as exc:
            if made:
                self.path.unlink(missing_ok=True)
            raise RecordError(
                f"cannot write {self.path}: {exc.strerror or exc}", exc.errno or errno.EIO
            ) from exc
        self._lock = threading.Lock()
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._writer = Writer(self._stream, chunk_size=chunk_size, compression=compression)
        self.messages = 0
        """Messages handed to the writer (including those :attr:`lost`)."""
        self.lost = 0
        """Messages that never reached the disk: the chunk under way when writing failed."""
        self._pending = 0
        self.error: RecordError | None = None
        self.complete = False
        """True once closed with the summary written."""
        self._closed = False
        self._good = 0
        self._guard(lambda: self._writer.start(profile="ros2", library=f"biris-hw {__version__}"))

    # -- writing -----------------------------------------------------------------------------
    def _guard(self, action: Any) -> bool:
        """Run a writer call; keep the file valid if it fails. False once failed."""
        if self.error is not None or self._closed:
            return False
        try:
            action()
            if self._stream.tell() != self._good:  # a chunk (or a record) went to the stream
                self._stream.flush()
                self._good = self._stream.tell()
                self._pending = 0
        except OSError as exc:
            self._salvage(exc)
            return False
        return True

    def _salvage(self, exc: OSError) -> None:
        """Cut the file back to the last good offset and end it there (see the module)."""
        self.lost += self._pending
        self._pending = 0
        reason = exc.strerror or str(exc)
        try:
            self._stream.close()  # its flush fails too; the descriptor is closed all the same
        except OSError:
            pass
        kept = "kept"
        try:
            fd = os.open(self.path, os.O_WRONLY)
            try:
                os.ftruncate(fd, self._good)
                os.pwrite(fd, _tail(), self._good)
            finally:
                os.close(fd)
        except OSError as again:
            kept = f"cut at byte {self._good} but not closed ({again.strerror or again})"
        self._closed = True
        self.error = RecordError(
            f"writing {self.path} failed: {reason}; recording stopped. The "
            f"{self.messages - self.lost} messages written before are {kept} in a valid MCAP "
            f"file ({self.lost} lost)",
            exc.errno or errno.EIO,
        )

    def _channel(self, topic: str, msgtype: str, definition: str) -> int:
        channel = self._channels.get(topic)
        if channel is None:
            schema = self._schemas.get(msgtype)
            if schema is None:
                schema = self._writer.register_schema(
                    name=msgtype, encoding="ros2msg", data=definition.encode()
                )
                self._schemas[msgtype] = schema
            channel = self._writer.register_channel(
                topic=topic, message_encoding="cdr", schema_id=schema
            )
            self._channels[topic] = channel
        return channel

    def write(
        self, topic: str, msgtype: str, definition: str, data: bytes, log_time_ns: int
    ) -> bool:
        """Add one CDR message (its channel registered on first use); False if the file has
        failed or is closed (:attr:`error` says why)."""
        with self._lock:

            def add() -> None:
                channel = self._channel(topic, msgtype, definition)
                self.messages += 1
                self._pending += 1
                self._writer.add_message(
                    channel_id=channel,
                    log_time=log_time_ns,
                    data=data,
                    publish_time=log_time_ns,
                    sequence=self.messages,
                )

            return self._guard(add)

    def metadata(self, name: str, values: Mapping[str, str]) -> bool:
        """Add a metadata record (strings only, as MCAP requires)."""
        with self._lock:
            return self._guard(lambda: self._writer.add_metadata(name, dict(values)))

    def flush(self) -> bool:
        """Write the chunk under way now, so a crash loses nothing before this point."""
        with self._lock:
            return self._guard(self._writer.flush)

    def close(self) -> bool:
        """Write the summary and close; True if the file is complete. Idempotent."""
        with self._lock:
            if self._closed:
                return self.complete
            if self._guard(self._writer.finish):
                try:
                    self._stream.close()
                    self.complete = True
                except OSError as exc:
                    self._salvage(exc)
            self._closed = True
            return self.complete
