"""Whose stacks an agent subscribes to (the runtime's side of the core's ``Listen``)."""

from __future__ import annotations

from agents.transport.base import Inbox, Keys, Transport


class StackSubscriptions:
    """Whose stacks an agent subscribes to: every robot's (``stack/*``), or, in a simulated real
    time run, only those of the robots its simulated radio hears at the coming step (the core's
    ``Listen``): the stacks of robots out of range are then never sent to this agent at all,
    instead of being received, handed to the loop and dropped there (two thirds of all stacks
    in a 20-robot world)."""

    def __init__(self, transport: Transport, keys: Keys, inbox: Inbox, robot: str) -> None:
        self.transport, self.keys, self.inbox = transport, keys, inbox
        self.exprs: set[str] = set()
        # The pushes addressed to this robot (event-driven relay answering its asks), from any
        # peer, whoever it follows: only peers it asked send them.
        self.pushes = keys.stack_to("*", robot)
        transport.subscribe(self.pushes, inbox)

    def follow(self, peers: frozenset[str] | None) -> bool:
        """Subscribe to the stacks of ``peers`` only (None: of every robot); whether a
        subscription was added (the pushes to this robot are always subscribed to)."""
        want = {self.keys.stack("*")} if peers is None else {self.keys.stack(p) for p in peers}
        for expr in sorted(self.exprs - want):
            self.transport.unsubscribe(expr, self.inbox)
        added = sorted(want - self.exprs)
        for expr in added:
            self.transport.subscribe(expr, self.inbox)
        self.exprs = want
        return bool(added)
