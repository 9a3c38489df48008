"""What an agent commits and how it rebuilds, without any I/O: the :class:`Ledger` of what is
journaled, suspect or refused, and a node rebuilt from the journal's committed records — the
replay after a restart and the roll-back after a failed step (``agents.core``, "Fail-soft").

A ``stack`` record is decoded and merged as it was received; a ``frame`` or ``frame_unfused``
record is the step it was (with or without the fusion of the held slots). Frames must follow
each other from the node's step on: a record out of order is an error of the journal.
"""

from __future__ import annotations

import zlib
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from agents.journal import Record
from agents.node import RobotNode
from protocol.frames import decode_frame

FRAME, FRAME_UNFUSED = "frame", "frame_unfused"  # journal kinds of a step with and without fusion


@dataclass(slots=True)
class Replayed:
    """How many frame and stack records were replayed (restores do not count again)."""

    frames: int = 0
    stacks: int = 0


def apply(node: RobotNode, record: Record, replayed: Replayed) -> None:
    """Replay one committed record on ``node``; raises if it does not apply."""
    if record.kind == "stack":
        message = node.decode_stack(record.body)
        if message is None:
            raise ValueError(node.counters.last_error)
        node.merge(message)
        replayed.stacks += 1
    elif record.kind in (FRAME, FRAME_UNFUSED):
        frame = decode_frame(record.body)
        if frame.robot != node.robot or frame.k != node.k + 1:
            raise ValueError(f"frame of {frame.robot} at step {frame.k} after {node.k}")
        node.on_frame(frame, fuse=record.kind == FRAME)
        replayed.frames += 1


def restore(make_node: Callable[[], RobotNode], records: Sequence[Record]) -> RobotNode:
    """A fresh node replayed from ``records``, which applied before but for stack records that
    failed then (quarantined): those are skipped again. A frame that fails raises."""
    node = make_node()
    for record in records:
        try:
            apply(node, record, Replayed())
        except Exception:
            if record.kind in (FRAME, FRAME_UNFUSED):
                raise
    return node


MAX_REFUSED = (
    4096  # slot versions (and failed frames) remembered as refused, oldest forgotten first
)


class Ledger:
    """What of an agent's input is journaled, suspect or refused (``agents.core``,
    "Fail-soft"). A merged stack waits, uncommitted, for the step that fuses it: its record is
    journaled with that step's frame, and its new versions stay suspects until then. A step that
    fails refuses its suspects for good (they are never merged again) and the very bytes of its
    frame; the node is then rebuilt from the committed records and the batch's."""

    def __init__(self) -> None:
        self.uncommitted: list[Record] = []
        self.suspects: list[tuple[str, tuple[int, int]]] = []
        # The records committed while handling the current batch of messages: the shell carries
        # out a batch's actions after it, so the journal does not hold them yet.
        self.batch: list[Record] = []
        self.refused: OrderedDict[tuple[str, tuple[int, int]], None] = OrderedDict()
        self.bad_frames: OrderedDict[int, None] = OrderedDict()
        self.deferred_in_row = 0  # steps since the last one that fused (catching up)

    def took(self, merged: Sequence[tuple[str, tuple[int, int]]], payload: bytes) -> None:
        """A stack that changed the node (``merged``: its new versions)."""
        self.suspects += merged
        self.uncommitted.append(Record("stack", payload))

    def commit(self, frame: bytes, fused: bool) -> list[Record]:
        """The records that commit a step taken with the frame bytes ``frame``: a step that
        deferred its fusion commits its frame alone (the stacks merged so far stay suspects,
        for the step that fuses them); one that fused, those stacks and its frame."""
        if not fused:
            self.deferred_in_row += 1
            records = [Record(FRAME_UNFUSED, frame)]
        else:
            records = [*self.uncommitted, Record(FRAME, frame)]
            self.uncommitted, self.suspects, self.deferred_in_row = [], [], 0
        self.batch += records
        return records

    def failed(self, frame: bytes) -> list[tuple[str, tuple[int, int]]]:
        """A step with the frame bytes ``frame`` failed: these bytes and the suspects are
        refused; the suspects, returned, are tried without on the retry."""
        self.bad_frames[zlib.crc32(frame)] = None
        _bound(self.bad_frames)
        suspects = list(self.suspects)
        for version in suspects:
            self.refused[version] = None
        _bound(self.refused)
        return suspects

    def rollback(self, committed: Sequence[Record]) -> list[Record]:
        """The records to rebuild the node from after a failed step: the journal's
        (``committed``) and the batch's; nothing uncommitted is kept."""
        self.uncommitted, self.suspects = [], []
        return [*committed, *self.batch]

    def is_bad(self, frame: bytes) -> bool:
        """Whether these very frame bytes failed a step before."""
        return zlib.crc32(frame) in self.bad_frames


def _bound(table: OrderedDict[Any, None]) -> None:
    while len(table) > MAX_REFUSED:
        table.popitem(last=False)
