"""Fleet runs in a campaign (python -m sitl campaign run --mode fleet): two fleets at once on one
host, each on instance offsets of its own lease (sitl.fleet.lease), both finished."""

import csv
import json
import subprocess
import sys

import pytest

from ..paths import ROOT

# two fleets at once on 2 cores: 15 s; the leases themselves are tests/unit/test_fleet_lease.py's
pytestmark = pytest.mark.slow


def test_two_fleets_at_once_fly_on_ports_of_their_own(tmp_path):
    out = tmp_path / "fleets"
    cmd = [sys.executable, "-m", "sitl", "campaign", "run", "--config", "configs/sitl/chain/three_link.toml",
           "--seeds", "0-1", "--duration", "8", "--mode", "fleet", "--workers", "2", "--quiet", "--out", str(out)]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    rows = list(csv.DictReader(open(out / "results.csv")))
    assert [(r["mode"], r["seed"], r["status"]) for r in rows] == [("fleet", "0", "ok"), ("fleet", "1", "ok")]
    assert all(r["took_off"] == "true" and r["crashed"] == "false" for r in rows)
    wires = [next(iter(json.loads((out / "three_link-fleet" / "base" / f"seed-{s}" / "link1" / "link1_ports.json")
                                  .read_text()))) for s in (0, 1)]
    assert wires[0] != wires[1]  # link 1 of each fleet on its own companion port
    # what the fleets printed (their port tables) is in their folders, not on the campaign's console
    assert "QGroundControl" in (out / "three_link-fleet" / "base" / "seed-0" / "console.txt").read_text()
    assert "QGroundControl" not in res.stdout
