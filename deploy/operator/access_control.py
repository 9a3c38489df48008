"""Zenoh access control of a secure fleet (docs/deploy.md, "Access control"): the rules every
member's session enforces on what its direct neighbours send it, by the certificate common name of
the link. Pure: a JSON-able document for the ``access_control`` section of a Zenoh config."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from agents.transport.base import Keys

DECLARATIONS = (
    "declare_subscriber",
    "declare_queryable",
    "declare_liveliness_subscriber",
    "liveliness_query",
    "query",
    "reply",
)


def access_control(
    fleet: str,
    robots: Sequence[str],
    operator: str,
    viewer: bool = False,
    simulator: bool = False,
    routers: Sequence[str] = (),
) -> dict[str, Any]:
    """Zenoh access control of every member (see the module docstring). ``viewer``: the
    operator's own session, which also takes every robot's estimates, stacks and tokens from
    whichever member it is linked to (a robot routes for a client operator, so they arrive over
    that robot's link); it never acts on them."""
    keys = Keys(fleet)
    prefix = keys.prefix
    rules: list[dict[str, Any]] = [
        _rule("declare", DECLARATIONS, ["ingress", "egress"], [f"{prefix}/**"]),
        _rule("own-puts", ("put", "delete"), ["egress"], [f"{prefix}/**"]),
        _rule("own-tokens", ("liveliness_token",), ["egress"], [f"{prefix}/**"]),
        _rule("operator", ("put",), ["ingress"], [f"{prefix}/ctl/**", f"{prefix}/sim/**"]),
    ]
    if simulator:
        rules[-1]["key_exprs"].append(f"{prefix}/frames/*")
    subjects: list[dict[str, Any]] = [
        {"id": "members", "cert_common_names": [*robots, operator, *routers]},
        {"id": f"cn-{operator}", "cert_common_names": [operator]},
    ]
    policies: list[dict[str, Any]] = [
        {"id": "members", "rules": ["declare", "own-puts", "own-tokens"], "subjects": ["members"]},
        {"id": "operator", "rules": ["operator"], "subjects": [f"cn-{operator}"]},
    ]
    if routers:
        rules.append(_rule("relay", ("put",), ["ingress"], [f"{prefix}/**"]))
        rules.append(_rule("relay-tokens", ("liveliness_token",), ["ingress"], [f"{prefix}/**"]))
        subjects.append({"id": "routers", "cert_common_names": list(routers)})
        policies.append(
            {"id": "routers", "rules": ["relay", "relay-tokens"], "subjects": ["routers"]}
        )
    if viewer:
        seen = [f"{prefix}/estimate/*", f"{prefix}/stack/*"]
        rules.append(_rule("view", ("put",), ["ingress"], seen))
        rules.append(
            _rule("view-tokens", ("liveliness_token",), ["ingress"], [f"{prefix}/alive/*"])
        )
        policies[0]["rules"] += ["view", "view-tokens"]
    for r in robots:
        own = [
            keys.stack(r),
            keys.stack_to(r, "*"),  # event-driven relay's pushes to the robots that asked
            keys.estimate(r),
            keys.frames(r),
            f"{prefix}/ctl/need/{r}",
        ]
        rules.append(_rule(f"puts-{r}", ("put",), ["ingress"], own))
        rules.append(_rule(f"token-{r}", ("liveliness_token",), ["ingress"], [keys.alive(r)]))
        subjects.append({"id": f"cn-{r}", "cert_common_names": [r]})
        policies.append({"id": r, "rules": [f"puts-{r}", f"token-{r}"], "subjects": [f"cn-{r}"]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def _rule(rid: str, messages: Sequence[str], flows: list[str], key_exprs: list[str]) -> dict:
    return {
        "id": rid,
        "messages": list(messages),
        "flows": flows,
        "permission": "allow",
        "key_exprs": key_exprs,
    }
