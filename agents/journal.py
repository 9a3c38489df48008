"""A durable append-only journal, from which a restarted agent rebuilds exactly its belief.

The agent appends every own sensor frame and every accepted stack message, already validated and
in wire form, then commits once per step; replaying the records in order reproduces the belief.
The file is a sequence of records ``[u32 LE payload length][u32 LE crc32 of payload][payload]``
with payload = msgpack ``[kind, body]``. The first record, kind ``"header"``, holds the format
version and the caller's identity (robot id, seed, scenario hash...): a journal is never reused
by another robot or run.

Why a log and not SQLite: a step is one sequential ``write`` and one ``fsync``, with no page
cache, B-tree or WAL checkpoint in between; the records are opaque bytes that only get replayed
in order, so a query engine buys nothing; and crash recovery is one rule — keep the longest
prefix of intact records (length, crc32 and payload all check out) and truncate the rest —
tested at every byte offset of a torn tail. An intact record after a corrupt one is dropped too:
order matters in a replay, and a gap would rebuild a belief the agent never had.

Durability: a record is on disk once :meth:`Journal.commit` returned (``fsync``); the file is
created under a temporary name with its header, fsynced, linked into place (never replacing an
existing journal) and its directory fsynced, so a journal is never seen without its header.
One process at a time may hold a journal (``flock``).
"""

from __future__ import annotations

import fcntl
import logging
import os
import re
import struct
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import msgpack

log = logging.getLogger(__name__)

FORMAT = 1
HEADER = "header"
KIND = re.compile(r"^[a-z_]{1,16}$")
_PREFIX = struct.Struct("<II")  # payload length, crc32 of payload
_MAX_PAYLOAD = 2**32 - 1


class JournalError(Exception):
    """A journal that may not be used: not a journal, another identity, already in use.
    ``key`` names the mismatching identity key, when that is the reason."""

    def __init__(self, message: str, key: str = "") -> None:
        super().__init__(message)
        self.key = key


@dataclass(frozen=True, slots=True)
class Record:
    """One journal entry: what it is (``kind``) and its bytes (usually a wire message)."""

    kind: str
    body: bytes


def _frame(kind: str, body: bytes) -> bytes:
    payload = msgpack.packb([kind, body], use_bin_type=True)
    if len(payload) > _MAX_PAYLOAD:
        raise ValueError(f"record of {len(payload)} bytes is too large for a journal")
    return _PREFIX.pack(len(payload), zlib.crc32(payload)) + payload


def _parse(data: bytes, offset: int) -> tuple[Record, int] | None:
    """The intact record at ``offset`` and the offset after it, or None if torn or corrupt."""
    if len(data) - offset < _PREFIX.size:
        return None
    length, crc = _PREFIX.unpack_from(data, offset)
    start = offset + _PREFIX.size
    payload = data[start : start + length]
    if len(payload) != length or zlib.crc32(payload) != crc:
        return None
    try:
        doc = msgpack.unpackb(payload, raw=False)
    except Exception:  # any undecodable payload (msgpack raises many types) ends the intact prefix
        return None
    if not (isinstance(doc, list) and len(doc) == 2):
        return None
    kind, body = doc
    if not (isinstance(kind, str) and KIND.fullmatch(kind) and isinstance(body, bytes)):
        return None
    return Record(kind, body), start + length


def _check_identity(identity: Mapping[str, str | int]) -> dict[str, str | int]:
    for key, value in identity.items():
        ok = isinstance(key, str) and isinstance(value, str | int) and not isinstance(value, bool)
        if not ok:
            raise JournalError(f"identity {key!r}: expected a string key and a str or int value")
    return dict(identity)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _create(path: Path, identity: dict[str, str | int]) -> None:
    """Make ``path`` a journal holding only its header, unless a journal is already there."""
    missing = [p for p in (path.parent, *path.parent.parents) if not p.exists()]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    header = msgpack.packb({"format": FORMAT, "identity": identity}, use_bin_type=True)
    with open(tmp, "wb") as f:
        f.write(_frame(HEADER, header))
        f.flush()
        os.fsync(f.fileno())
    try:
        os.link(tmp, path)  # unlike a rename, never replaces a journal created meanwhile
    except FileExistsError:
        pass
    finally:
        tmp.unlink()
    for directory in (path.parent, *(p.parent for p in missing)):
        _fsync_dir(directory)


class Journal:
    """An open journal; see the module docstring. Use :meth:`open`, not the constructor."""

    def __init__(self, path: Path, fd: int, size: int, truncated_bytes: int) -> None:
        self.path = path
        self.truncated_bytes = truncated_bytes  # torn or corrupt tail dropped by open
        self._fd: int | None = fd
        self._size = size  # bytes on disk, all of them committed
        self._pending = bytearray()

    @classmethod
    def open(cls, path: Path, identity: Mapping[str, str | int]) -> tuple[Journal, list[Record]]:
        """Open (or create) the journal of ``identity`` at ``path`` and read its records.

        Raises :class:`JournalError` if ``path`` is not a journal, belongs to another identity
        (``key`` names the first differing key) or is open in another process.
        """
        ident = _check_identity(identity)
        path = Path(path)
        if not path.exists():
            _create(path, ident)
        fd = os.open(path, os.O_RDWR | os.O_APPEND)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise JournalError(f"{path} is in use by another process") from None
        try:
            records, end, size = _read(path, ident)
            if end < size:
                log.warning(
                    "journal %s: dropped %d bytes of torn or corrupt tail", path, size - end
                )
                os.ftruncate(fd, end)
                os.fsync(fd)
        except BaseException:
            os.close(fd)
            raise
        return cls(path, fd, end, size - end), records

    def append(self, kind: str, body: bytes | bytearray | memoryview) -> None:
        """Queue a record; it reaches the disk with the next :meth:`commit`."""
        if not (isinstance(kind, str) and KIND.fullmatch(kind)) or kind == HEADER:
            raise ValueError(f"invalid record kind {kind!r}")
        if not isinstance(body, bytes | bytearray | memoryview):
            raise TypeError(f"record body must be bytes, got {type(body).__name__}")
        self._open_fd()
        self._pending += _frame(kind, bytes(body))

    def commit(self) -> None:
        """Write the queued records and fsync: once this returns they survive a crash."""
        fd = self._open_fd()
        if not self._pending:
            return
        data = bytes(self._pending)
        try:
            written = 0
            while written < len(data):
                written += os.write(fd, data[written:])
            os.fsync(fd)
        except OSError:
            os.ftruncate(fd, self._size)  # leave no half-written step behind
            raise
        self._size += len(data)
        self._pending.clear()

    def close(self) -> None:
        """Commit what is queued and close. Closing twice is harmless."""
        if self._fd is None:
            return
        try:
            self.commit()
        finally:
            self._release()

    def _release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # also releases the flock
            self._fd = None

    def _open_fd(self) -> int:
        if self._fd is None:
            raise JournalError(f"{self.path} is closed")
        return self._fd

    def __enter__(self) -> Journal:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close()
            return
        # A step that failed half-way is not committed: the journal keeps whole steps only.
        self._pending.clear()
        self._release()


def _read(path: Path, identity: dict[str, str | int]) -> tuple[list[Record], int, int]:
    """Records after the header, the offset after the last intact one, and the file size."""
    data = path.read_bytes()
    first = _parse(data, 0)
    header = _header(first[0]) if first else None
    if first is None or header is None:
        raise JournalError(f"{path} is not a semfleet journal (no valid header)")
    if header.get("format") != FORMAT or not isinstance(header.get("identity"), dict):
        raise JournalError(f"{path}: not a journal of format {FORMAT}")
    stored = header["identity"]
    for key in sorted(set(stored) | set(identity), key=str):
        mine, theirs = identity.get(key), stored.get(key)
        if (type(mine), mine) != (type(theirs), theirs):
            raise JournalError(
                f"{path} belongs to another run: identity {key!r} is {theirs!r} in the journal, "
                f"{mine!r} here",
                str(key),
            )
    records = []
    end = first[1]
    while (parsed := _parse(data, end)) is not None and parsed[0].kind != HEADER:
        records.append(parsed[0])
        end = parsed[1]
    return records, end, len(data)


def _header(record: Record) -> dict[str, Any] | None:
    if record.kind != HEADER:
        return None
    try:
        header = msgpack.unpackb(record.body, raw=False)
    except Exception:  # an undecodable header means "not a journal", whatever msgpack raised
        return None
    return header if isinstance(header, dict) else None
