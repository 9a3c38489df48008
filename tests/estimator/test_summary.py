"""A slot's realisations as columns (``estimator.summary.Realisations``, what the codec decodes
into) behave as the tuple of ``Realisation`` they stand for: indexing, slicing, iteration, the
class matrix, log φ and the distinct ξ — and the fusion takes either form to the same belief."""

from __future__ import annotations

import numpy as np
import pytest

from deploy.base.build import belief_model, belief_rng
from deploy.study.fleet import make_nodes
from estimator.hybrid import BeliefConfig
from estimator.summary import LocalSummary, Realisation, Realisations, Slot, Xi
from sim.loader import load_scenario
from sim.sensors import Simulator


def _xis(rng: np.random.Generator, count: int, n: int) -> list[Xi]:
    return [
        Xi(rng.standard_normal((n, 3)), np.eye(3 * n) * (1 + i), rng.standard_normal(3 * n))
        for i in range(count)
    ]


@pytest.mark.parametrize("seed", range(5))
def test_columns_give_the_realisations_they_hold(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, r = int(rng.integers(0, 6)), int(rng.integers(1, 30))
    xis = _xis(rng, 4, n)
    xis.append(xis[1])  # one ξ held twice: it is one ξ
    classes = rng.integers(0, 5, (r, n)).astype(np.uint8)
    log_phi = rng.standard_normal(r)
    index = rng.integers(0, len(xis), r)
    cols = Realisations(classes, log_phi, xis, index)
    rows = tuple(
        Realisation(tuple(int(c) for c in classes[i]), float(log_phi[i]), xis[int(index[i])])
        for i in range(r)
    )
    assert len(cols) == r
    for got, want in zip(cols, rows, strict=True):
        assert got.classes == want.classes and type(got.classes[0] if n else 0) is int
        assert got.log_phi == want.log_phi and got.xi is want.xi
    assert cols[-1].xi is rows[-1].xi and cols[r - 1].log_phi == rows[-1].log_phi
    assert [x.log_phi for x in cols[1::2]] == [x.log_phi for x in rows[1::2]]
    with pytest.raises(IndexError):
        cols[r]
    a, b = LocalSummary(tuple(range(n)), cols), LocalSummary(tuple(range(n)), rows)
    np.testing.assert_array_equal(a.class_matrix(), b.class_matrix())
    assert a.class_matrix().dtype == b.class_matrix().dtype == np.int64
    np.testing.assert_array_equal(a.log_phis(), b.log_phis())
    (xa, wa), (xb, wb) = a.distinct_xi(), b.distinct_xi()
    assert wa == wb and len(xa) == len(xb) and all(x is y for x, y in zip(xa, xb, strict=True))


def test_columns_of_the_wrong_shapes_are_refused() -> None:
    xis = _xis(np.random.default_rng(0), 1, 2)
    with pytest.raises(ValueError, match="columns"):
        Realisations(np.zeros(3, np.uint8), np.zeros(3), xis, np.zeros(3, np.intp))
    with pytest.raises(ValueError, match="columns"):
        Realisations(np.zeros((3, 2), np.uint8), np.zeros(2), xis, np.zeros(3, np.intp))


def test_the_fusion_takes_a_slot_as_columns_to_the_very_belief_it_takes_as_tuples() -> None:
    """Two robots of the paper world, r2's slots fused into r1's D at every step, once as the
    tuples the estimator makes and once as the columns a decoder makes: bit-identical D."""
    s = load_scenario("paper")
    frames = Simulator(s, 4).all_frames()
    model = belief_model(s)
    twins = [
        make_nodes(s, model, BeliefConfig.joint(), lambda r: belief_rng(4, [r])) for _ in range(2)
    ]
    for k in range(25):
        for nodes, as_columns in zip(twins, (False, True), strict=True):
            nodes["r2"].on_frame(frames["r2"][k])
            summary = nodes["r2"].track.summary()
            if summary is not None:
                if as_columns:
                    xis, which = summary.distinct_xi()
                    cols = Realisations(
                        summary.class_matrix().astype(np.uint8),
                        summary.log_phis(),
                        xis,
                        np.array(which, dtype=np.intp),
                    )
                    summary = LocalSummary(summary.object_ids, cols)
                nodes["r1"].distributed.integrate([Slot("r2", k + 1, summary)])
            nodes["r1"].on_frame(frames["r1"][k])
    a, b = (nodes["r1"].distributed.snapshot("r1") for nodes in twins)
    assert a.object_ids == b.object_ids and len(a.object_ids) > 0
    for name in ("weights", "classes", "robot_pose", "object_pose", "object_cov"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
