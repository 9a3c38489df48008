"""SimRadio: a simulated robot's radio, without any I/O (built only in a simulation).

The simulator publishes, a step ahead (``sim/listen``) and at each step (``sim/links``), who
hears whom (docs/agents.md). The radio keeps those verdicts within ``window`` steps ahead and
answers: whether a sender is heard at the coming step (:meth:`SimRadio.heard`: a stack of a
robot out of range is not even read), whom to subscribe to (:meth:`SimRadio.listen`) and which
stacks are worth waking for (:meth:`SimRadio.hear`). No real robot ever obeys it.
"""

from __future__ import annotations

from collections.abc import Callable

from agents.control import StepOrder, decode_control
from protocol.errors import RemoteProtocolError

Links = dict[str, tuple[str, ...]]  # receiver → the senders it hears


class SimRadio:
    def __init__(self, robot: str, window: int, max_control_bytes: int) -> None:
        self.robot = robot
        self.window = window
        self.max_control_bytes = max_control_bytes
        self.links: dict[int, Links] = {}  # the verdicts obeyed (``sim/links``)
        self.ahead: dict[int, Links] = {}  # those sent a step ahead (``sim/listen``): to subscribe
        self.listening: frozenset[str] | None = None  # the peers of the last subscription
        self.hearing: frozenset[str] | None = None  # the keys of the last wake-up set
        self.invalid_links = 0
        self.listen_changes = 0
        self.ignored_out_of_range = 0

    def on_links(self, payload: bytes, ahead: bool, k: int) -> Exception | None:
        """Keep a verdict of who hears whom at a step within the window of ``k`` (``ahead``:
        sent a step ahead); the error of one that does not decode (counted), else None."""
        try:
            order = decode_control(payload, max_bytes=self.max_control_bytes)
            if not isinstance(order, StepOrder):
                raise ValueError(f"expected links, got {type(order).__name__}")
        except (RemoteProtocolError, ValueError) as exc:
            self.invalid_links += 1
            return exc
        if k <= order.k <= k + self.window:
            (self.ahead if ahead else self.links)[order.k] = order.links
        return None

    def heard(self, sender: str, k: int) -> bool:
        """Whether the latest links published for step ``k + 1`` let ``sender`` through to this
        robot (no links yet: nobody is heard)."""
        due = [j for j in self.links if j <= k + 1]
        if not due:
            return False
        return sender in self.links[max(due)].get(self.robot, ())

    def out_of_range(self) -> None:
        """A stack of a robot not heard was dropped (counted once the first links are here:
        before them nobody is out of range)."""
        if self.links:
            self.ignored_out_of_range += 1

    def listen(self, k: int, roster: frozenset[str] | None, initial: bool) -> frozenset[str] | None:
        """The peers to subscribe to when they changed (``initial``: always), else None: the
        robots heard at step ``k + 1`` or at any later step whose links are here, those sent a
        step ahead included (so that a subscription is in place before its links are due: one
        declared as they change misses what the peer publishes meanwhile); nobody before the
        first links; never a robot outside the ``roster``."""
        due = [j for j in self.links if j <= k + 1]
        first = max(due) if due else k + 1
        robots: set[str] = set()
        for later, links in [*self.links.items(), *self.ahead.items()]:
            if later >= first:
                robots.update(links.get(self.robot, ()))
        if roster is not None:
            robots &= roster
        peers = frozenset(robots - {self.robot})
        if not initial and peers == self.listening:
            return None
        self.listening = peers
        self.listen_changes += 1
        return peers

    def hear(self, k: int, key_of: Callable[[str], str]) -> frozenset[str] | None:
        """The stack keys worth waking for when they changed, else None: those of the robots
        heard under the links due at step ``k + 1`` or under any later links already here;
        before the first links, None (every stack wakes the agent)."""
        if not self.links:
            return None
        due = [j for j in self.links if j <= k + 1]
        first = max(due) if due else min(self.links)
        robots: set[str] = set()
        for j, links in self.links.items():
            if j >= first:
                robots.update(links.get(self.robot, ()))
        keys = frozenset(key_of(r) for r in robots - {self.robot})
        if keys == self.hearing:
            return None
        self.hearing = keys
        return keys

    def forget_before(self, k: int) -> None:
        """Drop the verdicts of steps up to ``k`` but the one in force at ``k + 1``."""
        latest = max((j for j in self.links if j <= k + 1), default=None)
        self.links = {j: v for j, v in self.links.items() if j > k or j == latest}
        self.ahead = {j: v for j, v in self.ahead.items() if j > k}
