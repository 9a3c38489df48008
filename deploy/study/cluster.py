"""Seeded runs as tasks of an existing Dask cluster (``semfleet study --cluster ADDRESS``), with
the contract of :func:`deploy.study.runner.run_seeded`: the same calls, results in the order of the
calls, the first failure cancels the rest.

Dask is an optional extra (``pip install 'semfleet[cluster]'``), imported only here and only
when a study asks for a cluster. Every worker must have semfleet installed (the calls are
pickled by reference to ``deploy.study.runner``); a run's numbers depend on its seed only, so a seed
gives the same results on a cluster as in a local process.
"""

from __future__ import annotations

import importlib
import uuid
from collections.abc import Callable
from types import ModuleType
from typing import Any

from deploy.base.errors import RunFailure, UsageError
from deploy.study.types import StudyError

# How long to wait for the scheduler to answer before giving up on it.
CONNECT_TIMEOUT_S = 10
EXTRA = "pip install 'semfleet[cluster]'"


def distributed_module() -> ModuleType:
    """``dask.distributed``, or a usage error naming the extra that installs it."""
    try:
        return importlib.import_module("distributed")
    except ImportError:
        raise UsageError(f"--cluster needs Dask's distributed scheduler: {EXTRA}") from None


def run_on_cluster(
    calls: dict[int, tuple[Any, ...]], address: str, advance: Callable[[], None] = lambda: None
) -> list[Any]:
    """``calls[seed] = (function, *args)``, each a task on the cluster whose scheduler is at
    ``address``; results in the order of ``calls``. A task whose worker died becomes a
    :class:`StudyError` naming its seed; an exception raised by a run is re-raised with a note
    naming the seed. ``advance()`` after every finished run."""
    distributed = distributed_module()
    try:
        client = distributed.Client(address, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise RunFailure(f"--cluster {address}: no Dask scheduler answered ({exc})") from None
    batch = uuid.uuid4().hex[:8]  # task keys of two studies on one cluster never collide
    done: dict[int, Any] = {}
    futures: dict[Any, int] = {}
    try:
        for seed, (function, *args) in calls.items():
            key = f"semfleet-{batch}-seed-{seed}"
            futures[client.submit(function, *args, key=key, pure=False)] = seed
        for future in distributed.as_completed(list(futures), loop=client.loop):
            seed = futures[future]
            try:
                done[seed] = future.result()
            except distributed.KilledWorker as exc:
                raise StudyError(f"run with seed {seed} failed: {exc}") from exc
            except Exception as exc:
                exc.add_note(f"in the run with seed {seed}")
                raise
            advance()
    finally:
        # A failed run, Ctrl-C or a stop signal: the cluster drops what is still queued.
        client.cancel(list(futures))
        client.close()
    return [done[s] for s in calls]
