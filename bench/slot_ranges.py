"""The numbers real slots carry, to choose ``protocol.codec.Limits`` (docs/wire.md, "Limits").

Runs the in-process fleet on bundled worlds and seeds and, after every robot step, summarises L
(the slot that goes on the wire) and D (the fused belief) and records, over every realisation:
Λ's smallest and largest eigenvalue, its condition number λmax/λmin, |log φ|, max |x|, |y| and
|θ| of ``lin``, max |η|, ‖η‖₂/λmax (a lower bound on the mean's tangent offset ‖δ‖₂, which is what
the η bound limits) and ‖Λ⁻¹η‖₂ (that offset itself), and whether the default ``Limits`` refuse
any slot or need eigenvalues for one. A measurement, not a timing benchmark:
``python -m bench.slot_ranges [world:variant ...]`` prints one line per world and the overall range.
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Iterable

import numpy as np

from agents.node import RobotNode
from deploy.base.build import belief_model, belief_rng
from deploy.study.fleet import link_model_for, make_nodes, run_fleet
from estimator.hybrid import BeliefConfig
from estimator.slots import summarise
from estimator.summary import LocalSummary
from protocol import codec
from protocol.codec import Limits, numbers_problem
from sim.loader import load_scenario
from sim.sensors import Simulator

WORLDS = ("paper", "paper:experiment", "lanes:short", "rendezvous:short")
SEEDS = (1, 2, 3)
STEPS = 60
FIELDS = (
    *("lam_min", "lam_max", "cond", "log_phi", "xy", "theta", "eta", "eta_over_lam", "delta"),
    *("refused", "eigvalsh"),
)


def slot_figures(summary: LocalSummary) -> dict[str, float]:
    """The largest (or, for ``lam_min``, smallest) value of every figure over the realisations
    (of a per-object summary: its one ξ, and ``log_phi`` over every object's class log φ);
    ``refused`` and ``eigvalsh`` are 1 when the default ``Limits`` refuse the slot, or need
    eigenvalues to decide (the Cholesky certificate of ``protocol.codec`` cannot)."""
    xis, which = summary.distinct_xi()
    info = np.stack([x.info for x in xis])
    eta = np.stack([x.eta for x in xis])
    lin = np.stack([x.lin for x in xis])
    if summary.per_object is not None:  # what the codec checks of a per-object slot
        phi = np.asarray(summary.per_object.log_phi, dtype=float)
        xi = xis[0]
        problem = codec.class_phi_problem("slot", phi, Limits()) or codec.object_xi_problem(
            "slot", xi.lin, xi.info, xi.eta, Limits()
        )
        refused = problem is not None
    else:
        rows = np.array([which.index(x) for x in range(len(xis))])
        phi = summary.log_phis()
        refused = numbers_problem("slot", phi, lin, info, eta, Limits(), rows) is not None
    lam = np.linalg.eigvalsh(info)
    delta = np.linalg.solve(info, eta[..., None])[..., 0]
    return {
        "lam_min": float(lam[:, 0].min()),
        "lam_max": float(lam[:, -1].max()),
        "cond": float((lam[:, -1] / lam[:, 0]).max()),
        "log_phi": float(np.abs(phi).max()) if phi.size else 0.0,
        "xy": float(np.abs(lin[..., :2]).max()),
        "theta": float(np.abs(lin[..., 2]).max()),
        "eta": float(np.abs(eta).max()),
        "eta_over_lam": float((np.linalg.norm(eta, axis=1) / lam[:, -1]).max()),
        "delta": float(np.linalg.norm(delta, axis=1).max()),
        "refused": float(refused),
        "eigvalsh": float(not codec._certified(info, eta, Limits())),
    }


def _fold(acc: dict[str, float], fig: dict[str, float]) -> None:
    for name, value in fig.items():
        pick = min if name == "lam_min" else max
        acc[name] = pick(acc.get(name, value), value)


def _rng(seed: int, robot: str) -> np.random.Generator:
    return belief_rng(seed, [robot])


def measure(world: str, seeds: Iterable[int], steps: int) -> dict[str, dict[str, float]]:
    """Figures of L's and D's summaries over every robot step of ``world`` under ``seeds``."""
    out: dict[str, dict[str, float]] = {"L": {}, "D": {}}
    for seed in seeds:
        scenario = load_scenario(world)
        frames = Simulator(scenario, seed).all_frames()
        model = belief_model(scenario)
        nodes = make_nodes(scenario, model, BeliefConfig(), functools.partial(_rng, seed))

        def on_step(robot: str, k: int, node: RobotNode, fused: float, ms: float) -> None:
            for name, belief in (("L", node.local), ("D", node.distributed)):
                summary = summarise(belief)
                if summary is not None:
                    _fold(out[name], slot_figures(summary))

        run_fleet(nodes, frames, link_model_for(scenario), min(steps, scenario.steps), on_step)
    return out


def _line(label: str, fig: dict[str, float]) -> str:
    return f"{label:28s} " + " ".join(f"{name}={fig[name]:.3g}" for name in FIELDS)


def main(worlds: Iterable[str]) -> None:
    total: dict[str, dict[str, float]] = {"L": {}, "D": {}}
    for world in worlds:
        got = measure(world, SEEDS, STEPS)
        for name in ("L", "D"):
            print(_line(f"{world} {name}", got[name]))
            _fold(total[name], got[name])
    for name in ("L", "D"):
        print(_line(f"all {name}", total[name]))


if __name__ == "__main__":
    main(sys.argv[1:] or WORLDS)
