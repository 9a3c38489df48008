"""One attacked launch and its report (``semfleet chaos --attack``; :mod:`deploy.launch.attacks`
has the attacks themselves).

The launch is lock-step, with the attackers' sessions opened as soon as the agents' ports are
known. On a secure fleet two attackers act at once: a session that knows the fleet's CA but holds
no certificate, and one holding a member's certificate and signing key (the last robot's) that
attacks another member (the first robot). On a plain fleet one session with no credentials at
all shows what each attack does where nothing stops it. Afterwards every estimate the conductor
received is compared with the clean run — the in-process runner, which a clean lock-step launch
equals — and each attack's evidence is read off the estimates and the agents' counters.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from agents.transport.base import Keys
from agents.transport.zenoh_transport import ZenohSettings
from deploy.base.build import belief_model, belief_rng, make_nodes
from deploy.launch.attacks import Achieved, Attacker, Identity, evidence, open_all, roles
from deploy.launch.conductor import Conductor, links_at
from deploy.launch.errors import LaunchError, PlanError
from deploy.launch.run import Launcher, LaunchPlan
from deploy.study.fleet import link_model_for, run_fleet
from estimator.hybrid import BeliefConfig, BeliefSnapshot
from sim.sensors import Simulator

FIELDS = ("weights", "robot_pose", "robot_cov", "object_pose", "object_cov")
RTOL = ATOL = 1e-9  # a clean lock-step launch equals the in-process runner to rounding error


@dataclass(slots=True)
class AttackReport:
    """What the attacks of one run achieved. ``compared``: (robot, step) estimates compared with
    the clean run, ``differing`` those that differ (robot, step, belief); ``stopped_early``:
    agents that stopped before the run's last step; ``failure``: why the run ended early."""

    fleet: str
    attackers: list[Attacker]
    achieved: list[Achieved]
    compared: int
    differing: list[tuple[str, int, str]]
    stopped_early: list[str]
    counters: dict[str, dict[str, int]]
    failure: str = ""
    steps: int = 0
    connected: dict[str, str] = field(default_factory=dict)
    last_step: dict[str, int] = field(default_factory=dict)

    @property
    def identical(self) -> bool:
        return self.compared > 0 and not self.differing and not self.stopped_early

    def achieved_nothing(self) -> bool:
        return self.identical and not any(a.effects for a in self.achieved)


class AttackedLauncher(Launcher):
    """A launcher whose attackers open their sessions once the agents' ports are known."""

    def __init__(self, plan: LaunchPlan, attacks: Sequence[str]) -> None:
        super().__init__(plan)
        self.attacks = tuple(attacks)
        self.attackers: list[Attacker] = []
        frames = Simulator(plan.scenario, plan.seed).all_frames()
        links = [links_at(self.links, frames, plan.robots, k) for k in range(1, self.steps + 1)]
        self.roles = roles(links, plan.robots)  # (victim, accomplice)

    def _conductor(self, conductor_port: int) -> Conductor:
        """The conductor, whose wait for the agents' tokens is followed by the attackers'
        sessions (dialling every agent, once every agent listens)."""
        conductor = super()._conductor(conductor_port)
        plan = self.plan
        m = plan.scenario.num_classes
        keys = Keys(plan.fleet)
        self.attackers = [
            Attacker(i, self.attacks, keys, plan.robots, *self.roles, m, self.steps, plan.seed)
            for i in self._identities()
        ]
        wait_alive = conductor.wait_alive

        async def wait_then_attack(timeout: float, check: Callable[[], None] | None = None) -> None:
            await wait_alive(timeout, check)
            await open_all(self.attackers)

        conductor.wait_alive = wait_then_attack  # type: ignore[method-assign]
        return conductor

    def _identities(self) -> list[Identity]:
        plan = self.plan
        scheme = "tls" if plan.secure else "tcp"
        dial = tuple(f"{scheme}/127.0.0.1:{self.agents[r].port}" for r in plan.robots)
        out = plan.out / "attackers"
        if self._fleet is None:
            return [Identity("no credentials", ZenohSettings(connect=dial, gossip=False))]
        victim, accomplice = self.roles
        ca = self._fleet[victim] / "ca.pem"
        bare = {"transport": {"link": {"tls": {"root_ca_certificate": str(ca.resolve())}}}}
        folder = self._fleet[accomplice].resolve()
        tls = {
            "root_ca_certificate": str(folder / "ca.pem"),
            "connect_certificate": str(folder / "tls.pem"),
            "connect_private_key": str(folder / "tls.key"),
            "enable_mtls": True,
        }
        member = {"transport": {"link": {"tls": tls}}}
        key = serialization.load_pem_private_key((folder / "signing.key").read_bytes(), None)
        assert isinstance(key, Ed25519PrivateKey)
        return [
            Identity(
                "uncertified (the fleet's CA, no certificate)",
                ZenohSettings(
                    connect=dial, gossip=False, config_file=_config(out / "uncertified.json5", bare)
                ),
            ),
            Identity(
                f"certified as {accomplice} (attacking {victim})",
                ZenohSettings(
                    connect=dial, gossip=False, config_file=_config(out / "member.json5", member)
                ),
                accomplice,
                key,
            ),
        ]

    async def run_attacked(self) -> tuple[Conductor, str]:
        """The run; returns the conductor and, if the run ended early, why."""

        def on_step(_conductor: Conductor, k: int) -> None:
            for a in self.attackers:
                a.on_step(k)

        failure = ""
        try:
            await self.run(on_step)
        except LaunchError as exc:
            failure = str(exc)
        finally:
            for a in self.attackers:
                await a.close()
        assert self.conductor is not None
        return self.conductor, failure


def _config(path: Path, doc: Mapping[str, Any]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return path


def clean_snapshots(plan: LaunchPlan, steps: int) -> dict[tuple[str, str, int], BeliefSnapshot]:
    """(belief, robot, step) → snapshot of the clean in-process run of ``plan``'s scenario."""
    s = plan.scenario
    frames = Simulator(s, plan.seed).all_frames()
    nodes = make_nodes(s, belief_model(s), BeliefConfig(), lambda r: belief_rng(plan.seed, [r]))
    nodes = {r: n for r, n in nodes.items() if r in plan.robots}
    out: dict[tuple[str, str, int], BeliefSnapshot] = {}

    def record(robot: str, k: int, node, _f: float, _ms: float) -> None:  # type: ignore[no-untyped-def]
        out[("local", robot, k)] = node.local.snapshot(robot)
        out[("distributed", robot, k)] = node.distributed.snapshot(robot)

    run_fleet(nodes, frames, link_model_for(s, plan.comm), steps, record)
    return out


def _same(a: BeliefSnapshot, b: BeliefSnapshot) -> bool:
    if a.object_ids != b.object_ids or not np.array_equal(a.classes, b.classes):
        return False
    if (a.class_probs is None) != (b.class_probs is None):
        return False  # per-object class marginals in one only
    fields = FIELDS if a.class_probs is None else (*FIELDS, "class_probs")
    return all(
        np.shape(getattr(a, f)) == np.shape(getattr(b, f))
        and np.allclose(getattr(a, f), getattr(b, f), rtol=RTOL, atol=ATOL)
        for f in fields
    )


def run_attacks(plan: LaunchPlan, attacks: Sequence[str]) -> AttackReport:
    """Run ``plan`` (lock-step, nothing else chaotic) under ``attacks`` and report."""
    if plan.mode != "lockstep" or plan.faults.schedule() or plan.faults.drop:
        raise PlanError("attacks run on a clean lock-step launch (no other faults)")
    if len(plan.robots) < 2:
        raise PlanError("attacks need two robots: a victim and another member")
    plan.keep_estimates = True
    launcher = AttackedLauncher(plan, attacks)
    conductor, failure = asyncio.run(launcher.run_attacked())
    steps = launcher.steps
    collected = conductor.collected
    reference = clean_snapshots(plan, steps)
    differing = []
    for (robot, k), est in sorted(collected.estimates.items()):
        for belief, snap in est.beliefs.items():
            ref = reference.get((belief, robot, k))
            if ref is not None and not _same(snap, ref):
                differing.append((robot, k, belief))
    stopped = sorted(r for r in plan.robots if collected.last_step.get(r, 0) < steps)
    achieved = evidence(
        attacks,
        collected.estimates,
        collected.counters,
        collected.last_step,
        steps,
        stopped,
        launcher.roles[0],
    )
    connected = {
        a.identity.label: (
            f"refused: {a.error}"
            if a.error
            else f"saw {len(a.seen_alive)} of {len(plan.robots)} agents' tokens"
        )
        for a in launcher.attackers
    }
    return AttackReport(
        "secure" if plan.secure else "insecure",
        launcher.attackers,
        achieved,
        len(collected.estimates),
        differing,
        stopped,
        {r: dict(c) for r, c in collected.counters.items()},
        failure,
        steps,
        connected,
        dict(collected.last_step),
    )


def run_each(make_plan: Callable[[str], LaunchPlan], attacks: Sequence[str]) -> list[AttackReport]:
    """One attacked launch per attack (``make_plan(attack)`` gives its plan): an attack that
    stops the fleet or holds a version cannot hide what another one would have done."""
    return [run_attacks(make_plan(a), (a,)) for a in attacks]
