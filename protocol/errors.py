"""Protocol errors, split by fault (as in h11): we did something illegal, or the peer did."""

from __future__ import annotations


class ProtocolError(Exception):
    """Base of every error the wire layer raises. ``field`` names the offending field."""

    def __init__(self, message: str, field: str = "") -> None:
        super().__init__(f"{field}: {message}" if field else message)
        self.field = field


class LocalProtocolError(ProtocolError):
    """We tried to send something the protocol does not allow (a bug on our side)."""


class RemoteProtocolError(ProtocolError):
    """A peer sent something malformed; it is counted and dropped, the agent lives on."""


class MalformedMessage(RemoteProtocolError):
    """Not msgpack, wrong structure, wrong types or shapes, truncated."""


class UnsupportedVersion(RemoteProtocolError):
    """A schema version or message type this implementation does not know."""


class LimitExceeded(RemoteProtocolError):
    """Over a configured limit: sizes, counts, or a number beyond its configured bound (what a
    different configuration could accept)."""


class InvalidValue(RemoteProtocolError):
    """Well-formed but meaningless under any configuration: non-finite numbers, asymmetric or
    indefinite matrices, angles beyond ±2π, bad ids."""


class BadSignature(RemoteProtocolError):
    """A slot that a fleet with signing keys cannot accept: unsigned, of an owner the roster does
    not know, or whose owner's signature does not verify (forged or altered on the way)."""


class SenderMismatch(RemoteProtocolError):
    """A stack whose ``sender`` is not the robot of the key it was published on."""
