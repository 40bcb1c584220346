"""Instance offsets leased per host (sitl.fleet.lease): fleets side by side never share a port."""

import fcntl
import itertools
from contextlib import ExitStack
from types import SimpleNamespace

import pytest

from sitl.fleet.lease import MAX_INSTANCES, lease_instance_offset


def _fleet(n):
    return SimpleNamespace(skeleton=SimpleNamespace(n_links=n))


def test_leases_side_by_side_take_disjoint_instances_clear_of_the_gcs_port(tmp_path):
    with ExitStack() as stack:
        offsets = [stack.enter_context(lease_instance_offset(_fleet(3), 14550, lock_dir=tmp_path)) for _ in range(4)]
        # 0-2, 3-5, 6-8; 9-11 would put a companion port (14540 + K + i) on the GCS port 14550
        assert offsets == [0, 3, 6, 11]
        assert stack.enter_context(lease_instance_offset(_fleet(2), 14550, lock_dir=tmp_path)) == 14
    with lease_instance_offset(_fleet(3), 14550, lock_dir=tmp_path) as k:
        assert k == 0  # released at the end of the block


def test_a_host_with_no_free_instances_waits_then_says_so(tmp_path):
    with ExitStack() as stack:
        for j in range(MAX_INSTANCES):
            f = stack.enter_context(open(tmp_path / f"aerial-skeleton-instance-{j}.lock", "w"))
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        ticks = itertools.count(0.0, 1.0)
        slept = []
        with pytest.raises(TimeoutError, match="no free instance offset for 3 links within 5 s"):
            with lease_instance_offset(_fleet(3), 14550, lock_dir=tmp_path, timeout_s=5.0,
                                       clock=lambda: next(ticks), sleep=slept.append):
                pass
        assert slept and all(s == 0.5 for s in slept)


def test_a_fleet_too_large_for_the_layout_is_refused(tmp_path):
    with pytest.raises(ValueError, match="no instance offset fits a fleet of 41 links"):
        with lease_instance_offset(_fleet(41), 14550, lock_dir=tmp_path):
            pass
