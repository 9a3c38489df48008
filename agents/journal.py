"""A durable append-only journal, from which a restarted agent rebuilds exactly its belief.

The agent appends every own sensor frame and every accepted stack message, already validated and
in wire form, then commits once per step; replaying the records in order reproduces the belief.
The file is a sequence of records ``[u32 LE payload length][u32 LE crc32 of payload][payload]``
with payload = msgpack ``[kind, body]``. The first record, kind ``"header"``, holds the format
version, the caller's identity (robot id, seed, scenario hash...): a journal is never reused
by another robot or run — and the epoch the caller gave when the journal was made (0 in a
journal made before epochs; docs/wire.md, "Versions and epochs").

Why a log and not SQLite: a step is one sequential ``write`` and one ``fsync``, with no page
cache, B-tree or WAL checkpoint in between; the records are opaque bytes that only get replayed
in order, so a query engine buys nothing; and crash recovery is one rule — replay the longest
prefix of intact records (length, crc32 and payload all check out) and cut the rest off —
tested at every byte offset of a torn tail. An intact record after a corrupt one is not
replayed either: order matters in a replay, and a gap would rebuild a belief the agent never had.

Nothing is cut off unread, though: every byte after the intact prefix is first copied to a side
file ``<journal name>.corrupt-<offset>`` next to the journal (``offset``: the decimal byte offset
in the journal where the dropped bytes began, i.e. the journal's size after the cut; if that name
is taken by an earlier recovery, ``.2``, ``.3``… is appended). The side file is written under a
temporary name, fsynced, hard-linked into place (never replacing a file) and its directory
fsynced before the journal is truncated; :attr:`Journal.set_aside` names it and
:attr:`Journal.truncated_bytes` counts its bytes. A torn tail (the last step cut short by a
crash) is set aside too: it cannot be told apart from a corrupt length field, which looks exactly
like a record running past the end of the file, and one small file per crash costs nothing next
to deleting intact records. The side file starts at the first bad record; the records after it
are whole, in the same framing, for an operator to inspect or salvage.

Quarantine: a record the agent cannot use — the frame of a step that raised, a journal record
whose body fails to decode during replay — goes to ``<journal name>.quarantine`` with
:meth:`Journal.quarantine`, in the same framing with payload = msgpack ``[kind, body, reason,
index]`` (``index``: the caller's position of the record — its 0-based index among the replayed
records, or the step of a frame — or nil). Each record is fsynced on its own. An I/O error of
the quarantine file is logged and counted (:attr:`Journal.quarantine_failures`), never raised:
losing evidence must not stop the agent. :func:`read_quarantine` reads it back.

Durability: a record is on disk once :meth:`Journal.commit` returned (``fsync``); a commit that
fails cuts the file back to its last committed size, so no half-written step is left behind. The
file is created under a temporary name with its header, fsynced, linked into place (never
replacing an existing journal) and its directory fsynced, so a journal is never seen without its
header. One process at a time may hold a journal (``flock``).

Over 300 lines for a reason: the file format, recovery at every byte offset, the side files
(corrupt, cut, quarantine) and the lock are one durability contract; each part relies on how the
others write and fsync.
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
QUARANTINE_SUFFIX = ".quarantine"
MAX_REASON = 2000  # characters of a quarantine reason kept (an exception text can be huge)
_PREFIX = struct.Struct("<II")  # payload length, crc32 of payload
_MAX_PAYLOAD = 2**32 - 1
_MAX_INDEX = 2**63 - 1


class BadHeader(Exception):
    """The file's first record is not an intact header of this format (a flipped byte, a file
    that is not a journal): raised inside :func:`_read`, see :meth:`Journal.open`."""


class JournalError(Exception):
    """A journal that may not be used: not a journal, another identity, already in use, or its
    bad tail could not be set aside. ``key`` names the mismatching identity key, when that is
    the reason."""

    def __init__(self, message: str, key: str = "") -> None:
        super().__init__(message)
        self.key = key


@dataclass(frozen=True, slots=True)
class Record:
    """One journal entry: what it is (``kind``) and its bytes (usually a wire message)."""

    kind: str
    body: bytes


@dataclass(frozen=True, slots=True)
class QuarantinedRecord:
    """A record the agent could not use, as :meth:`Journal.quarantine` stored it."""

    kind: str
    body: bytes
    reason: str
    index: int | None


def quarantine_path(journal: Path) -> Path:
    """The quarantine file of the journal at ``journal``: ``<journal name>.quarantine``."""
    return journal.with_name(journal.name + QUARANTINE_SUFFIX)


def _frame(doc: list[Any]) -> bytes:
    payload = msgpack.packb(doc, use_bin_type=True)
    if len(payload) > _MAX_PAYLOAD:
        raise ValueError(f"record of {len(payload)} bytes is too large for a journal")
    return _PREFIX.pack(len(payload), zlib.crc32(payload)) + payload


def _unframe(data: bytes, offset: int) -> tuple[Any, int] | None:
    """The msgpack document of the intact record at ``offset`` and the offset after it, or None
    if torn or corrupt."""
    if len(data) - offset < _PREFIX.size:
        return None
    length, crc = _PREFIX.unpack_from(data, offset)
    start = offset + _PREFIX.size
    payload = data[start : start + length]
    if len(payload) != length or zlib.crc32(payload) != crc:
        return None
    try:
        return msgpack.unpackb(payload, raw=False), start + length
    except Exception:  # any undecodable payload (msgpack raises many types) ends the intact prefix
        return None


def _is_kind(kind: object) -> bool:
    return isinstance(kind, str) and KIND.fullmatch(kind) is not None


def _parse(data: bytes, offset: int) -> tuple[Record, int] | None:
    """The intact journal record at ``offset`` and the offset after it, or None."""
    parsed = _unframe(data, offset)
    if parsed is None or not (isinstance(parsed[0], list) and len(parsed[0]) == 2):
        return None
    (kind, body), end = parsed
    if not (_is_kind(kind) and isinstance(body, bytes)):
        return None
    return Record(kind, body), end


def _parse_quarantined(data: bytes, offset: int) -> tuple[QuarantinedRecord, int] | None:
    """The intact quarantine record at ``offset`` and the offset after it, or None."""
    parsed = _unframe(data, offset)
    if parsed is None or not (isinstance(parsed[0], list) and len(parsed[0]) == 4):
        return None
    (kind, body, reason, index), end = parsed
    ok = _is_kind(kind) and isinstance(body, bytes) and isinstance(reason, str)
    if not (ok and (index is None or _is_index(index))):
        return None
    return QuarantinedRecord(kind, body, reason, index), end


def _is_index(index: object) -> bool:
    return type(index) is int and 0 <= index <= _MAX_INDEX


def _check_record(kind: object, body: object) -> None:
    if not _is_kind(kind) or kind == HEADER:
        raise ValueError(f"invalid record kind {kind!r}")
    if not isinstance(body, bytes | bytearray | memoryview):
        raise TypeError(f"record body must be bytes, got {type(body).__name__}")


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


def _write_synced(path: Path, data: bytes) -> None:
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def _write_all(fd: int, data: bytes) -> None:
    written = 0
    while written < len(data):
        written += os.write(fd, data[written:])
    os.fsync(fd)


def _cut_back(fd: int, size: int, path: Path) -> bool:
    """Truncate ``fd`` to ``size`` after a failed write; False (logged) if even that failed."""
    try:
        os.ftruncate(fd, size)
    except OSError as exc:
        log.error("%s: could not cut a failed write back to %d bytes: %s", path, size, exc)
        return False
    return True


def _link_unique(src: Path, name: Path) -> Path:
    """Hard-link ``src`` as ``name``, else ``name.2``, ``name.3``…: the first that is free."""
    candidate, n = name, 1
    while True:
        try:
            os.link(src, candidate)  # unlike a rename, never replaces a file
            return candidate
        except FileExistsError:
            n += 1
            candidate = name.with_name(f"{name.name}.{n}")


def _create(path: Path, identity: dict[str, str | int], epoch: int) -> None:
    """Make ``path`` a journal holding only its header, unless a journal is already there."""
    missing = [p for p in (path.parent, *path.parent.parents) if not p.exists()]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    doc = {"format": FORMAT, "identity": identity, "epoch": epoch}
    header = msgpack.packb(doc, use_bin_type=True)
    _write_synced(tmp, _frame([HEADER, header]))
    try:
        os.link(tmp, path)  # unlike a rename, never replaces a journal created meanwhile
    except FileExistsError:
        pass
    finally:
        tmp.unlink()
    for directory in (path.parent, *(p.parent for p in missing)):
        _fsync_dir(directory)


def _set_aside(path: Path, dropped: bytes, offset: int, label: str = "corrupt") -> Path:
    """Copy ``dropped``, the journal's bytes from ``offset`` on, to a new side file
    ``<journal>.<label>-<offset>``, durably."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{label}.tmp")
    try:
        _write_synced(tmp, dropped)
        side = _link_unique(tmp, path.with_name(f"{path.name}.{label}-{offset}"))
    finally:
        tmp.unlink(missing_ok=True)
    _fsync_dir(path.parent)
    return side


class Journal:
    """An open journal; see the module docstring. Use :meth:`open`, not the constructor.

    ``truncated_bytes``: the bytes open cut off after the intact prefix, all of them copied to
    the side file ``set_aside`` (None when nothing was cut). ``quarantined`` and
    ``quarantine_failures`` count this session's :meth:`quarantine` calls that reached the disk
    and that did not; ``epoch`` the one in the header; ``moved_aside`` where a file with a bad
    header was moved (``Journal.open(..., set_aside_bad_header=...)``), None if none was."""

    def __init__(
        self,
        path: Path,
        fd: int,
        size: int,
        truncated_bytes: int,
        set_aside: Path | None,
        epoch: int = 0,
    ) -> None:
        self.path = path
        self.epoch = epoch
        self.truncated_bytes = truncated_bytes
        self.set_aside = set_aside
        self.quarantined = 0
        self.quarantine_failures = 0
        self.moved_aside: Path | None = None
        self._fd: int | None = fd
        self._size = size  # bytes on disk, all of them committed
        self._pending = bytearray()

    @classmethod
    def open(
        cls,
        path: Path,
        identity: Mapping[str, str | int],
        epoch: int = 0,
        set_aside_bad_header: str | None = None,
    ) -> tuple[Journal, list[Record]]:
        """Open (or create, with ``epoch`` in its header) the journal of ``identity`` at ``path``
        and read its records.

        Bytes after the intact prefix are copied to a side file before they are cut off (see the
        module docstring). Raises :class:`JournalError` if ``path`` is not a journal, belongs to
        another identity (``key`` names the first differing key), is open in another process, or
        its bad tail cannot be set aside (then the journal is left untouched).

        ``set_aside_bad_header`` (a label, e.g. a UTC time stamp): a file whose header is not
        intact — a flipped byte, or no journal at all — is instead moved to
        ``<journal>.bad-header-<label>`` (never replacing a file; ``moved_aside``) and a new,
        empty journal is made in its place, logged once. A journal of another identity is
        never moved: it is intact, and another run may need it.
        """
        ident = _check_identity(identity)
        path = Path(path)
        if not (isinstance(epoch, int) and 0 <= epoch <= _MAX_INDEX):
            raise ValueError(f"epoch {epoch!r}: expected an integer in 0..{_MAX_INDEX}")
        try:
            return cls._open(path, ident, epoch)
        except BadHeader as exc:
            if set_aside_bad_header is None:
                raise JournalError(str(exc)) from None
            moved = _move_aside(path, f"bad-header-{set_aside_bad_header}", exc)
        journal, records = cls._open(path, ident, epoch)
        journal.moved_aside = moved
        return journal, records

    @classmethod
    def _open(
        cls, path: Path, ident: dict[str, str | int], epoch: int
    ) -> tuple[Journal, list[Record]]:
        if not path.exists():
            _create(path, ident, epoch)
        fd = os.open(path, os.O_RDWR | os.O_APPEND)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise JournalError(f"{path} is in use by another process") from None
        try:
            records, end, data, stored = _read(path, ident)
            side = _recover(path, fd, data, end) if end < len(data) else None
        except BaseException:
            os.close(fd)
            raise
        return cls(path, fd, end, len(data) - end, side, stored), records

    def append(self, kind: str, body: bytes | bytearray | memoryview) -> None:
        """Queue a record; it reaches the disk with the next :meth:`commit`."""
        _check_record(kind, body)
        self._open_fd()
        self._pending += _frame([kind, bytes(body)])

    def commit(self) -> None:
        """Write the queued records and fsync: once this returns they survive a crash.

        If the write fails, the file is cut back to its committed size and the error raised; the
        records stay queued, so the next commit retries them (the belief in memory already holds
        that step: dropping them would let a replay skip it). If even the cut fails, the journal
        closes: no record may follow a half-written one (the next open sets it aside)."""
        fd = self._open_fd()
        if not self._pending:
            return
        data = bytes(self._pending)
        try:
            _write_all(fd, data)
        except OSError:
            if not _cut_back(fd, self._size, self.path):
                self._release()
            raise
        self._size += len(data)
        self._pending.clear()

    def records(self) -> list[Record]:
        """The committed records, read back from disk (what a replay would see now)."""
        self._open_fd()
        return [record for record, _ in self._committed()]

    def cut(self, index: int) -> Path | None:
        """Cut the journal before its committed record ``index``: the records from there on are
        copied to a side file (returned; None if there was nothing to cut) before the file is
        truncated. Queued records are dropped (they followed the cut ones)."""
        fd = self._open_fd()
        if not (isinstance(index, int) and index >= 0):
            raise ValueError(f"cut index must be a non-negative integer, got {index!r}")
        offsets = [start for _, start in self._committed()]
        self._pending.clear()
        if index >= len(offsets):
            return None
        start = offsets[index]
        data = self.path.read_bytes()[: self._size]
        side = _set_aside(self.path, data[start:], start, "cut")
        log.warning(
            "journal %s: cut before record %d (offset %d); %d bytes set aside in %s",
            self.path,
            index,
            start,
            len(data) - start,
            side,
        )
        os.ftruncate(fd, start)
        os.fsync(fd)
        self._size = start
        return side

    def _committed(self) -> list[tuple[Record, int]]:
        """The committed records after the header, each with its offset in the file."""
        data = self.path.read_bytes()[: self._size]
        first = _parse(data, 0)
        out: list[tuple[Record, int]] = []
        end = first[1] if first is not None else len(data)
        while (parsed := _parse(data, end)) is not None:
            out.append((parsed[0], end))
            end = parsed[1]
        return out

    @property
    def quarantine_path(self) -> Path:
        return quarantine_path(self.path)

    def quarantine(
        self,
        kind: str,
        body: bytes | bytearray | memoryview,
        reason: str,
        index: int | None = None,
    ) -> bool:
        """Append a record the agent could not use to :attr:`quarantine_path` and fsync it;
        ``reason`` is kept up to :data:`MAX_REASON` characters, ``index`` as in the module
        docstring. Returns whether it reached the disk: an I/O error is logged and counted, never
        raised. Bad arguments raise like :meth:`append`; so does a closed journal."""
        _check_record(kind, body)
        if not isinstance(reason, str):
            raise TypeError(f"quarantine reason must be a string, got {type(reason).__name__}")
        if not (index is None or _is_index(index)):
            raise ValueError(f"quarantine index must be None or in 0..2^63-1, got {index!r}")
        self._open_fd()
        data = _frame([kind, bytes(body), reason[:MAX_REASON], index])
        path = self.quarantine_path
        try:
            _append_synced(path, data)
        except OSError as exc:
            self.quarantine_failures += 1
            log.error("%s: could not quarantine a %s record (index %s): %s", path, kind, index, exc)
            return False
        self.quarantined += 1
        log.info("%s: quarantined a %s record (index %s): %s", path, kind, index, reason)
        return True

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


def _recover(path: Path, fd: int, data: bytes, end: int) -> Path:
    """Copy ``data[end:]`` to a new side file, then cut the journal ``fd`` back to ``end``."""
    try:
        side = _set_aside(path, data[end:], end)
    except OSError as exc:
        raise JournalError(
            f"{path}: {len(data) - end} bytes from offset {end} are torn or corrupt and could "
            f"not be copied aside ({exc}); the journal is left untouched"
        ) from exc
    log.warning(
        "journal %s: %d bytes from offset %d are torn or corrupt: copied to %s and cut off",
        path,
        len(data) - end,
        end,
        side,
    )
    os.ftruncate(fd, end)
    os.fsync(fd)
    return side


def _move_aside(path: Path, label: str, why: BadHeader) -> Path:
    """Move the file at ``path`` to ``<path>.<label>`` (``.2``, ``.3``… if taken), durably, and
    log it: the caller makes a new journal in its place."""
    fd = os.open(path, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise JournalError(f"{path} is in use by another process") from None
        try:
            side = _link_unique(path, path.with_name(f"{path.name}.{label}"))
            path.unlink()
            _fsync_dir(path.parent)
        except OSError as exc:
            raise JournalError(f"{why}; it could not be moved aside ({exc})") from exc
    finally:
        os.close(fd)
    log.warning("journal %s: %s; moved to %s, starting an empty journal", path, why, side)
    return side


def _append_synced(path: Path, data: bytes) -> None:
    """Append ``data`` to ``path`` (created if missing) and fsync; a failed write is cut back."""
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        size = os.fstat(fd).st_size
        try:
            _write_all(fd, data)
        except OSError:
            _cut_back(fd, size, path)
            raise
    finally:
        os.close(fd)
    if size == 0:
        _fsync_dir(path.parent)


def read_quarantine(path: Path) -> list[QuarantinedRecord]:
    """The records of the quarantine file ``path``, oldest first. Like a journal, only the intact
    prefix is read (a torn last record, from a crash while quarantining, is skipped and logged);
    the file is never changed."""
    data = Path(path).read_bytes()
    records, end = [], 0
    while (parsed := _parse_quarantined(data, end)) is not None:
        records.append(parsed[0])
        end = parsed[1]
    if end < len(data):
        log.warning("%s: %d bytes from offset %d are torn or corrupt", path, len(data) - end, end)
    return records


def _read(path: Path, identity: dict[str, str | int]) -> tuple[list[Record], int, bytes, int]:
    """Records after the header, the offset after the last intact one, the file's bytes and the
    header's epoch."""
    data = path.read_bytes()
    first = _parse(data, 0)
    header = _header(first[0]) if first else None
    if first is None or header is None:
        raise BadHeader(f"{path} is not a semfleet journal (no valid header)")
    if header.get("format") != FORMAT or not isinstance(header.get("identity"), dict):
        raise BadHeader(f"{path}: not a journal of format {FORMAT}")
    epoch = header.get("epoch", 0)
    if type(epoch) is not int or not 0 <= epoch <= _MAX_INDEX:
        raise BadHeader(f"{path}: header epoch {epoch!r} is not an integer in 0..{_MAX_INDEX}")
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
    return records, end, data, epoch


def _header(record: Record) -> dict[str, Any] | None:
    if record.kind != HEADER:
        return None
    try:
        header = msgpack.unpackb(record.body, raw=False)
    except Exception:  # an undecodable header means "not a journal", whatever msgpack raised
        return None
    return header if isinstance(header, dict) else None


class MemoryLog:
    """The committed records of an agent without a journal (kept in memory, for roll-backs)."""

    def __init__(self) -> None:
        self._records: list[Record] = []
        self._pending: list[Record] = []

    def append(self, kind: str, body: bytes) -> None:
        self._pending.append(Record(kind, body))

    def commit(self) -> None:
        self._records += self._pending
        self._pending = []

    def records(self) -> list[Record]:
        return list(self._records)

    def cut(self, index: int) -> None:
        self._records = self._records[:index]

    def quarantine(self, kind: str, body: bytes, reason: str, index: int | None = None) -> None:
        log.warning("quarantined %s record (no journal): %s", kind, reason)

    def close(self) -> None:
        pass
