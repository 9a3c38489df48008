"""A stack message read without its slot bodies (docs/wire.md, "Decoding only what is new").

:func:`scan` unpacks a message as ``msgpack.unpackb`` would, except that every map in the
top-level ``slots`` array becomes a :class:`SlotFrame`: its small fields (owner, epoch, stamp,
sig) unpacked, its bodies (``objects`` and ``real``, nearly all of a slot's bytes) only located.
The codec then parses a body only for a slot version the receiver will take, verifies a
signature over the body bytes as received (no re-packing), and keeps those bytes so that a relay
re-sends them untouched. Malformed input raises what ``msgpack.unpackb`` raises for it (the codec
turns every exception into ``MalformedMessage``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import msgpack

BODIES = ("objects", "real")


@dataclass(frozen=True, slots=True)
class SlotFrame:
    """One slot map of a message: ``fields`` as unpacked (a body field maps to :data:`BODY`),
    the byte range of the whole map (``start``, ``end``) and of each body (``spans``)."""

    start: int
    end: int
    fields: dict[str, Any]
    spans: dict[str, tuple[int, int]]


class _Body:
    """Stands for a body field in :attr:`SlotFrame.fields` (not unpacked yet)."""

    def __repr__(self) -> str:
        return "<body>"


BODY = _Body()


def _is_map(byte: int) -> bool:
    return 0x80 <= byte <= 0x8F or byte in (0xDE, 0xDF)


def _is_array(byte: int) -> bool:
    return 0x90 <= byte <= 0x9F or byte in (0xDC, 0xDD)


def _key(unpacker: msgpack.Unpacker) -> str:
    key = unpacker.unpack()
    if not isinstance(key, str | bytes):
        raise ValueError(f"{type(key).__name__} is not allowed for map key")
    return key  # type: ignore[return-value]  # bytes keys fail the codec's key checks


def scan(data: bytes) -> Any:
    """The document of ``data`` with its slot maps as :class:`SlotFrame` (module docstring)."""
    if not data or not _is_map(data[0]):
        return msgpack.unpackb(data, raw=False, strict_map_key=True, use_list=True)
    unpacker = msgpack.Unpacker(
        raw=False, strict_map_key=True, use_list=True, max_buffer_size=len(data)
    )
    unpacker.feed(data)
    doc: dict[Any, Any] = {}
    for _ in range(unpacker.read_map_header()):
        key = _key(unpacker)
        if key == "slots" and unpacker.tell() < len(data) and _is_array(data[unpacker.tell()]):
            slots: list[Any] = []
            for _ in range(unpacker.read_array_header()):
                at = unpacker.tell()
                if at < len(data) and _is_map(data[at]):
                    slots.append(_frame(unpacker, at))
                else:
                    slots.append(unpacker.unpack())
            doc[key] = slots
        else:
            doc[key] = unpacker.unpack()
    if unpacker.tell() != len(data):
        raise ValueError(f"extra data after the message ({len(data) - unpacker.tell()} bytes)")
    return doc


def _frame(unpacker: msgpack.Unpacker, start: int) -> SlotFrame:
    fields: dict[str, Any] = {}
    spans: dict[str, tuple[int, int]] = {}
    for _ in range(unpacker.read_map_header()):
        key = _key(unpacker)
        if key in BODIES:
            first = unpacker.tell()
            unpacker.skip()
            spans[key] = (first, unpacker.tell())
            fields[key] = BODY
        else:
            fields[key] = unpacker.unpack()
    return SlotFrame(start, unpacker.tell(), fields, spans)
