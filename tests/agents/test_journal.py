"""The durable journal: records round trip, reopening appends, another identity is refused, a torn
or corrupt tail is copied aside and cut back to the last intact record, a failed commit leaves the
file as it was, the quarantine file round trips and never raises for its own I/O errors, and
committed records survive SIGKILL of a real process. (SIGKILL proves the process-crash case; what
the fsync adds, surviving a power cut, cannot be shown without pulling the plug. A full disk is
shown with a monkeypatched ``os.write``.)"""

from __future__ import annotations

import errno
import itertools
import os
import signal
import subprocess
import sys
import textwrap
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import pytest

from agents.journal import (
    MAX_REASON,
    Journal,
    JournalError,
    QuarantinedRecord,
    Record,
    _parse,
    quarantine_path,
    read_quarantine,
)

ROOT = Path(__file__).resolve().parents[2]
IDENTITY: dict[str, str | int] = {"robot": "r1", "seed": 7, "scenario": "a3f9"}
RECORDS = [
    Record("frame", b"\x01\x02"),
    Record("stack", b""),
    Record("stack", bytes(range(256)) * 3),
    Record("frame", b"\xff" * 70_000),  # longer than 2^16: a u32 length
    Record("x", b"last"),
]


def _write(path: Path, records: list[Record], identity: dict[str, str | int] = IDENTITY) -> None:
    journal, _ = Journal.open(path, identity)
    with journal:
        for r in records:
            journal.append(r.kind, r.body)
        journal.commit()


def _offsets(path: Path) -> list[int]:
    """Start offset of every record (the header first) and the end of the file."""
    data = path.read_bytes()
    out = [0]
    while out[-1] < len(data):
        out.append(out[-1] + 8 + int.from_bytes(data[out[-1] : out[-1] + 4], "little"))
    return out


def _reopen(path: Path) -> tuple[Journal, list[Record]]:
    return Journal.open(path, IDENTITY)


def _documents(data: bytes) -> list[Any]:
    """The msgpack payloads of ``data``, a sequence of whole records, read as the docs say."""
    docs, offset = [], 0
    while offset < len(data):
        length = int.from_bytes(data[offset : offset + 4], "little")
        crc = int.from_bytes(data[offset + 4 : offset + 8], "little")
        payload = data[offset + 8 : offset + 8 + length]
        assert len(payload) == length and zlib.crc32(payload) == crc
        docs.append(msgpack.unpackb(payload, raw=False))
        offset += 8 + length
    return docs


def _same_file(fd: int, path: Path) -> bool:
    return os.fstat(fd).st_ino == path.stat().st_ino


def _torn_write(path: Path, keep: int) -> Callable[[int, bytes], int]:
    """An ``os.write`` under which writes to ``path`` put ``keep`` bytes on disk, then fail as a
    full disk does; writes to other files go through."""
    real = os.write

    def write(fd: int, data: bytes) -> int:
        if not _same_file(fd, path):
            return real(fd, data)
        assert real(fd, bytes(data[:keep])) == keep
        raise OSError(errno.ENOSPC, "No space left on device")

    return write


def _failing_fsync(path: Path) -> Callable[[int], None]:
    real = os.fsync

    def fsync(fd: int) -> None:
        if _same_file(fd, path):
            raise OSError(errno.EIO, "Input/output error")
        real(fd)

    return fsync


def test_journal_records_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "deep" / "dir" / "r1.journal"
    journal, records = Journal.open(path, IDENTITY)
    assert records == [] and journal.truncated_bytes == 0
    for r in RECORDS:
        journal.append(r.kind, r.body)
    journal.commit()
    journal.close()
    journal, records = _reopen(path)
    journal.close()
    assert records == RECORDS and journal.truncated_bytes == 0
    assert sorted(p.name for p in path.parent.iterdir()) == ["r1.journal"]  # no temporary left


def test_journal_file_layout_matches_docs(tmp_path: Path) -> None:
    path = tmp_path / "r1.journal"
    _write(path, [Record("frame", b"abc")])
    data = path.read_bytes()
    starts = _offsets(path)
    assert len(starts) == 3 and starts[-1] == len(data)
    payloads = []
    for start, end in itertools.pairwise(starts):
        length = int.from_bytes(data[start : start + 4], "little")
        crc = int.from_bytes(data[start + 4 : start + 8], "little")
        payload = data[start + 8 : end]
        assert len(payload) == length and zlib.crc32(payload) == crc
        payloads.append(msgpack.unpackb(payload, raw=False))
    kind, header = payloads[0]
    assert kind == "header"
    assert msgpack.unpackb(header, raw=False) == {"format": 1, "identity": IDENTITY, "epoch": 0}
    assert payloads[1] == ["frame", b"abc"]


def test_journal_keeps_the_epoch_it_was_made_with(tmp_path: Path) -> None:
    """The epoch given when a journal is made is the one every reopen returns (the robot's slots
    keep their versions across restarts); a journal made before epochs has epoch 0."""
    path = tmp_path / "r1.journal"
    journal, _ = Journal.open(path, IDENTITY, 1_764_000_000_000)
    journal.close()
    journal, _ = Journal.open(path, IDENTITY, 1_999_000_000_000)
    journal.close()
    assert journal.epoch == 1_764_000_000_000
    old = tmp_path / "old.journal"
    header = msgpack.packb({"format": 1, "identity": IDENTITY}, use_bin_type=True)
    payload = msgpack.packb(["header", header], use_bin_type=True)
    old.write_bytes(len(payload).to_bytes(4, "little") + zlib.crc32(payload).to_bytes(4, "little"))
    with old.open("ab") as f:
        f.write(payload)
    journal, records = Journal.open(old, IDENTITY, 5)
    journal.close()
    assert journal.epoch == 0 and records == []
    with pytest.raises(ValueError, match="epoch"):
        Journal.open(tmp_path / "bad.journal", IDENTITY, -1)
    for epoch in (-1, 2**63, 1.5):  # a header whose epoch no journal was made with
        bad = tmp_path / f"epoch{epoch}.journal"
        header = msgpack.packb({"format": 1, "identity": IDENTITY, "epoch": epoch})
        payload = msgpack.packb(["header", header], use_bin_type=True)
        prefix = len(payload).to_bytes(4, "little") + zlib.crc32(payload).to_bytes(4, "little")
        bad.write_bytes(prefix + payload)
        with pytest.raises(JournalError, match="epoch"):
            Journal.open(bad, IDENTITY, 5)


def test_journal_reopen_appends_after_existing_records(tmp_path: Path) -> None:
    path = tmp_path / "r1.journal"
    _write(path, RECORDS[:2])
    _write(path, RECORDS[2:])
    journal, records = _reopen(path)
    journal.close()
    assert records == RECORDS


def test_journal_commit_per_step_and_bytes_like_bodies(tmp_path: Path) -> None:
    path = tmp_path / "r1.journal"
    with _reopen(path)[0] as journal:
        for k in range(1, 4):
            journal.append("frame", bytearray([k]))
            journal.append("stack", memoryview(bytes([k, k])))
            journal.commit()
        journal.commit()  # nothing queued: a no-op
    _, records = _reopen(path)
    assert records == [
        r
        for k in range(1, 4)
        for r in (Record("frame", bytes([k])), Record("stack", bytes([k] * 2)))
    ]


def test_journal_uncommitted_records_are_lost_only_when_the_step_failed(tmp_path: Path) -> None:
    path = tmp_path / "r1.journal"
    journal, _ = _reopen(path)
    journal.append("frame", b"1")
    journal.close()  # a clean close commits
    with pytest.raises(RuntimeError), _reopen(path)[0] as journal:
        journal.append("frame", b"2")
        raise RuntimeError("the step failed half-way")
    journal, records = _reopen(path)
    journal.close()
    assert records == [Record("frame", b"1")]


@pytest.mark.parametrize("key", ["robot", "seed", "scenario"])
def test_journal_identity_mismatch_names_the_key(tmp_path: Path, key: str) -> None:
    path = tmp_path / "r1.journal"
    _write(path, RECORDS)
    before = path.read_bytes()
    other = {**IDENTITY, key: "other"}
    with pytest.raises(JournalError, match=key) as caught:
        Journal.open(path, other)
    assert caught.value.key == key
    assert path.read_bytes() == before  # never touched


@pytest.mark.parametrize(
    ("identity", "key"),
    [
        ({"robot": "r1", "seed": 7}, "scenario"),  # a key missing
        ({**IDENTITY, "extra": 1}, "extra"),  # a key added
        ({**IDENTITY, "seed": "7"}, "seed"),  # same text, other type
    ],
)
def test_journal_identity_must_match_exactly(
    tmp_path: Path, identity: dict[str, str | int], key: str
) -> None:
    path = tmp_path / "r1.journal"
    _write(path, [])
    with pytest.raises(JournalError) as caught:
        Journal.open(path, identity)
    assert caught.value.key == key


@pytest.mark.parametrize("content", [b"", b"not a journal at all", bytes(8), bytes(100)])
def test_journal_refuses_a_file_that_is_not_a_journal(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "r1.journal"
    path.write_bytes(content)
    with pytest.raises(JournalError, match="not a semfleet journal"):
        Journal.open(path, IDENTITY)
    assert path.read_bytes() == content  # a foreign file is never truncated


@pytest.mark.parametrize("flip", [0, 4, 9, 20])
def test_a_journal_with_a_damaged_header_is_moved_aside_and_started_anew(
    tmp_path: Path, flip: int, caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 43, finding 7: a flipped byte in the header (its length, crc or payload) left an
    agent that would not start until an operator moved the journal aside."""
    path = tmp_path / "r1.journal"
    _write(path, [Record("frame", b"k1"), Record("stack", b"s1")])
    data = bytearray(path.read_bytes())
    data[flip] ^= 0x10
    path.write_bytes(bytes(data))
    with pytest.raises(JournalError, match="not a semfleet journal"):
        Journal.open(path, IDENTITY)  # without the option: refused, and left as it is
    assert path.read_bytes() == bytes(data)
    with caplog.at_level("WARNING", logger="agents.journal"):
        journal, records = Journal.open(path, IDENTITY, 42, set_aside_bad_header="20261207T010000Z")
    with journal:
        assert records == [] and journal.epoch == 42
        assert journal.moved_aside == tmp_path / "r1.journal.bad-header-20261207T010000Z"
        assert journal.moved_aside.read_bytes() == bytes(data)  # every byte kept
    assert [r.getMessage().split(";")[1] for r in caplog.records] == [
        f" moved to {journal.moved_aside}, starting an empty journal"
    ]
    # The new journal works, and a second bad header at the same stamp takes the next name.
    path.write_bytes(b"junk")
    journal, _ = Journal.open(path, IDENTITY, 43, set_aside_bad_header="20261207T010000Z")
    with journal:
        assert journal.moved_aside == tmp_path / "r1.journal.bad-header-20261207T010000Z.2"
    reopened, records = Journal.open(path, IDENTITY, set_aside_bad_header="x")
    with reopened:
        assert records == [] and reopened.moved_aside is None and reopened.epoch == 43


def test_a_journal_of_another_run_is_never_moved_aside(tmp_path: Path) -> None:
    path = tmp_path / "r1.journal"
    _write(path, [Record("frame", b"k1")])
    with pytest.raises(JournalError, match="belongs to another run"):
        Journal.open(path, {**IDENTITY, "seed": 8}, set_aside_bad_header="x")
    assert list(tmp_path.iterdir()) == [path]


def test_journal_refuses_another_format_version(tmp_path: Path) -> None:
    path = tmp_path / "r1.journal"
    header = msgpack.packb({"format": 2, "identity": IDENTITY})
    payload = msgpack.packb(["header", header])
    path.write_bytes(
        len(payload).to_bytes(4, "little") + zlib.crc32(payload).to_bytes(4, "little") + payload
    )
    with pytest.raises(JournalError, match="format"):
        Journal.open(path, IDENTITY)


def test_journal_is_held_by_one_opener_at_a_time(tmp_path: Path) -> None:
    path = tmp_path / "r1.journal"
    journal, _ = _reopen(path)
    with pytest.raises(JournalError, match="in use"):
        _reopen(path)
    journal.close()
    _reopen(path)[0].close()


@pytest.mark.parametrize(
    ("kind", "body", "error"),
    [
        ("header", b"", ValueError),  # reserved for the first record
        ("", b"", ValueError),
        ("Frame", b"", ValueError),
        ("x" * 17, b"", ValueError),
        ("frame", "text", TypeError),
        (b"frame", b"", ValueError),
    ],
)
def test_journal_append_rejects_bad_records(
    tmp_path: Path, kind: str, body: bytes, error: type[Exception]
) -> None:
    with _reopen(tmp_path / "r1.journal")[0] as journal, pytest.raises(error):
        journal.append(kind, body)


def test_journal_closed_journal_refuses_appends(tmp_path: Path) -> None:
    journal, _ = _reopen(tmp_path / "r1.journal")
    journal.close()
    journal.close()
    with pytest.raises(JournalError, match="closed"):
        journal.append("frame", b"")


def test_journal_torn_tail_is_cut_back_at_every_offset(tmp_path: Path) -> None:
    """A crash while writing the last record: whatever prefix of it reached the disk, reopening
    keeps the records before it, reports the bytes dropped, and appends after them."""
    path = tmp_path / "r1.journal"
    records = [Record("frame", b"a" * 20), Record("stack", b"b" * 40), Record("frame", b"c" * 30)]
    _write(path, records)
    full = path.read_bytes()
    starts = _offsets(path)
    last = starts[-2]
    for cut in range(last, len(full)):
        path.write_bytes(full[:cut])
        journal, got = _reopen(path)
        assert got == records[:-1], cut
        assert journal.truncated_bytes == cut - last, cut
        assert path.stat().st_size == last, cut
        if cut == last:
            assert journal.set_aside is None
        else:  # every torn tail is kept, each in a file of its own: the same offset each time
            suffix = "" if cut == last + 1 else f".{cut - last}"
            assert journal.set_aside == path.with_name(f"r1.journal.corrupt-{last}{suffix}"), cut
            assert journal.set_aside.read_bytes() == full[last:cut], cut
        journal.append("frame", b"again")
        journal.close()
        journal, got = _reopen(path)
        journal.close()
        assert got == [*records[:-1], Record("frame", b"again")], cut


@pytest.mark.parametrize("where", ["length", "crc", "payload", "kind", "body"])
def test_journal_corrupt_record_in_the_middle_is_copied_aside_with_all_later_ones(
    tmp_path: Path, where: str
) -> None:
    """Replay order matters: a record after a corrupt one would rebuild a belief the agent never
    had, so the journal keeps only the intact prefix; but the bytes it cuts off, the intact later
    records among them, are first copied to a side file."""
    path = tmp_path / "r1.journal"
    _write(path, RECORDS)
    data = bytearray(path.read_bytes())
    starts = _offsets(path)
    second = starts[2]  # RECORDS[1]
    offset = {"length": second, "crc": second + 4, "payload": starts[3] - 1}.get(where)
    if offset is None:  # a payload that passes its crc but is not [kind, body]
        payload = msgpack.packb(["Not-A-Kind", b""] if where == "kind" else ["frame", 7])
        record = len(payload).to_bytes(4, "little") + zlib.crc32(payload).to_bytes(4, "little")
        data[second : starts[3]] = record + payload
    else:
        data[offset] ^= 0x40
    path.write_bytes(bytes(data))
    journal, records = _reopen(path)
    assert records == RECORDS[:1]
    assert journal.truncated_bytes == len(data) - second
    journal.append("frame", b"after the recovery")
    journal.close()
    assert path.stat().st_size > second
    side = path.with_name(f"r1.journal.corrupt-{second}")
    assert journal.set_aside == side
    assert side.read_bytes() == bytes(data[second:])
    later = bytes(data[len(data) - (starts[-1] - starts[3]) :])  # RECORDS[2:], whole
    assert side.read_bytes().endswith(later)
    assert [Record(*doc) for doc in _documents(later)] == RECORDS[2:]  # recoverable
    journal, records = _reopen(path)
    journal.close()
    assert records == [RECORDS[0], Record("frame", b"after the recovery")]
    assert journal.set_aside is None and side.read_bytes() == bytes(data[second:])


def test_journal_set_aside_never_replaces_an_earlier_side_file(tmp_path: Path) -> None:
    path = tmp_path / "r1.journal"
    _write(path, RECORDS[:1])
    end = path.stat().st_size
    for garbage in (b"\xff" * 9, b"\x00\x01" * 20):
        with path.open("ab") as f:
            f.write(garbage)
        journal, records = _reopen(path)
        journal.close()
        assert records == RECORDS[:1] and journal.set_aside is not None
        assert journal.set_aside.read_bytes() == garbage
    first = path.with_name(f"r1.journal.corrupt-{end}")
    assert first.read_bytes() == b"\xff" * 9
    assert first.with_name(first.name + ".2").read_bytes() == b"\x00\x01" * 20


def test_journal_that_cannot_set_its_tail_aside_is_left_untouched(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "r1.journal"
    _write(path, RECORDS[:2])
    with path.open("ab") as f:
        f.write(b"\xff" * 20)
    before = path.read_bytes()

    def link(src: Path, dst: Path) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr("agents.journal.os.link", link)
        with pytest.raises(JournalError, match=r"20 bytes from offset \d+ .* left untouched"):
            _reopen(path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r1.journal"]  # no temporary left
    journal, records = _reopen(path)  # not held: the failed open released its lock
    journal.close()
    assert records == RECORDS[:2] and journal.set_aside is not None


# --------------------------------------------------------------------------- failed commits


@pytest.mark.parametrize("failure", ["write", "fsync"])
def test_journal_failed_commit_leaves_the_file_unchanged_and_the_journal_usable(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, failure: str
) -> None:
    """A full disk mid-commit (part of the step written) or a failed fsync (all of it written):
    commit raises, the file is cut back to its committed size, and the step stays queued, so the
    next commit writes it with the records queued since."""
    path = tmp_path / "r1.journal"
    journal, _ = _reopen(path)
    journal.append("frame", b"1")
    journal.commit()
    size = path.stat().st_size
    journal.append("frame", b"2" * 1000)
    with monkeypatch.context() as m:
        if failure == "write":
            m.setattr("agents.journal.os.write", _torn_write(path, 100))
        else:
            m.setattr("agents.journal.os.fsync", _failing_fsync(path))
        with pytest.raises(OSError):
            journal.commit()
    assert path.stat().st_size == size
    journal.append("stack", b"3")
    journal.commit()
    journal.close()
    journal, records = _reopen(path)
    journal.close()
    assert records == [Record("frame", b"1"), Record("frame", b"2" * 1000), Record("stack", b"3")]
    assert journal.truncated_bytes == 0 and journal.set_aside is None


def test_journal_failed_rollback_closes_the_journal_and_open_sets_the_torn_step_aside(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """If even cutting the half-written step back fails, nothing may follow it: the journal
    closes, and the next open copies the torn bytes aside."""
    path = tmp_path / "r1.journal"
    journal, _ = _reopen(path)
    journal.append("frame", b"1")
    journal.commit()
    size = path.stat().st_size
    journal.append("frame", b"2" * 1000)

    def ftruncate(fd: int, length: int) -> None:
        raise OSError(errno.EIO, "Input/output error")

    with monkeypatch.context() as m:
        m.setattr("agents.journal.os.write", _torn_write(path, 100))
        m.setattr("agents.journal.os.ftruncate", ftruncate)
        with pytest.raises(OSError, match="No space left"):
            journal.commit()
    torn = path.read_bytes()[size:]
    assert len(torn) == 100
    with pytest.raises(JournalError, match="closed"):
        journal.append("frame", b"3")
    journal, records = _reopen(path)
    journal.close()
    assert records == [Record("frame", b"1")]
    assert journal.set_aside is not None and journal.set_aside.read_bytes() == torn


# --------------------------------------------------------------------------- quarantine

QUARANTINED = [
    QuarantinedRecord("frame", b"\x00\x01", "step 3 raised FloatingPointError: overflow", 3),
    QuarantinedRecord("stack", bytes(range(256)) * 300, "replay: MalformedMessage: objects", 17),
    QuarantinedRecord("frame", b"", "no position known", None),
]


def test_journal_quarantine_round_trips_and_never_enters_the_replay(tmp_path: Path) -> None:
    path = tmp_path / "r1.journal"
    journal, _ = _reopen(path)
    for q in QUARANTINED[:2]:
        assert journal.quarantine(q.kind, q.body, q.reason, q.index)
    journal.close()
    journal, records = _reopen(path)  # a restarted agent adds to the same file
    q = QUARANTINED[2]
    assert journal.quarantine(q.kind, memoryview(q.body), q.reason, q.index)
    assert journal.quarantine("frame", bytearray(b"x"), "y" * (MAX_REASON + 5), 2**63 - 1)
    journal.close()
    assert records == []
    assert (journal.quarantined, journal.quarantine_failures) == (2, 0)
    assert journal.quarantine_path == quarantine_path(path) == tmp_path / "r1.journal.quarantine"
    expected = [*QUARANTINED, QuarantinedRecord("frame", b"x", "y" * MAX_REASON, 2**63 - 1)]
    assert read_quarantine(journal.quarantine_path) == expected
    docs = _documents(journal.quarantine_path.read_bytes())  # the journal's framing
    assert docs[0] == ["frame", b"\x00\x01", "step 3 raised FloatingPointError: overflow", 3]
    assert _reopen(path)[1] == []


def test_read_quarantine_skips_a_torn_last_record(tmp_path: Path) -> None:
    path = tmp_path / "r1.journal"
    with _reopen(path)[0] as journal:
        for q in QUARANTINED:
            journal.quarantine(q.kind, q.body, q.reason, q.index)
    qpath = quarantine_path(path)
    full = qpath.read_bytes()
    qpath.write_bytes(full[:-1])
    assert read_quarantine(qpath) == QUARANTINED[:2]
    assert qpath.read_bytes() == full[:-1]  # read only
    # A record intact by its crc but with an index no quarantine writes ends the prefix too.
    for index in (-1, "3"):
        payload = msgpack.packb(["frame", b"x", "reason", index], use_bin_type=True)
        prefix = len(payload).to_bytes(4, "little") + zlib.crc32(payload).to_bytes(4, "little")
        qpath.write_bytes(full + prefix + payload)
        assert read_quarantine(qpath) == QUARANTINED


@pytest.mark.parametrize("failure", ["write", "fsync", "open"])
def test_journal_quarantine_io_error_is_counted_not_raised(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, failure: str
) -> None:
    path = tmp_path / "r1.journal"
    journal, _ = _reopen(path)
    qpath = journal.quarantine_path
    q = QUARANTINED[1]
    if failure == "open":
        qpath.mkdir()  # not a file: opening it fails
    else:
        assert journal.quarantine(q.kind, q.body, q.reason, q.index)
    size = qpath.stat().st_size
    with monkeypatch.context() as m:
        if failure == "write":
            m.setattr("agents.journal.os.write", _torn_write(qpath, 10))
        elif failure == "fsync":
            m.setattr("agents.journal.os.fsync", _failing_fsync(qpath))
        assert not journal.quarantine("frame", b"lost", "disk full", 4)
    assert journal.quarantine_failures == 1
    journal.append("frame", b"the agent goes on")
    journal.commit()
    journal.close()
    if failure == "open":
        return
    assert qpath.stat().st_size == size  # no half-written record left behind
    assert read_quarantine(qpath) == [q]
    assert journal.quarantined == 1


@pytest.mark.parametrize(
    ("kind", "body", "reason", "index", "error"),
    [
        ("Frame", b"", "r", None, ValueError),
        ("header", b"", "r", None, ValueError),
        ("frame", "text", "r", None, TypeError),
        ("frame", b"", b"reason", None, TypeError),
        ("frame", b"", "r", -1, ValueError),
        ("frame", b"", "r", 2**63, ValueError),
        ("frame", b"", "r", True, ValueError),
        ("frame", b"", "r", 1.0, ValueError),
    ],
)
def test_journal_quarantine_rejects_bad_arguments(
    tmp_path: Path, kind: str, body: bytes, reason: str, index: int, error: type[Exception]
) -> None:
    with _reopen(tmp_path / "r1.journal")[0] as journal, pytest.raises(error):
        journal.quarantine(kind, body, reason, index)
    assert not quarantine_path(tmp_path / "r1.journal").exists()


def test_journal_closed_journal_refuses_to_quarantine(tmp_path: Path) -> None:
    journal, _ = _reopen(tmp_path / "r1.journal")
    journal.close()
    with pytest.raises(JournalError, match="closed"):
        journal.quarantine("frame", b"", "r", None)


# --------------------------------------------------------------------------- SIGKILL

WRITER = textwrap.dedent(
    """
    import sys
    from pathlib import Path

    from agents.journal import Journal

    path, steps, hang = Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3] == "hang"
    journal, records = Journal.open(path, {"robot": "r1", "seed": 7})
    for k in range(len(records) // 2 + 1, steps + 1):
        journal.append("frame", b"f%d" % k)
        journal.append("stack", bytes([k % 256]) * (k * 997 % 5000))
        journal.commit()
        print("committed", k, flush=True)
    if hang:
        journal.append("frame", b"never committed")
        sys.stdin.read()  # wait to be killed with a record queued but not committed
    """
)


def _expected(k: int) -> list[Record]:
    return [Record("frame", b"f%d" % k), Record("stack", bytes([k % 256]) * (k * 997 % 5000))]


def _writer(path: Path, steps: int, hang: bool) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-c", WRITER, str(path), str(steps), "hang" if hang else "run"],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )


def _kill_after(proc: subprocess.Popen[str], k: int) -> None:
    """SIGKILL ``proc`` right after it printed "committed k"."""
    assert proc.stdout is not None
    try:
        for line in proc.stdout:
            if line.strip() == f"committed {k}":
                os.kill(proc.pid, signal.SIGKILL)
                break
        else:
            pytest.fail(f"the writer ended before committing step {k}")
    finally:
        proc.kill()  # a no-op if already dead; never leave a process behind
        proc.wait(timeout=30)
        proc.stdout.close()
        if proc.stdin is not None:
            proc.stdin.close()


def test_journal_committed_records_survive_sigkill(tmp_path: Path) -> None:
    """Killed while idle with a record queued: exactly the committed steps are there."""
    path = tmp_path / "r1.journal"
    _kill_after(_writer(path, 5, hang=True), 5)
    journal, records = Journal.open(path, {"robot": "r1", "seed": 7})
    journal.close()
    assert records == [r for k in range(1, 6) for r in _expected(k)]
    assert journal.truncated_bytes == 0


def test_journal_sigkill_mid_run_keeps_every_committed_step_and_resumes(tmp_path: Path) -> None:
    """Killed while still writing: every step acknowledged before the kill is there (later ones
    may be too, whole), and a restarted writer carries on where the journal ends."""
    path = tmp_path / "r1.journal"
    _kill_after(_writer(path, 400, hang=False), 40)
    journal, records = Journal.open(path, {"robot": "r1", "seed": 7})
    journal.close()
    steps = len(records) // 2
    assert steps >= 40 and len(records) == 2 * steps
    assert records == [r for k in range(1, steps + 1) for r in _expected(k)]
    _kill_after(_writer(path, 400, hang=True), 400)
    journal, records = Journal.open(path, {"robot": "r1", "seed": 7})
    journal.close()
    assert records == [r for k in range(1, 401) for r in _expected(k)]


def test_records_reads_back_exactly_the_committed_records(tmp_path: Path) -> None:
    journal, _ = Journal.open(tmp_path / "j.log", {"robot": "r1"})
    with journal:
        journal.append("frame", b"one")
        journal.append("stack", b"two")
        journal.commit()
        journal.append("frame", b"queued, not committed")
        assert journal.records() == [Record("frame", b"one"), Record("stack", b"two")]


def test_cut_sets_the_cut_records_aside_and_keeps_the_rest(tmp_path: Path) -> None:
    path = tmp_path / "j.log"
    journal, _ = Journal.open(path, {"robot": "r1"})
    bodies = [f"record {i}".encode() for i in range(5)]
    with journal:
        for b in bodies:
            journal.append("frame", b)
        journal.commit()
        size = path.stat().st_size
        side = journal.cut(2)
        assert side is not None and side.name.startswith("j.log.cut-")
        assert journal.records() == [Record("frame", b) for b in bodies[:2]]
        assert journal.cut(7) is None  # nothing to cut
        journal.append("frame", b"after the cut")
        journal.commit()
    assert path.stat().st_size < size
    _, records = Journal.open(path, {"robot": "r1"})
    assert [r.body for r in records] == [*bodies[:2], b"after the cut"]
    # The side file holds exactly the cut records, in journal framing.
    data, offset, cut = side.read_bytes(), 0, []
    while (parsed := _parse(data, offset)) is not None:
        cut.append(parsed[0].body)
        offset = parsed[1]
    assert cut == bodies[2:] and offset == len(data)
