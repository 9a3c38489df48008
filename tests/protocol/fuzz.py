"""What the wire-codec tests share (test_codec, test_frames, test_estimate): documents as msgpack
trees addressed by field paths, malformed blobs made from a reference document one field at a
time, and the fuzzing that proves nothing but a RemoteProtocolError naming a field escapes a
decoder.

Each test file makes one ``Wire`` (its decoder, reference document, default limits and what a
decoded message promises) and one ``Mutator`` (the structured fuzz, parametrised by the codec's
keys, sample strings and edge integers).

The asserts here carry their own messages: pytest rewrites asserts only in test modules.
"""

from __future__ import annotations

import copy
import struct
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from protocol.errors import MalformedMessage, RemoteProtocolError

Path = tuple[str | int, ...]

# Reproducible in CI: the same examples on every run, no example database, no timing flakiness.
FUZZ = settings(derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow])

SPECIAL_FLOATS = (0.0, -0.0, 5e-324, -5e-324, 2.2250738585072014e-308, 1.7976931348623157e308)
ROBOT_IDS = st.text(
    "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_-", min_size=1, max_size=32
)
# Up to four (offset, byte) overwrites of an encoded message; offsets wrap around its length.
BYTE_EDITS = st.lists(st.tuples(st.integers(0, 2**20), st.integers(0, 255)), min_size=1, max_size=4)
FLOAT64S = st.floats().map(lambda x: struct.pack("<d", x))


def finite(
    rng: np.random.Generator, shape: tuple[int, ...], special: Sequence[float] = SPECIAL_FLOATS
) -> np.ndarray:
    """Finite float64s of ``shape``: ordinary magnitudes, or arbitrary bit patterns (subnormals,
    ±0, extremes), with ``special`` values sprinkled in."""
    if rng.random() < 0.5:
        values = rng.standard_normal(shape) * 10.0 ** int(rng.integers(-3, 4))
    else:
        values = rng.integers(0, 2**64, size=shape, dtype=np.uint64).view(np.float64)
        values = np.where(np.isfinite(values), values, -0.0)
    chosen = rng.random(shape) < 0.2
    values[chosen] = rng.choice(special, size=int(chosen.sum()))
    return values


def corrupt(blob: bytes, edits: list[tuple[int, int]]) -> bytes:
    """``blob`` with each (offset, byte) of ``edits`` written, the offset modulo its length."""
    out = bytearray(blob)
    for at, byte in edits:
        out[at % len(out)] = byte
    return bytes(out)


# --------------------------------------------------------------------------- documents


def field_name(path: Path) -> str:
    """The field a decoder names for ``path``: ("slots", 0, "real") is "slots[0].real"."""
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else p)
    return out


def get_at(doc: Any, path: Path) -> Any:
    for p in path:
        doc = doc[p]
    return doc


def set_at(doc: Any, path: Path, value: Any) -> Any:
    """``doc`` with the node at ``path`` replaced (in place, but for the root: returns the new)."""
    if not path:
        return value
    get_at(doc, path[:-1])[path[-1]] = value
    return doc


def paths(node: Any, prefix: Path = ()) -> Iterator[Path]:
    """Every path in ``node``, parents before their children."""
    yield prefix
    if isinstance(node, dict):
        for k, v in node.items():
            yield from paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from paths(v, (*prefix, i))


def pack(doc: Any) -> bytes:
    return bytes(msgpack.packb(doc, use_bin_type=True))


@dataclass(frozen=True)
class Wire:
    """One codec under test: ``decode(blob, limits)``, the reference document malformed blobs are
    made from, the limits ``decode`` applies when given None, and ``check(decoded, limits)``: what
    a successful decode promises (it fails the test otherwise)."""

    decode: Callable[[bytes, Any], Any]
    ref_doc: Any
    default_limits: Any
    check: Callable[[Any, Any], None]

    def with_(self, path: Path, value: Any) -> bytes:
        """The reference document with the field at ``path`` replaced (or added)."""
        return pack(set_at(copy.deepcopy(self.ref_doc), path, value))

    def without(self, path: Path) -> bytes:
        """The reference document with the field at ``path`` deleted."""
        doc = copy.deepcopy(self.ref_doc)
        del get_at(doc, path[:-1])[path[-1]]
        return pack(doc)

    def poke(self, path: Path, index: int, value: float | int, fmt: str = "<d") -> bytes:
        """The reference document with 8-byte number ``index`` of the binary at ``path`` replaced
        by ``value`` packed as ``fmt``."""
        blob = get_at(self.ref_doc, path)
        return self.with_(path, blob[: 8 * index] + struct.pack(fmt, value) + blob[8 * index + 8 :])

    def assert_rejected(
        self, blob: bytes, error: type[RemoteProtocolError], field: str, limits: Any = None
    ) -> None:
        """``decode`` raises exactly ``error`` (or a subclass) for ``field``, and says so first."""
        with pytest.raises(error) as caught:
            self.decode(blob, limits)
        got = caught.value
        assert got.field == field, f"field {got.field!r}, expected {field!r}: {got!r}"
        assert str(got).startswith(f"{field}: "), f"message {str(got)!r} does not start {field!r}"

    def decode_or_reject(self, blob: bytes, limits: Any = None) -> None:
        """Decode and check what the decoded message promises, or accept a RemoteProtocolError
        naming a field; any other exception fails the test."""
        try:
            msg = self.decode(blob, limits)
        except RemoteProtocolError as exc:
            assert exc.field, f"error without a field: {exc!r}"
            return
        self.check(msg, limits or self.default_limits)

    def assert_every_prefix_malformed(self, blob: bytes) -> None:
        """Every proper prefix of ``blob`` is a MalformedMessage for "message"; whatever else
        escapes (or decodes) is reported, for every length."""
        escaped = []
        for length in range(len(blob)):
            try:
                self.decode(blob[:length], None)
            except MalformedMessage as exc:
                assert exc.field == "message", f"length {length}: {exc!r}"
            except Exception as exc:  # the point of the test: report what escaped, for every length
                escaped.append((length, repr(exc)))
            else:
                escaped.append((length, "decoded"))
        assert not escaped, escaped[:5]


# --------------------------------------------------------------------------- structured fuzz


class Mutator:
    """Random edits of a document at random field paths (replace, copy, delete, add, poke a number,
    resize), with values drawn around what the codec knows: its map keys (``known_keys``), strings
    (``strings``) and the integers at its edges (``edge_ints``), float64 blobs of up to
    ``float_blob_size`` numbers, any ``extra_scalars``, and ``numbers`` (8-byte packed) to poke."""

    OPS = ("replace", "copy", "delete", "add", "poke", "resize")

    def __init__(
        self,
        known_keys: Sequence[str],
        strings: Sequence[str],
        edge_ints: Sequence[int],
        float_blob_size: int = 9,
        extra_scalars: Sequence[st.SearchStrategy[Any]] = (),
        numbers: st.SearchStrategy[bytes] = FLOAT64S,
    ) -> None:
        float_blobs = st.lists(st.floats(), max_size=float_blob_size).map(
            lambda xs: struct.pack(f"<{len(xs)}d", *xs)
        )
        self.scalars: st.SearchStrategy[Any] = st.one_of(
            st.none(),
            st.booleans(),
            st.integers(-(2**63), 2**64 - 1),
            st.sampled_from(tuple(edge_ints)),
            st.floats(),
            st.text(max_size=40),
            st.sampled_from(tuple(strings)),
            st.binary(max_size=64),
            float_blobs,
            st.builds(msgpack.ExtType, st.integers(0, 127), st.binary(max_size=12)),
            *extra_scalars,
        )
        # Keys of generated maps; add_keys adds the non-string keys msgpack carries but a decoder
        # must refuse.
        self.keys = st.sampled_from(tuple(known_keys)) | st.text(max_size=8)
        self.add_keys = self.keys | st.integers(-3, 3) | st.binary(max_size=3)
        self.values = st.recursive(
            self.scalars,
            lambda children: (
                st.lists(children, max_size=4) | st.dictionaries(self.keys, children, max_size=4)
            ),
            max_leaves=8,
        )
        self.numbers = numbers

    def mutate(self, doc: Any, data: st.DataObject) -> Any:
        """One random edit at a random field path of ``doc`` (in place where it can be)."""
        where = list(paths(doc))[::-1]  # hypothesis favours the first choices: make them leaves
        path = data.draw(st.sampled_from(where))
        node = get_at(doc, path)
        op = data.draw(st.sampled_from(self.OPS))
        if op == "copy":
            return set_at(doc, path, copy.deepcopy(get_at(doc, data.draw(st.sampled_from(where)))))
        if op == "delete" and path:
            del get_at(doc, path[:-1])[path[-1]]
            return doc
        if op == "add" and isinstance(node, dict):
            node[data.draw(self.add_keys)] = data.draw(self.values)
            return doc
        if op == "add" and isinstance(node, list):
            node.insert(data.draw(st.integers(0, len(node))), data.draw(self.values))
            return doc
        if op == "poke" and isinstance(node, bytes) and len(node) >= 8:
            i = 8 * data.draw(st.integers(0, len(node) // 8 - 1))
            return set_at(doc, path, node[:i] + data.draw(self.numbers) + node[i + 8 :])
        if op == "resize" and isinstance(node, bytes | str | list):
            cut = data.draw(st.integers(0, len(node)))
            pad: Any = {bytes: b"\x00", str: "a", list: [0]}[type(node)]
            return set_at(doc, path, node[:cut] + pad * data.draw(st.integers(0, 9)))
        return set_at(doc, path, data.draw(self.values))

    def mutated(self, doc: Any, edits: int, data: st.DataObject) -> Any:
        """A deep copy of ``doc`` after ``edits`` random edits."""
        out = copy.deepcopy(doc)
        for _ in range(edits):
            out = self.mutate(out, data)
        return out
