"""The fleet's TLS files (``python -m companion certs``) and mutual TLS between group companions:
the files and their modes, real Zenoh sessions on loopback (the fleet's own meet, a session without
a certificate or with another CA's cannot reach them), and the ``[zenoh.tls] certs_dir`` checks."""

from __future__ import annotations

import datetime
import ipaddress
import os
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID

from companion.__main__ import main
from companion.config import CompanionSetup, load_setup
from companion.configfile import ConfigError, build
from companion.fleetnet.bus import zenoh_config
from companion.fleetnet.certs import check_group_certificate, new_fleet_certs
from companion.fleetnet.config import ZenohConfig, ZenohTls

from ..ports import free_ports
from ..waits import wait_for
from ..zenoh_peers import peer_session
from ..paths import ROOT

FILES = ["ca.key", "ca.pem", "companion-g1.key", "companion-g1.pem", "companion-g2.key", "companion-g2.pem"]


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def _cert(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


# -- the command --------------------------------------------------------------------------------------------
def test_certs_writes_a_fleet_ca_and_a_certificate_per_group_with_private_keys(tmp_path, capsys):
    out = tmp_path / "certs"
    assert main(["certs", str(out), "--groups", "3", "--hosts", "127.0.0.1", "10.0.0.12,pi2.local", "localhost",
                 "--days", "30"]) == 0
    assert "companion-g2.pem / .key  for 10.0.0.12,pi2.local" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == sorted(FILES + ["companion-g3.key", "companion-g3.pem"])
    for p in out.iterdir():
        assert _mode(p) == (0o600 if p.suffix == ".key" else 0o644), p.name
    ca = _cert(out / "ca.pem")
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for g, names in enumerate([[ipaddress.ip_address("127.0.0.1")],
                               [ipaddress.ip_address("10.0.0.12"), "pi2.local"], ["localhost"]]):
        cert = _cert(out / f"companion-g{g + 1}.pem")
        cert.verify_directly_issued_by(ca)
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert [n.value for n in san] == names
        eku = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        assert set(eku) == {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH}  # server and client
        assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
        now = datetime.datetime.now(datetime.timezone.utc)
        assert abs((cert.not_valid_after_utc - now).total_seconds() / 86400 - 30) < 0.01
        assert cert.not_valid_before_utc < now - datetime.timedelta(hours=23)  # Pis without a real-time clock
    check_group_certificate(out / "companion-g2.pem", out / "ca.pem", "pi2.local")
    check_group_certificate(out / "companion-g2.pem", out / "ca.pem", "10.0.0.12")
    with pytest.raises(ValueError, match=r"made for 10.0.0.12, pi2.local, not 10.0.0.13"):
        check_group_certificate(out / "companion-g2.pem", out / "ca.pem", "10.0.0.13")


def test_certs_refuses_to_overwrite_and_bad_input(tmp_path):
    out = tmp_path / "certs"
    new_fleet_certs(out, 2)
    before = {name: (out / name).read_bytes() for name in FILES}
    proc = subprocess.run([sys.executable, "-m", "companion", "certs", str(out), "--groups", "2"],
                          capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert proc.returncode == 2 and "refusing to overwrite" in proc.stderr and "ca.key" in proc.stderr
    (out / "companion-g2.key").unlink()  # one file missing: still nothing is replaced
    assert main(["certs", str(out), "--groups", "2"]) == 2
    assert {n: (out / n).read_bytes() for n in FILES if n != "companion-g2.key"} == \
           {n: b for n, b in before.items() if n != "companion-g2.key"}
    assert main(["certs", str(out), "--groups", "2", "--overwrite"]) == 0
    assert (out / "ca.pem").read_bytes() != before["ca.pem"] and _mode(out / "companion-g2.key") == 0o600
    with pytest.raises(ValueError, match="hosts lists 1 hosts for 2 groups"):
        new_fleet_certs(tmp_path / "x", 2, ["10.0.0.1"])
    with pytest.raises(ValueError, match="'pi_1' is neither an IP address nor a DNS name"):
        new_fleet_certs(tmp_path / "x", 1, ["pi_1"])
    with pytest.raises(ValueError, match="groups must be at least 1"):
        new_fleet_certs(tmp_path / "x", 0)
    with pytest.raises(ValueError, match="days"):
        new_fleet_certs(tmp_path / "x", 1, days=0)
    assert not (tmp_path / "x").exists()


# -- mutual TLS over Zenoh ----------------------------------------------------------------------------------
def _tls_cfg(certs: Path, n: int = 2) -> ZenohConfig:
    return ZenohConfig(endpoints=tuple(f"tls/127.0.0.1:{p}" for p in free_ports(n)), tls=ZenohTls(certs_dir=str(certs)))


def _outsider(endpoint: str, **tls: str) -> zenoh.Session:
    """A session on this host that connects to ``endpoint`` with the given TLS files."""
    return peer_session(connect=(endpoint,), **{f"transport__link__tls__{key}": path for key, path in tls.items()})


def test_two_groups_with_mutual_tls_meet_and_sessions_without_a_fleet_certificate_cannot(tmp_path):
    """Groups 1 and 2, configured by ``certs_dir`` alone, exchange a put; a session that trusts the
    fleet CA but has no client certificate, or one signed by another CA, opens no transport to
    group 1, so its puts never reach group 1's subscriber (while the fleet's still do)."""
    certs, other = tmp_path / "certs", tmp_path / "other"
    new_fleet_certs(certs, 2)
    new_fleet_certs(other, 2)  # another CA, the same names and hosts
    cfg = _tls_cfg(certs)
    sessions = [zenoh.open(zenoh_config(cfg, g, 2)) for g in range(2)]
    outsiders = []
    got = []
    try:
        sub = sessions[0].declare_subscriber("test_certs/**", lambda s: got.append((str(s.key_expr), s.payload.to_bytes())))
        assert wait_for(lambda: sessions[0].info.peers_zid(), 5.0), "the groups did not connect over mutual TLS"
        assert wait_for(lambda: (sessions[1].put("test_certs/fleet", b"1"), got)[1], 5.0)
        assert got[0] == ("test_certs/fleet", b"1")
        outsiders = [
            _outsider(cfg.endpoints[0], root_ca_certificate=str(certs / "ca.pem")),  # no client certificate
            _outsider(cfg.endpoints[0], root_ca_certificate=str(certs / "ca.pem"),  # another CA's certificate
                      connect_certificate=str(other / "companion-g2.pem"),
                      connect_private_key=str(other / "companion-g2.key")),
        ]
        deadline = time.monotonic() + 1.5
        while time.monotonic() < deadline:
            for k, s in enumerate(outsiders):
                s.put(f"test_certs/outsider{k}", b"x")
            time.sleep(0.05)
        assert all(not s.info.peers_zid() for s in outsiders)
        assert [str(z) for z in sessions[0].info.peers_zid()] == [str(sessions[1].info.zid())]
        got.clear()
        sessions[1].put("test_certs/fleet", b"2")
        assert wait_for(lambda: got, 2.0)
        assert got == [("test_certs/fleet", b"2")]  # the fleet's own only
        sub.undeclare()
    finally:
        for s in outsiders + sessions:
            s.close()


def test_without_mutual_tls_the_same_outsider_would_get_in(tmp_path):
    """The control of the test above: a listener with the fleet's certificate but ``enable_mtls``
    off admits the certificate-less session, so that test's refusal is mutual TLS at work."""
    certs = tmp_path / "certs"
    new_fleet_certs(certs, 1)
    cfg = ZenohConfig(endpoints=(f"tls/127.0.0.1:{free_ports(1)[0]}",), tls=ZenohTls(
        root_ca_certificate=str(certs / "ca.pem"), listen_certificate=str(certs / "companion-g1.pem"),
        listen_private_key=str(certs / "companion-g1.key")))
    zc = zenoh_config(cfg, 0, 1)
    assert zc.get_json("transport/link/tls/enable_mtls") == "false"
    listener = zenoh.open(zc)
    outsider = _outsider(cfg.endpoints[0], root_ca_certificate=str(certs / "ca.pem"))
    try:
        assert wait_for(lambda: outsider.info.peers_zid(), 5.0)
    finally:
        outsider.close()
        listener.close()


# -- [zenoh.tls] certs_dir ----------------------------------------------------------------------------------
def _setup_data(tls: dict, endpoints=("tls/10.0.0.11:7447", "tls/10.0.0.12:7447", "tls/10.0.0.13:7447")) -> dict:
    return {"name": "t", "skeleton": {"n_links": 7}, "companion": {"groups": [[1, 2], [3, 4, 5], [6, 7]]},
            "zenoh": {"endpoints": list(endpoints), "tls": tls}}


@pytest.mark.parametrize("tls, endpoints, key, reason", [
    ({"certs_dir": "c", "root_ca_certificate": "ca.pem"}, None, "zenoh.tls.certs_dir", "drop root_ca_certificate"),
    ({"certs_dir": "c", "listen_certificate": "a.pem", "listen_private_key": "a.key"}, None, "zenoh.tls.certs_dir",
     "drop listen_certificate, listen_private_key"),
    ({"certs_dir": "c", "enable_mtls": False}, None, "zenoh.tls.enable_mtls", "always uses mutual TLS"),
    ({"certs_dir": "c"}, ("tcp/10.0.0.11:7447", "tcp/10.0.0.12:7447", "tcp/10.0.0.13:7447"), "zenoh.endpoints",
     "use tls/ or quic/"),
    ({"certs_dir": "c"}, (), "zenoh.endpoints", "needs explicit tls/ endpoints"),
    ({"certs_dir": 3}, None, "zenoh.tls.certs_dir", "string"),
    ({"cert_dir": "c"}, None, "zenoh.tls.cert_dir", "certs_dir"),
])
def test_certs_dir_config_errors_name_the_key(tls, endpoints, key, reason):
    data = _setup_data(tls) if endpoints is None else _setup_data(tls, endpoints)
    with pytest.raises(ConfigError, match=reason) as err:
        build(CompanionSetup, data, file="t.toml")
    assert str(err.value).startswith(f"t.toml: {key}: ")


def test_certs_dir_is_relative_to_the_config_file_and_picks_each_groups_files(tmp_path):
    folder = tmp_path / "hw"
    folder.mkdir()
    (folder / "fleet.toml").write_text(
        'name = "t"\n[skeleton]\nn_links = 4\n[companion]\ngroups = [[1, 2], [3, 4]]\ndistributed = true\n'
        '[zenoh]\nendpoints = ["tls/127.0.0.1:7801", "tls/127.0.0.1:7802"]\n[zenoh.tls]\ncerts_dir = "keys/certs"\n')
    setup = load_setup(CompanionSetup, folder / "fleet.toml")
    certs = folder / "keys" / "certs"
    assert setup.zenoh.tls.certs_dir == str(certs) and setup.zenoh.tls.mtls
    new_fleet_certs(certs, 2)
    zc = zenoh_config(setup.zenoh, 1, 2, "fleet.toml")
    get = lambda k: zc.get_json(f"transport/link/tls/{k}").strip('"')  # noqa: E731
    assert get("root_ca_certificate") == str(certs / "ca.pem")
    assert get("listen_certificate") == get("connect_certificate") == str(certs / "companion-g2.pem")
    assert get("listen_private_key") == get("connect_private_key") == str(certs / "companion-g2.key")
    assert zc.get_json("transport/link/tls/enable_mtls") == "true"
    # the explicit keys still work as before (one computer's files, mTLS by choice)
    explicit = ZenohTls(root_ca_certificate=get("root_ca_certificate"), listen_certificate=get("listen_certificate"),
                        listen_private_key=get("listen_private_key"), connect_certificate=get("connect_certificate"),
                        connect_private_key=get("connect_private_key"), enable_mtls=True)
    zc2 = zenoh_config(ZenohConfig(endpoints=setup.zenoh.endpoints, tls=explicit), 1, 2)
    for k in ("root_ca_certificate", "listen_certificate", "listen_private_key", "connect_certificate",
              "connect_private_key", "enable_mtls"):
        assert zc2.get_json(f"transport/link/tls/{k}") == zc.get_json(f"transport/link/tls/{k}")


def test_a_companions_tls_files_are_checked_before_its_session_opens(tmp_path):
    certs = tmp_path / "certs"
    cfg = ZenohConfig(endpoints=("tls/127.0.0.1:7801", "tls/127.0.0.1:7802", "tls/10.0.0.13:7447"),
                      tls=ZenohTls(certs_dir=str(certs)))
    with pytest.raises(ConfigError, match=r"f.toml: zenoh.tls.certs_dir: no such file: .*ca.pem \(the fleet CA "
                                          r"certificate\); create them with `python -m companion certs DIR --groups 3"):
        zenoh_config(cfg, 0, 3, "f.toml")
    new_fleet_certs(certs, 2)  # made for two groups: group 3 has no certificate
    with pytest.raises(ConfigError, match=r"companion-g3.pem \(group 3's certificate\).*copy ca.pem, "
                                          r"companion-g3.pem and companion-g3.key to this computer"):
        zenoh_config(cfg, 2, 3)
    os.chmod(certs / "companion-g1.key", 0o644)
    with pytest.raises(ConfigError, match=r"zenoh.tls.certs_dir: .*companion-g1.key: readable by others"):
        zenoh_config(cfg, 0, 3)
    os.chmod(certs / "companion-g1.key", 0o600)
    zenoh_config(cfg, 0, 3)
    new_fleet_certs(certs, 3, ["127.0.0.1", "127.0.0.1", "127.0.0.1"], overwrite=True)  # --hosts left out
    with pytest.raises(ConfigError, match=r"companion-g3.pem: made for 127.0.0.1, not 10.0.0.13 \(this group's "
                                          r"endpoint\); make the certificates with --hosts"):
        zenoh_config(cfg, 2, 3)
    other = tmp_path / "other"
    new_fleet_certs(other, 1)
    (certs / "ca.pem").write_bytes((other / "ca.pem").read_bytes())  # a CA from another run
    with pytest.raises(ConfigError, match=r"companion-g1.pem: not signed by the fleet CA"):
        zenoh_config(cfg, 0, 3)
    (certs / "ca.pem").write_text("not a certificate\n")
    with pytest.raises(ConfigError, match=r"ca.pem: not a PEM certificate"):
        zenoh_config(cfg, 0, 3)
    late = datetime.datetime.now(datetime.timezone.utc) + datetime.timedelta(days=2000)
    with pytest.raises(ValueError, match=r"not now .*is this computer's clock set"):
        check_group_certificate(other / "companion-g1.pem", other / "ca.pem", "127.0.0.1", now=late)
