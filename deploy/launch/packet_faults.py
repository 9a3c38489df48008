"""Who hears whom, as nftables rules on real packets (``semfleet chaos --net netns``).

Pure: a link verdict in, the text of an ``nft -f -`` transaction out; nothing here runs a
command (:mod:`deploy.launch.netns` applies the text inside each robot's namespace).

Every robot's namespace holds one table, ``semfleet_<run>``, whose ``input`` chain filters what
arrives at that robot, by the sender's address on the bridge:

- a sender the verdict cuts (partition, out of range, outside the schedule): every packet dropped
  (counter ``cut``);
- every other robot: each packet dropped with the run's loss probability (counter ``lost``), the
  kernel's ``numgen random`` in steps of 1/:data:`LOSS_SCALE`.

The conductor's address (the bridge's) is never matched: frames, control and estimates always
flow. Rules sit on the *input* hook: a drop there is a packet that never arrived, as on a radio
(on the output hook the sender's ``sendto`` would fail with EPERM). The input chain is flushed and
refilled in the same transaction, so a change is atomic; the named counters survive it and count
for the whole run.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

LOSS_SCALE = 10_000  # loss probability resolution: 0.01 %
CHAIN = "input"
COUNTERS = ("lost", "cut")


class RulesetError(ValueError):
    """A verdict or an nft answer that does not fit the run (names the field)."""


@dataclass(frozen=True, slots=True)
class ReceiverRules:
    """What one robot's namespace drops: every packet from ``cut`` (sender addresses), each packet
    from ``lossy`` with probability ``loss``."""

    table: str
    cut: tuple[str, ...]
    lossy: tuple[str, ...]
    loss: float

    def __post_init__(self) -> None:
        if not 0.0 <= self.loss <= 1.0:
            raise RulesetError(f"loss {self.loss:g}: a probability needs 0 ≤ p ≤ 1")
        both = sorted(set(self.cut) & set(self.lossy))
        if both:
            raise RulesetError(f"addresses {', '.join(both)}: both cut and lossy")

    @property
    def threshold(self) -> int:
        """Packets whose random number in 0..LOSS_SCALE-1 is below this are lost."""
        return round(self.loss * LOSS_SCALE)


def receiver_rules(
    verdict: Mapping[str, Sequence[str]],
    receiver: str,
    addresses: Mapping[str, str],
    loss: float,
    table: str,
) -> ReceiverRules:
    """The rules of ``receiver``'s namespace for one step. ``verdict[r]``: the robots ``r`` hears
    (:func:`deploy.launch.conductor.links_at`); ``addresses``: every robot's address."""
    if receiver not in verdict:
        raise RulesetError(f"verdict: no entry for receiver {receiver}")
    unknown = sorted(set(verdict[receiver]) - set(addresses))
    if unknown:
        raise RulesetError(f"verdict of {receiver}: senders {unknown} have no address")
    heard = set(verdict[receiver])
    senders = [r for r in addresses if r != receiver]
    cut = tuple(addresses[s] for s in senders if s not in heard)
    lossy = tuple(addresses[s] for s in senders if s in heard) if loss > 0 else ()
    return ReceiverRules(table, cut, lossy, loss)


def ruleset(rules: ReceiverRules) -> str:
    """One ``nft -f -`` transaction: declare the table, its counters and chain (kept if they
    exist), flush the chain, fill it with this step's rules."""
    lines = [
        f"table inet {rules.table} {{",
        *(f"\tcounter {name} {{\n\t}}" for name in COUNTERS),
        f"\tchain {CHAIN} {{",
        "\t\ttype filter hook input priority filter; policy accept;",
        "\t}",
        "}",
        f"flush chain inet {rules.table} {CHAIN}",
        f"table inet {rules.table} {{",
        f"\tchain {CHAIN} {{",
    ]
    if rules.cut:
        lines.append(f'\t\tip saddr {_set(rules.cut)} counter name "cut" drop')
    if rules.lossy and rules.threshold > 0:
        lines.append(
            f"\t\tip saddr {_set(rules.lossy)} numgen random mod {LOSS_SCALE} < "
            f'{rules.threshold} counter name "lost" drop'
        )
    lines += ["\t}", "}"]
    return "\n".join(lines) + "\n"


def _set(addresses: Sequence[str]) -> str:
    return "{ " + ", ".join(addresses) + " }"


def counters(nft_json: str, table: str) -> dict[str, int]:
    """Packets per counter of ``table`` from ``nft -j list counters`` output."""
    try:
        doc = json.loads(nft_json)
        items = doc["nftables"]
    except (ValueError, KeyError, TypeError):
        raise RulesetError("nft -j list counters: not the JSON nft writes") from None
    found = {name: 0 for name in COUNTERS}
    for item in items if isinstance(items, list) else ():
        c = item.get("counter") if isinstance(item, dict) else None
        if isinstance(c, dict) and c.get("table") == table and c.get("name") in found:
            packets = c.get("packets")
            if not isinstance(packets, int):
                raise RulesetError(f"counter {c.get('name')}: packets {packets!r}")
            found[c["name"]] = packets
    return found


def describe_cuts(verdict: Mapping[str, Sequence[str]], robots: Sequence[str]) -> str:
    """The links a verdict cuts, for people: ``r1 ✗ r3`` (both directions cut) or ``r1 ↛ r2``
    (r1's packets to r2 only); ``none`` when every robot hears every other."""
    cut = {(s, r) for r in robots for s in robots if s != r and s not in verdict.get(r, ())}
    words = []
    for i, a in enumerate(robots):
        for b in robots[i + 1 :]:
            if (a, b) in cut and (b, a) in cut:
                words.append(f"{a} ✗ {b}")
            elif (a, b) in cut:
                words.append(f"{a} ↛ {b}")
            elif (b, a) in cut:
                words.append(f"{b} ↛ {a}")
    return ", ".join(words) or "none"
