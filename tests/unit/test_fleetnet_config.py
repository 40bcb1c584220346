"""The Zenoh layer's configuration, without a session: errors name the key, the leader order, and
the files it reads (access control, TLS, users) are checked when the bus opens."""

from __future__ import annotations

import os
from dataclasses import replace

import pytest

from companion.configfile import ConfigError, build
from companion.fleetnet.bus import FleetBus, zenoh_config
from companion.fleetnet.config import ZenohConfig
from sitl.scenario import Scenario


# -- config ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("zenoh_section, key, reason", [
    ({"prefix": "fleet/*"}, "zenoh.prefix", "wildcards"),
    ({"endpoints": ["tcp/10.0.0.1:7447", "tcp/10.0.0.2"]}, "zenoh.endpoints", "not a Zenoh endpoint"),
    ({"endpoints": ["tcp/10.0.0.1:7447"] * 3}, "zenoh.endpoints", "its own endpoint"),
    ({"endpoints": ["tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"]}, "zenoh", "2 endpoints for 3 groups"),
    ({"leader_order": [2, 2, 1]}, "zenoh", "leader_order"),
    ({"shift_deadline_ms": 60.0}, "zenoh", "step period"),
    ({"mode": "client"}, "zenoh.connect", "router"),
    ({"tls": {"root_ca_certificate": "/etc/ca.pem"}, "endpoints": ["tls/a:1", "tls/b:1", "tls/c:1"],
      "leaderorder": [1, 2, 3]}, "zenoh.leaderorder", "unknown key"),
    ({"endpoints": ["tls/a:1", "tls/b:1", "tls/c:1"]}, "zenoh.endpoints", r"need \[zenoh.tls\]"),
])
def test_zenoh_config_errors_name_the_key(zenoh_section, key, reason):
    data = {"name": "t", "skeleton": {"n_links": 7}, "companion": {"groups": [[1, 2], [3, 4, 5], [6, 7]]},
            "zenoh": zenoh_section}
    with pytest.raises(ConfigError, match=reason) as err:
        build(Scenario, data, file="t.toml")
    assert f"t.toml: {key}" in str(err.value)


def test_access_control_file_is_read_and_checked_at_open(tmp_path):
    missing = ZenohConfig(endpoints=("tcp/127.0.0.1:1", "tcp/127.0.0.1:2"), access_control=str(tmp_path / "acl.json5"))
    with pytest.raises(ConfigError, match="zenoh.access_control: cannot read"):
        FleetBus(missing, "t", 0, 2)
    bad = tmp_path / "bad.json5"
    bad.write_text("{ enabled: true, rules: [ }")
    with pytest.raises(ConfigError, match="zenoh.access_control: Zenoh rejected access_control"):
        FleetBus(replace(missing, access_control=str(bad)), "t", 0, 2)
    good = tmp_path / "acl.json5"
    good.write_text('{ enabled: false, default_permission: "deny" }')
    zc = zenoh_config(replace(missing, access_control=str(good)), 0, 2)
    assert '"deny"' in zc.get_json("access_control/default_permission")


def test_default_leader_order_is_middle_out_and_tls_files_are_checked_at_open(tmp_path):
    assert ZenohConfig().order(3) == (1, 0, 2)
    assert ZenohConfig().order(4) == (1, 2, 0, 3)
    assert ZenohConfig(leader_order=(3, 1, 2)).order(3) == (2, 0, 1)
    cfg = ZenohConfig(endpoints=("tls/127.0.0.1:1", "tls/127.0.0.1:2"),
                      tls=build(type(ZenohConfig().tls), {"root_ca_certificate": str(tmp_path / "missing.pem")}, file="x"))
    with pytest.raises(ConfigError, match="zenoh.tls.root_ca_certificate: no such file"):
        FleetBus(cfg, "t", 0, 2)


def test_a_users_file_others_can_read_or_without_the_group_is_refused(tmp_path):
    from companion.fleetnet.config import new_users_file

    users = tmp_path / "u.txt"
    new_users_file(users, 2)
    cfg = ZenohConfig(users_file=str(users))
    with pytest.raises(ConfigError, match="no user companion-g3"):
        zenoh_config(cfg, 2, 3)
    os.chmod(users, 0o644)
    with pytest.raises(ConfigError, match="readable by others"):
        zenoh_config(cfg, 0, 2)
