"""Owner-signed slots (wire version 2, docs/wire.md "Signed slots"): canonical bytes, Ed25519.

A slot's canonical bytes are the msgpack array ``["semfleet-slot-v2", owner, epoch, stamp,
objects, real]`` with ``objects`` and ``real`` exactly as they appear in the slot map. The owner
signs their BLAKE3 digest with Ed25519; a receiver recomputes them from the slot it decoded and
verifies the signature against the owner's public key from its roster. A relay re-sends the slot
with the owner's signature: it can neither forge nor alter anyone's slot. Pure: keys are passed
in, nothing is read from files.

Keys are `cryptography`'s (files, certificates) and so is signing. A verification runs in
ed25519-zebra (Rust, through py-ed25519-zebra-bindings): 0.034–0.060 ms here, against 0.083–0.104
ms in libsodium (PyNaCl) and 0.16–0.24 ms in OpenSSL through `cryptography`, measured in turns on
the same keys and signatures. It follows ZIP 215: S must be canonical (below ℓ), and the check is
the cofactored equation, which accepts a point encoding of R or A that is not canonical and
a public key of small order. The key is therefore admitted first, once per key: libsodium's
``crypto_core_ed25519_is_valid_point`` refuses a non-canonical encoding, a point of small order
and a point outside the prime-order subgroup — so a roster can hold no key that "verifies"
anything. For a signature of an honest owner both rules agree (a non-canonical encoding of a
random R has probability ~2⁻²⁴⁶), so a relay still cannot alter a signature's bytes.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any

import blake3
import msgpack
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey
from ed25519_zebra import ed_verify
from nacl.bindings import crypto_core_ed25519_is_valid_point

CONTEXT = "semfleet-slot-v2"
SIGNATURE_BYTES = 64

# The canonical bytes' first two items: the array header and the context.
_HEAD = bytes(msgpack.Packer(use_bin_type=True).pack_array_header(6)) + msgpack.packb(CONTEXT)

# owner → the Ed25519 public key that signs its slots
SigningKeys = Mapping[str, Ed25519PublicKey]


def canonical_bytes(
    owner: str, epoch: int, stamp: int, objects: list[Any], real: list[Any]
) -> bytes:
    """What the owner signs: the slot's fields in wire form, in one msgpack array."""
    doc = [CONTEXT, owner, epoch, stamp, objects, real]
    return bytes(msgpack.packb(doc, use_bin_type=True))


def digest(data: bytes) -> bytes:
    """What the Ed25519 signature covers: the 32-byte BLAKE3 hash of the canonical bytes (one
    pass over a slot, where Ed25519 alone hashes a long message with SHA-512 twice to sign and
    once to verify; BLAKE3 rather than SHA-256 because a slot can be a megabyte: measured here
    0.13 ms against 0.60 ms for 1.1 MB, docs/wire.md)."""
    return bytes(blake3.blake3(data).digest())


def digest_of_parts(
    owner: str, epoch: int, stamp: int, objects: bytes | memoryview, real: bytes | memoryview
) -> bytes:
    """:func:`digest` of the canonical bytes, given ``objects`` and ``real`` already packed (the
    bytes of a slot as received): the same hash, without building the canonical bytes."""
    head = _HEAD + msgpack.packb(owner) + msgpack.packb(epoch) + msgpack.packb(stamp)
    h = blake3.blake3(head)
    h.update(objects)
    h.update(real)
    return bytes(h.digest())


def sign(key: Ed25519PrivateKey, data: bytes) -> bytes:
    return key.sign(digest(data))


def verify(key: Ed25519PublicKey, data: bytes, signature: bytes) -> bool:
    return verify_digest(key, digest(data), signature)


def verify_digest(key: Ed25519PublicKey, digest_: bytes, signature: bytes) -> bool:
    raw = key.public_bytes_raw()
    if len(signature) != SIGNATURE_BYTES or not admitted(raw):
        return False
    return bool(ed_verify(bytes(signature), bytes(digest_), raw))


@functools.lru_cache(maxsize=4096)
def admitted(public: bytes) -> bool:
    """Whether a 32-byte Ed25519 public key may verify anything: a canonical encoding of a point
    of the prime-order subgroup, not of small order (cached: a roster's keys are few and fixed,
    and the check costs a scalar multiplication)."""
    return len(public) == 32 and bool(crypto_core_ed25519_is_valid_point(public))
