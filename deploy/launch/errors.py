"""The launch's own errors: a plan that cannot run (the user's mistake) and a run that failed."""

from __future__ import annotations

from deploy.base.errors import UsageError


class PlanError(UsageError):
    """A launch plan that cannot run as asked: unknown or repeated robots, steps outside the
    scenario, faults outside the run or a restart without a kill before it. Raised before any
    process starts."""


class LaunchError(RuntimeError):
    """The launch failed: an agent died, did not start, or the run stalled."""
