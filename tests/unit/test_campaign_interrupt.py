"""A fleet run of a campaign stopped by Ctrl-C or SIGTERM stops the campaign and is not recorded
as finished (sitl.campaign.runs.fly_spec): a serial campaign used to take the interrupted flight
for a finished one and fly on to the next."""

from __future__ import annotations

from contextlib import contextmanager
from types import SimpleNamespace

import pytest

import sitl.campaign.runs as runs
import sitl.fleet.lease as lease
from sitl.campaign.grid import RunSpec


@pytest.mark.parametrize("interrupted", [False, True])
def test_an_interrupted_fleet_run_stops_the_campaign(tmp_path, monkeypatch, interrupted):
    metrics = {"interrupted": interrupted, "crashed": False}
    kind = SimpleNamespace(launch=lambda *a, **k: metrics)
    monkeypatch.setattr(runs, "load_spec", lambda spec: (kind, SimpleNamespace(cameras=())))

    @contextmanager
    def offset(sc, gcs_port):
        yield 0

    monkeypatch.setattr(lease, "lease_instance_offset", offset)
    spec = RunSpec("configs/sitl/chain/three_link.toml", (), 1, "fleet", 10.0)
    if interrupted:
        with pytest.raises(KeyboardInterrupt):
            runs.fly_spec(tmp_path, spec)
    else:
        assert runs.fly_spec(tmp_path, spec) is metrics
