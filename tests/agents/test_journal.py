"""The durable journal: records round trip, reopening appends, another identity is refused, a torn
or corrupt tail is cut back to the last intact record, and committed records survive SIGKILL of a
real process. (SIGKILL proves the process-crash case; what the fsync adds, surviving a power cut,
cannot be shown without pulling the plug.)"""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import textwrap
import zlib
from pathlib import Path

import msgpack
import pytest

from agents.journal import Journal, JournalError, Record

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
    assert msgpack.unpackb(header, raw=False) == {"format": 1, "identity": IDENTITY}
    assert payloads[1] == ["frame", b"abc"]


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
        journal.append("frame", b"again")
        journal.close()
        journal, got = _reopen(path)
        journal.close()
        assert got == [*records[:-1], Record("frame", b"again")], cut


@pytest.mark.parametrize("where", ["length", "crc", "payload", "kind"])
def test_journal_corrupt_record_in_the_middle_drops_it_and_all_later_ones(
    tmp_path: Path, where: str
) -> None:
    """Replay order matters: a record after a corrupt one would rebuild a belief the agent never
    had, so the journal keeps only the intact prefix."""
    path = tmp_path / "r1.journal"
    _write(path, RECORDS)
    data = bytearray(path.read_bytes())
    starts = _offsets(path)
    second = starts[2]  # RECORDS[1]
    offset = {"length": second, "crc": second + 4, "payload": starts[3] - 1}.get(where)
    if offset is None:  # a payload that passes its crc but is not [kind, body]
        payload = msgpack.packb(["Not-A-Kind", b""])
        record = len(payload).to_bytes(4, "little") + zlib.crc32(payload).to_bytes(4, "little")
        data[second : starts[3]] = record + payload
    else:
        data[offset] ^= 0x40
    path.write_bytes(bytes(data))
    journal, records = _reopen(path)
    assert records == RECORDS[:1]
    assert journal.truncated_bytes == len(data) - second
    journal.close()
    assert path.stat().st_size == second


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
