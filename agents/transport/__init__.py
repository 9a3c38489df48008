"""Transports: the in-memory one for unit tests and Zenoh (``agents.transport.zenoh_transport``,
imported only where needed, so that nothing else loads zenoh)."""

from agents.transport.base import Inbox, Keys, Message, Transport
from agents.transport.memory import MemoryBus, MemoryTransport

__all__ = ["Inbox", "Keys", "MemoryBus", "MemoryTransport", "Message", "Transport"]
