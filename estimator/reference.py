"""An independent reference for the class posterior: per-realisation Laplace evidence of the whole
batch problem, optimised with Levenberg–Marquardt (design doc §3's check).

For every class realisation C of the observed objects the full factor graph (start priors,
odometry, object priors, geometric and semantic factors under C) is optimised in batch and its
evidence approximated by Laplace's method, ``log Z_C = −E(θ*) − ½ log det Λ(θ*) + const``. It
shares nothing with the incremental belief but the factor definitions, so agreement between the
two checks the branching, the weight integral and the bookkeeping of the hybrid belief. Its cost is
M^n batch solves: tiny problems only.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.factors import diagonal_noise, object_key, pose_key, semantic_factor
from estimator.hybrid import BeliefConfig, BeliefModel
from estimator.models import SensorFrame, viewpoint

Array = NDArray[np.float64]

MAX_REALISATIONS = 4096


def laplace_class_posterior(
    model: BeliefModel,
    starts: Mapping[str, ArrayLike],
    steps: Sequence[Sequence[SensorFrame]],
    config: BeliefConfig | None = None,
) -> tuple[list[int], dict[tuple[int, ...], float]]:
    """Posterior probability of every class realisation of the objects seen in ``steps``.

    ``steps[k − 1]`` holds the frames of step k (one per robot at most). Object priors are centred
    on the first measurement composed with the dead-reckoned pose, as the belief does at first
    sight. Returns (object ids in order of first sighting, realisation → probability).
    """
    cfg = config or BeliefConfig()
    robots = list(starts)
    slot = {r: i for i, r in enumerate(robots)}
    graph = gtsam.NonlinearFactorGraph()
    init = gtsam.Values()
    start_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array(cfg.start_prior_sigmas))
    prior_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array(cfg.object_prior_sigmas))
    odo_noise = diagonal_noise(model.odometry_noise)
    geo_noise = diagonal_noise(model.geometric_noise)
    dead: dict[str, gtsam.Pose2] = {}
    for r, s in starts.items():
        dead[r] = gtsam.Pose2(*np.asarray(s, dtype=float))
        graph.add(gtsam.PriorFactorPose2(pose_key(slot[r], 0), dead[r], start_noise))
        init.insert(pose_key(slot[r], 0), dead[r])
    objects: list[int] = []
    sightings = []
    for frames in steps:
        for f in frames:
            u = gtsam.Pose2(*f.odometry)
            prev, cur = pose_key(slot[f.robot], f.k - 1), pose_key(slot[f.robot], f.k)
            graph.add(gtsam.BetweenFactorPose2(prev, cur, u, odo_noise))
            dead[f.robot] = dead[f.robot].compose(u)
            init.insert(cur, dead[f.robot])
            for d in f.detections:
                oj = object_key(d.object_id)
                if d.object_id not in objects:
                    objects.append(d.object_id)
                    o = dead[f.robot].compose(gtsam.Pose2(*d.z_geo))
                    graph.add(gtsam.PriorFactorPose2(oj, o, prior_noise))
                    init.insert(oj, o)
                graph.add(gtsam.BetweenFactorPose2(cur, oj, gtsam.Pose2(*d.z_geo), geo_noise))
                sightings.append((cur, oj, d.object_id, np.asarray(d.z_sem, dtype=float)))
    m = model.num_classes
    if m ** len(objects) > MAX_REALISATIONS:
        raise ValueError(f"{m}^{len(objects)} realisations: too many for the batch reference")
    index = {j: i for i, j in enumerate(objects)}
    log_post: dict[tuple[int, ...], float] = {}
    for classes in itertools.product(range(m), repeat=len(objects)):
        g = gtsam.NonlinearFactorGraph(graph)
        for xk, oj, j, z in sightings:
            x, o = init.atPose2(xk), init.atPose2(oj)
            psi0 = float(viewpoint([x.x(), x.y(), x.theta()], [o.x(), o.y(), o.theta()]))
            g.add(semantic_factor(model.classifier, classes[index[j]], z, xk, oj, psi0))
        params = gtsam.LevenbergMarquardtParams()
        params.setRelativeErrorTol(1e-12)
        params.setAbsoluteErrorTol(1e-12)
        params.setMaxIterations(200)
        opt = gtsam.LevenbergMarquardtOptimizer(g, init, params).optimize()
        info, _ = g.linearize(opt).hessian()
        _, log_det = np.linalg.slogdet(info)
        log_prior = sum(np.log(model.class_prior[c]) for c in classes)
        log_post[classes] = float(log_prior - g.error(opt) - 0.5 * log_det)
    top = max(log_post.values())
    weights = {c: np.exp(v - top) for c, v in log_post.items()}
    total = sum(weights.values())
    return objects, {c: float(w / total) for c, w in weights.items()}
