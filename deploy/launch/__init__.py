"""`semfleet launch` and `semfleet chaos`: one conductor and one agent process per robot, on
loopback Zenoh (or, for ``chaos --net netns``, on a bridge between network namespaces).

- :mod:`deploy.launch.run` — the plan, the launcher that runs it and :func:`launch`;
- :mod:`deploy.launch.supervisor` — ports, agent configs, agent processes, shutdown on signals;
- :mod:`deploy.launch.conductor` — the simulated world: truth-less frames, lock-step orders,
  simulated links, the estimates that come back;
- :mod:`deploy.launch.scoring` — those estimates against ground truth, in the study's metrics;
- :mod:`deploy.launch.chaos` — faults (loss, partitions, kills, restarts) and garbage stacks;
- :mod:`deploy.launch.netns` (with :mod:`deploy.launch.netns_records`) — ``--net netns``: one
  network namespace per agent on a bridge, and its removal whatever ends the run;
- :mod:`deploy.launch.packet_faults` — link verdicts as nftables rules on real packets;
- :mod:`deploy.launch.table` — the live table.
"""

from deploy.launch.chaos import Faults, garbage_stack
from deploy.launch.errors import LaunchError, PlanError
from deploy.launch.run import LAUNCH_METHODS, Launcher, LaunchOutcome, LaunchPlan, launch
from deploy.launch.supervisor import AgentProcess, Stopped, free_ports, write_agent_config

__all__ = [
    "LAUNCH_METHODS",
    "AgentProcess",
    "Faults",
    "LaunchError",
    "LaunchOutcome",
    "LaunchPlan",
    "Launcher",
    "PlanError",
    "Stopped",
    "free_ports",
    "garbage_stack",
    "launch",
    "write_agent_config",
]
