"""An agent's config file (TOML, docs/agents.md): read, validated and typed as an
:class:`AgentConfig`; every mistake an :class:`AgentConfigError` naming the file and field."""

from __future__ import annotations

import base64
import math
from dataclasses import dataclass
from pathlib import Path

from cryptography.exceptions import UnsupportedAlgorithm
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from agents.core import CATCH_UP_STEPS, GOSSIP_PERIOD_S, STACK_GOSSIP, WINDOW_STEPS, CoreSettings
from agents.gossip import RELAYS
from agents.node import Signing
from agents.ros2.bridge import Ros2Settings
from agents.transport.zenoh_transport import ZenohConfigError, ZenohSettings
from deploy.operator.ros2_config import read_ros2
from deploy.study.types import ASSOCIATE_ON
from estimator.hybrid import CLASS_KINDS, POSE_WINDOW, BeliefConfig
from estimator.sparse_xi import MAX_XI_PARENTS, XI_PARENTS
from protocol.codec import Limits
from protocol.signing import admitted
from protocol.validate import valid_id
from sim.loader import FieldReader, parse_toml, read_file
from sim.robot_model import RobotModel, load_robot_model
from sim.scenario import ScenarioError

MODES = ("lockstep", "realtime")
# The class representation of an agent's beliefs when its config does not say (``classes``).
DEFAULT_CLASSES = BeliefConfig().classes


class AgentConfigError(ValueError):
    """A bad agent config: names the file and field."""

    def __init__(self, path: Path, field: str, reason: str) -> None:
        super().__init__(f"{path}: {field}: {reason}")
        self.field = field


@dataclass(frozen=True, slots=True)
class AgentConfig:
    robot: str
    fleet: str
    model_path: Path
    model: RobotModel
    start: tuple[float, float, float]
    roster: frozenset[str]
    seed: int
    runtime: CoreSettings
    journal: Path | None
    zenoh: ZenohSettings
    limits: Limits
    signing: Signing | None = None
    ros2: Ros2Settings | None = None
    classes: str = DEFAULT_CLASSES
    # BeliefConfig.window: robot poses older than this many steps are marginalised (None: all kept).
    pose_window: int | None = POSE_WINDOW
    # The slots this robot keeps, its own included (None: a stack's max_slots, 64; docs/
    # distributed.md, "How many robots a D holds").
    keep_slots: int | None = None
    # Frames without global ids: what the robot's association gates on, its D or its own L
    # (docs/estimator.md, "Data association on the robot").
    associate_on: str = ASSOCIATE_ON[0]
    # BeliefConfig.xi_parents: a sparse slot's parents per object beyond its tree parent
    # (docs/estimator.md, "What the sparse ξ loses, and what more parents buy").
    xi_parents: int = XI_PARENTS


_AGENT_KEYS = {
    "fleet", "model", "start", "roster", "seed", "mode", "gossip_period", "journal",
    "publish_local", "simulation", "window", "world_extent", "stack_gossip", "relay", "catch_up",
    "listen_in_range", "classes", "pose_window", "keep_slots", "associate_on", "xi_parents",
}  # fmt: skip
_ZENOH_KEYS = {
    "listen", "connect", "gossip", "shared_memory", "lease_ms", "config_file", "insecure", "mode",
}  # fmt: skip
# A robot's session is a peer (links to its peers, the default) or a client of a router that
# forwards for it (docs/deploy.md, "Routers"); never a router itself (`semfleet router` is one).
ZENOH_MODES = ("peer", "client")
MAX_EXTENT = 1e7  # metres: a UTM-like frame; beyond, float64 poses lose millimetres


def load_agent_config(path: Path, robot: str) -> AgentConfig:
    """Parse and validate an agent config; relative paths are relative to the file's folder.
    Read with the scenario format's field reader (one validation path for every config file);
    every error is an :class:`AgentConfigError` naming the file and the field."""
    if not valid_id(robot):
        raise AgentConfigError(path, "--robot", f"invalid robot id {robot!r}")
    try:
        return _read_agent_config(path, robot)
    except ScenarioError as exc:
        raise AgentConfigError(path, exc.field or "toml", exc.reason) from None


def _check_security(z: FieldReader, settings: ZenohSettings, insecure: bool) -> None:
    """The JSON5 file and the TOML fields must agree, and an agent reachable off loopback runs
    with mutual TLS unless its config says ``insecure = true``."""
    try:
        exposed = settings.off_loopback()
        secure = settings.mutual_tls()
    except ZenohConfigError as exc:
        raise z.fail("config_file", str(exc)) from None
    if exposed and not secure and not insecure:
        raise z.fail(
            "insecure",
            f"endpoints {', '.join(exposed)} are not on loopback and the session has no mutual "
            "TLS (tls/ endpoints, root_ca_certificate, enable_mtls): use the files of "
            "`semfleet fleet init`, or set insecure = true to run without authentication",
        )


def _read_signing(sec: FieldReader, base: Path, robot: str, roster: list[str]) -> Signing:
    """``[security]``: this robot's Ed25519 signing key and the roster of public keys (both
    written by ``semfleet fleet init``); every robot of the agent's roster must have a key."""
    sec.check_keys({"signing_key", "roster"})
    key_path = base / sec.string("signing_key")
    try:
        key = serialization.load_pem_private_key(key_path.read_bytes(), None)
    except OSError as exc:
        raise sec.fail("signing_key", f"{key_path}: {exc.strerror}") from None
    except (ValueError, TypeError, UnsupportedAlgorithm) as exc:
        raise sec.fail("signing_key", f"{key_path}: not a PEM private key ({exc})") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise sec.fail("signing_key", f"{key_path}: not an Ed25519 key")
    roster_path = base / sec.string("roster")
    label = str(roster_path)
    doc = FieldReader(label, parse_toml(read_file(roster_path, "roster"), label), "")
    doc.check_keys({"fleet", "robots"})
    robots = doc.table("robots")
    keys = {}
    for r in roster:
        if not robots.has(r):
            raise sec.fail("roster", f"{roster_path} has no signing key for {r}")
        entry = robots.table(r)
        entry.check_keys({"signing_key"})
        try:
            raw = base64.b64decode(entry.string("signing_key"), validate=True)
            keys[r] = Ed25519PublicKey.from_public_bytes(raw)
        except ValueError:
            raise entry.fail("signing_key", "not a base64 Ed25519 public key") from None
        if not admitted(raw):  # it would verify nothing (protocol/signing.py), or anything
            why = "of small order, outside the prime-order subgroup or not canonically encoded"
            raise entry.fail("signing_key", f"not a usable Ed25519 public key: a point {why}")
    if keys[robot].public_bytes_raw() != key.public_key().public_bytes_raw():
        raise sec.fail("signing_key", f"not the key {roster_path} holds for {robot}")
    return Signing(key, keys)


def _pose_window(a: FieldReader, classes: str) -> int | None:
    """``[agent] pose_window``: a number of steps, or "all" to keep every pose; by default
    ``POSE_WINDOW`` with per-object classes, every pose with joint ones (which need it)."""
    if not a.has("pose_window"):
        return POSE_WINDOW if classes == "per_object" else None
    value = a.raw["pose_window"]
    if isinstance(value, str):
        if value != "all":
            raise a.fail("pose_window", f'{value!r}: a number of steps ≥ 1, or "all"')
        return None
    window = a.integer("pose_window", 1, 1_000_000)
    if classes != "per_object":
        raise a.fail("pose_window", 'needs classes = "per_object" (one continuous belief)')
    return window


def _read_agent_config(path: Path, robot: str) -> AgentConfig:
    label = str(path)
    top = FieldReader(label, parse_toml(read_file(path, "agent config"), label), "")
    top.check_keys({"agent", "zenoh", "security", "ros2"})
    a = top.table("agent") if top.has("agent") else FieldReader(label, {}, "agent")
    z = top.table("zenoh") if top.has("zenoh") else FieldReader(label, {}, "zenoh")
    a.check_keys(_AGENT_KEYS)
    z.check_keys(_ZENOH_KEYS)
    base = path.parent
    model_path = base / a.string("model")
    try:
        model = load_robot_model(model_path)
    except ScenarioError as exc:
        raise a.fail("model", str(exc)) from None
    extent = a.number("world_extent", positive=True) if a.has("world_extent") else None
    if extent is not None and not 1.0 <= extent <= MAX_EXTENT:
        raise a.fail("world_extent", f"must be in 1..{MAX_EXTENT:g} m")
    limits = Limits(num_classes=model.num_classes, world_extent=extent or Limits().world_extent)
    x, y, theta = a.vector("start", 3)
    if max(abs(x), abs(y)) > limits.world_extent or abs(theta) > 2 * math.pi:
        reason = f"|x|, |y| ≤ world_extent {limits.world_extent:g} m and |theta| ≤ 2π"
        raise a.fail("start", reason)
    roster_field = a.array("roster")
    roster = [roster_field.string(i) for i in range(len(roster_field.raw))]
    if not all(valid_id(r) for r in roster) or len(set(roster)) != len(roster):
        raise a.fail("roster", "expected distinct robot ids")
    if robot not in roster:
        raise a.fail("roster", f"does not list this robot ({robot})")
    fleet = a.string("fleet") if a.has("fleet") else "default"
    if not valid_id(fleet):
        raise a.fail("fleet", f"invalid fleet name {fleet!r}")
    mode = a.string("mode") if a.has("mode") else "realtime"
    if mode not in MODES:
        raise a.fail("mode", f"{mode!r} (known: {', '.join(MODES)})")
    period = a.number("gossip_period") if a.has("gossip_period") else GOSSIP_PERIOD_S
    if not 0.01 <= period <= 3600:
        raise a.fail("gossip_period", "must be in 0.01..3600 s")
    stack_gossip = a.string("stack_gossip") if a.has("stack_gossip") else "ask"
    if stack_gossip not in STACK_GOSSIP:
        raise a.fail("stack_gossip", f"{stack_gossip!r} (known: {', '.join(STACK_GOSSIP)})")
    relay = a.string("relay") if a.has("relay") else "event"
    if relay not in RELAYS:
        raise a.fail("relay", f"{relay!r} (known: {', '.join(RELAYS)})")
    classes = a.string("classes") if a.has("classes") else DEFAULT_CLASSES
    if classes not in CLASS_KINDS:
        raise a.fail("classes", f"{classes!r} (known: {', '.join(CLASS_KINDS)})")
    pose_window = _pose_window(a, classes)
    associate_on = a.string("associate_on") if a.has("associate_on") else ASSOCIATE_ON[0]
    if associate_on not in ASSOCIATE_ON:
        raise a.fail("associate_on", f"{associate_on!r} (known: {', '.join(ASSOCIATE_ON)})")
    xi_parents = XI_PARENTS
    if a.has("xi_parents"):
        xi_parents = a.integer("xi_parents", 0, MAX_XI_PARENTS)
        if classes != "per_object":
            raise a.fail("xi_parents", 'shapes a sparse ξ: needs classes = "per_object"')
    runtime = CoreSettings(
        mode=mode,
        stack_gossip=stack_gossip,
        relay=relay,
        gossip_period=period,
        window=a.integer("window", 1, 100_000) if a.has("window") else WINDOW_STEPS,
        publish_local=a.boolean("publish_local") if a.has("publish_local") else True,
        simulation=a.boolean("simulation") if a.has("simulation") else False,
        catch_up=a.integer("catch_up", 0, 1000) if a.has("catch_up") else CATCH_UP_STEPS,
        listen_in_range=(a.boolean("listen_in_range") if a.has("listen_in_range") else True),
    )
    endpoints = {}
    for name in ("listen", "connect"):
        field = z.array(name) if z.has(name) else FieldReader(label, [], f"zenoh.{name}")
        values = [field.string(i) for i in range(len(field.raw))]
        for e in values:
            if "/" not in e:
                raise z.fail(name, f"bad endpoint {e!r} (e.g. tcp/127.0.0.1:7447)")
        endpoints[name] = tuple(values)
    mode = z.string("mode") if z.has("mode") else "peer"
    if mode not in ZENOH_MODES:
        raise z.fail("mode", f"{mode!r} (known: {', '.join(ZENOH_MODES)})")
    if mode == "client" and (endpoints["listen"] or not endpoints["connect"]):
        raise z.fail("mode", "a client listens on nothing and connects to its router (connect)")
    zenoh_settings = ZenohSettings(
        mode=mode,
        listen=endpoints["listen"],
        connect=endpoints["connect"],
        gossip=z.boolean("gossip") if z.has("gossip") else None,
        shared_memory=z.boolean("shared_memory") if z.has("shared_memory") else None,
        lease_ms=z.integer("lease_ms", 100, 3_600_000) if z.has("lease_ms") else None,
        config_file=base / z.string("config_file") if z.has("config_file") else None,
    )
    insecure = z.boolean("insecure") if z.has("insecure") else False
    _check_security(z, zenoh_settings, insecure)
    signing = None
    if top.has("security"):
        signing = _read_signing(top.table("security"), base, robot, roster)
    ros2 = None
    if top.has("ros2"):
        ros2 = read_ros2(top.table("ros2"), robot, model.num_classes, insecure)
    return AgentConfig(
        ros2=ros2,
        signing=signing,
        robot=robot,
        fleet=fleet,
        model_path=model_path,
        model=model,
        start=(x, y, theta),
        roster=frozenset(roster),
        seed=a.integer("seed", 0, 2**63 - 1) if a.has("seed") else 0,
        runtime=runtime,
        journal=base / a.string("journal") if a.has("journal") else None,
        zenoh=zenoh_settings,
        limits=limits,
        classes=classes,
        pose_window=pose_window,
        keep_slots=a.integer("keep_slots", 2, limits.max_slots) if a.has("keep_slots") else None,
        associate_on=associate_on,
        xi_parents=xi_parents,
    )
