"""Cases shared by the tests of the Zenoh layer (tests/unit/test_fleetnet*.py and
tests/integration/test_fleetnet_zenoh.py): chain layouts, eq. 6's boundaries of a chain, CPG
targets, and message equality."""

from __future__ import annotations

import numpy as np

from companion.estimation.semi import semi_distributed_apply
from companion.load.model import LoadObservation
from companion.messages import ChainTargets, GroupBoundaryReport, NeighbourPose

from .chains import perturbed_chain

PERIOD_US = 50_000
LAYOUTS = [((0, 1), (2, 3, 4), (5, 6)), ((0, 1), (2, 3)), ((0,), (1, 2), (3,), (4, 5, 6, 7))]


def targets(rng, links, time_us=12_340_000, seq=7) -> ChainTargets:
    k = len(links)
    q = rng.normal(size=(k, 4))
    return ChainTargets(1, time_us, seq, tuple(links), rng.normal(size=(k, 3)), q / np.linalg.norm(q, axis=1, keepdims=True),
                        *(rng.normal(size=(k, 3)) for _ in range(6)))


def neighbour_pose(rng, observer: int = 1, observed: int = 2, t_capture_s: float = 3.25) -> NeighbourPose:
    """A random neighbour pose (unit quaternions, a positive-definite covariance, mounts near the link)."""
    def unit():
        q = rng.normal(size=4)
        return q / np.linalg.norm(q)
    A = rng.normal(size=(6, 6))
    return NeighbourPose(observer, observed, t_capture_s, 42, unit(), rng.normal(0.0, 0.5, 3), A @ A.T + 1e-3 * np.eye(6),
                         rng.normal(0.0, 0.3, 3), unit(), rng.normal(0.0, 0.3, 3), unit())


def load_observation(rng, vehicle: int = 1, stamp_s: float = 2.5) -> LoadObservation:
    """A random load observation with the load's attitude (a unit quaternion, a positive-definite joint covariance)."""
    q = rng.normal(size=4)
    A = rng.normal(size=(6, 6))
    joint = A @ A.T + 1e-3 * np.eye(6)
    return LoadObservation(vehicle, stamp_s, rng.normal(0.0, 1.0, 3), joint[:3, :3], q / np.linalg.norm(q), joint)


def equal(a, b) -> bool:
    for name in a.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            if not np.array_equal(x, y):
                return False
        elif x != y:
            return False
    return True


def chain_boundaries(seed: int, groups):
    n = groups[-1][-1] + 1
    p, v, q, w, d, P = perturbed_chain(np.random.default_rng(seed), n)
    ref = semi_distributed_apply(p, v, q, w, d, P, groups)
    reports = [GroupBoundaryReport(g, PERIOD_US, b.left_tip, b.right_tip, b.info_pv) for g, b in enumerate(ref.boundaries)]
    return ref, reports
