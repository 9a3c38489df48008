"""Zenoh's errors in the user's terms: what ``ZenohTransport`` raises when a session cannot
open.

Zenoh's Rust errors end every cause with where it was raised in Zenoh's own build
(``… at /root/.cargo/git/checkouts/zenoh-…/tcp.rs:61.``): a path from inside a dependency tells
a user nothing and changes with every build, so it is cut. A listen endpoint whose port is taken
is named, with what to do about it.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

# " at /any/path/file.rs:61." (and Windows' "C:\...\file.rs:61"), the sentence's dot kept aside.
_RUST_LOCATION = re.compile(r"\s+at\s+(?:[A-Za-z]:)?[^\s]*\.rs:\d+(?::\d+)?\.?")
_IN_USE = ("Address already in use", "os error 98", "os error 48")


def without_build_paths(text: str) -> str:
    """``text`` without Zenoh's source locations, white space folded."""
    return " ".join(_RUST_LOCATION.sub("", text).split())


def locator(endpoint: str) -> str:
    """``host:port`` of an endpoint such as ``tls/127.0.0.1:7447?rel=1#iface=eth0``."""
    return endpoint.split("/", 1)[-1].split("#", 1)[0].split("?", 1)[0]


def open_error(text: str, listen: Sequence[str], connect: Sequence[str]) -> str:
    """The sentence for a session that did not open with Zenoh's error ``text``: the listen
    endpoint that is taken when that is the cause, else the endpoints and Zenoh's reason."""
    reason = without_build_paths(text)
    if any(marker in reason for marker in _IN_USE):
        taken = [e for e in listen if locator(e) in reason] or list(listen)
        if taken:
            return (
                f"cannot listen on {', '.join(taken)}: the address is in use (another process "
                "listens there: stop it, or give this session another port)"
            )
    where = [f"listening on {', '.join(listen)}"] if listen else []
    where += [f"dialling {', '.join(connect)}"] if connect else []
    return f"Zenoh session ({'; '.join(where) or 'no endpoint'}): {reason}"
