"""Fleet mode end to end with standard MAVLink software: a MAVSDK client on a link's onboard port
(parameters and telemetry), and stock-PX4 messages (ODOMETRY in and out, GPS time) between the
links and the companion.

Each test launches a real fleet on the ports of its own instance offset (the ``fleet_ports``
fixture, see test_fleet.py) and checks that every port is free again afterwards.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from dataclasses import replace

import pytest

from sitl.fleet.launcher import launch
from sitl.fleet.layout import check_instance_offset
from sitl.scenario import load_scenario

from ..ports import assert_ports_released, children_of
from ..waits import wait_for
from ..paths import ROOT, THREE_LINK


def test_mavsdk_client_discovers_reads_sets_parameters_and_gets_telemetry(tmp_path, fleet_ports):
    """MAVSDK in its own process on link 2's onboard port (the companion is not started): reads
    and sets an integer and a float parameter (bytewise, as the vehicle declares), is refused
    on the read-only MAV_SYS_ID and reads it back unchanged; gets the home and finds every
    health flag set (what MAVSDK's examples wait for before they arm)."""
    sc = load_scenario(THREE_LINK, duration_s=12.0)
    result = {}

    def fleet():
        result["metrics"] = launch(sc, tmp_path, speed=1.0, companion=False, **fleet_ports.launch_kwargs)

    runner = threading.Thread(target=fleet, daemon=True)
    runner.start()
    wait_for(lambda: len(children_of(os.getpid())) >= 3, 20.0, poll_s=0.1)
    # paced: the fleet keeps the default scheduling policy
    assert {os.sched_getscheduler(pid) for pid in children_of(os.getpid())} == {os.SCHED_OTHER}
    client = subprocess.run([sys.executable, str(ROOT / "tests" / "mavsdk_client.py"),
                             f"udpin://127.0.0.1:{fleet_ports.companion(1)}", "2",
                             "--timeout", "15", "--set-int", "SKL_SM_EN=0", "--set-int", "MAV_SYS_ID=7",
                             "--set-float", "SKL_CORR_HOLD=0.375"], capture_output=True, text=True, timeout=60)
    runner.join(60)
    assert not runner.is_alive()
    out = json.loads(client.stdout.strip().splitlines()[-1])
    assert client.returncode == 0 and out["discovered"] and out["sysid"] == 2, client.stderr[-2000:]
    assert out["IMP_KP_Z"] == pytest.approx(sc.firmware.gains.kp_n_m[2], rel=1e-6)
    assert out["MAV_SYS_ID"] == 2
    assert sc.firmware.allocation.selective_mapping  # so that setting 0 is a change
    assert out["set"]["SKL_SM_EN"] == {"result": "SUCCESS", "read_back": 0}
    assert out["set"]["SKL_CORR_HOLD"] == {"result": "SUCCESS", "read_back": pytest.approx(0.375)}
    assert out["set"]["MAV_SYS_ID"]["result"] != "SUCCESS" and out["set"]["MAV_SYS_ID"]["read_back"] == 2
    counts = out["telemetry_counts"]
    assert counts.get("position", 0) >= 5 and counts.get("attitude_euler", 0) >= 10
    lat, lon, _ = out["position"]
    assert lat == pytest.approx(sc.origin.lat_deg, abs=1e-3) and lon == pytest.approx(sc.origin.lon_deg, abs=1e-3)
    assert counts.get("home", 0) >= 1, out
    home_lat, home_lon, home_alt = out["home"]  # link 2 on the ground, where the first estimate put it
    assert home_lat == pytest.approx(lat, abs=1e-5) and home_lon == pytest.approx(lon, abs=1e-5)
    assert home_alt == pytest.approx(sc.origin.alt_m, abs=1.0)
    assert out["health_all_ok"] and all(out["health"].values()), out["health"]
    assert "metrics" in result  # the fleet ran to its end (the links stayed on the ground, unarmed)
    assert result["metrics"]["scheduling"] == "default"
    assert_ports_released(fleet_ports, 3)


def test_standard_messages_mode_corrects_through_odometry(tmp_path, fleet_ports):
    """Stock-PX4 mode: ODOMETRY in, corrections as external-vision ODOMETRY (MAV_FRAME_LOCAL_FRD),
    on GPS time. The fleet runs 11 PX4 instances up (``--instance-offset`` K + 11, K this test's
    slot): every port moves with it, the companion's too."""
    sc = load_scenario(THREE_LINK, duration_s=12.0)
    # as next to real Pixhawks: every link's clock mapped onto GPS time through SYSTEM_TIME
    sc = replace(sc, companion=replace(sc.companion, mode="standard", time_base="gps"))
    for bad in (-1, 8, 38):  # 14548-14550 would take the GCS port; 14578-14580 a vehicle's own
        with pytest.raises(ValueError, match="instance offset"):
            check_instance_offset(sc, bad)
    ports = fleet_ports.shifted(11)
    m = launch(sc, tmp_path, speed=0.0, **ports.launch_kwargs)
    assert not m["crashed"]
    assert m["constraint_pos_p95_m"]["after"] < 0.05 * m["constraint_pos_p95_m"]["before"]
    assert m["correction_latency_ms"]["samples"] > 100 and m["correction_latency_ms"]["p99"] <= 30.0
    comp = json.loads((tmp_path / "companion" / "companion_summary.json").read_text())
    assert comp["links"]["1"]["per_type"].get("ODOMETRY", 0) > 300
    assert "SKELETON_LINK_STATE" not in comp["links"]["1"]["per_type"]
    assert comp["links"]["1"]["per_type"].get("SYSTEM_TIME", 0) >= 10 and comp["withheld_steps"] == 0
    link1 = json.loads((tmp_path / "link1" / "link1_ports.json").read_text())
    onboard_url = f"udpout://127.0.0.1:{ports.companion(0)}?bind={ports.vehicle(0)}"
    assert {f"tcpin://127.0.0.1:{ports.sim(0)}", f"udpout://127.0.0.1:{ports.gcs_port}?bind={ports.gcs_from(0)}",
            onboard_url} < set(link1)
    onboard = link1[onboard_url]
    assert onboard["per_type"].get("ODOMETRY", 0) > 100 and "SKELETON_CORRECTION" not in onboard["per_type"]
