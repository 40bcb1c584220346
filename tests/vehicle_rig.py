"""A vehicle in-process behind real loopback sockets, with a fake simulator and a fake GCS: the
rig of the vehicle's tests (the ``rig`` fixture of ``conftest.py`` is one)."""

import time

import numpy as np

from companion.estimation.so3 import quat_from_euler_zyx
from companion.mavlink.port import MavlinkPort
from companion.skeleton.body import LinkInertia
from companion.skeleton.rotors import RotorGeometry
from link_firmware_sim.firmware import FirmwareConfig, LinkFirmware
from link_firmware_sim.geo import GeoOrigin
from link_firmware_sim.vehicle.core import Vehicle
from link_firmware_sim.vehicle.hil import decode_actuators, encode_ahrs, encode_hil_gps, encode_hil_sensor
from link_firmware_sim.vehicle.links import VehiclePorts
from link_firmware_sim.vehicle.params import ParamTable, StreamRates
from link_firmware_sim.vehicle.simlink import SimLinkPort

ORIGIN = GeoOrigin()
LEVEL = quat_from_euler_zyx(0.0, 0.0, 0.0)


class Rig:
    """A vehicle (sysid 2) plus a fake simulator (TCP) and a fake GCS (UDP)."""

    def __init__(self, tmp_path, params_file=None, signing=None, key=None, gcs_key=None, sim_link="tcp",
                 companion=False):
        """``companion``: the vehicle's onboard link goes to :attr:`companion` (a second fake) and
        its ground-station link to :attr:`gcs`; without, both are :attr:`gcs`'s onboard link."""
        self.gcs = MavlinkPort("udpin://127.0.0.1:0", system_id=255, component_id=190,
                               signing="required" if gcs_key else "off", key=gcs_key)
        gcs_port = self.gcs.transport.local_port()
        self.companion = MavlinkPort("udpin://127.0.0.1:0", system_id=254, component_id=191) if companion else None
        fw = LinkFirmware(1, FirmwareConfig(), LinkInertia(1.8, (0.04, 0.16, 0.16)), RotorGeometry.odar())
        params = ParamTable(2, FirmwareConfig(), ORIGIN, StreamRates(50.0, 0.0), params_file or tmp_path / "p.json")
        sim = "tcpin://127.0.0.1:0" if sim_link == "tcp" else f"unixin://{tmp_path / 'sim.sock'}"
        if companion:
            ports = VehiclePorts(sim=sim, onboard=f"udpout://127.0.0.1:{self.companion.transport.local_port()}",
                                 gcs=f"udpout://127.0.0.1:{gcs_port}")
        else:
            ports = VehiclePorts(sim=sim, onboard=f"udpout://127.0.0.1:{gcs_port}", gcs=None)
        self.vehicle = Vehicle(1, fw, params, ports, tmp_path / "out", signing=signing, key=key,
                               key_path=tmp_path / "vehicle.key")
        if sim_link == "tcp":
            sim_port = self.vehicle.sim.transport.local_port()
            self.sim = MavlinkPort(f"tcpout://127.0.0.1:{sim_port}", system_id=250, component_id=1)
        else:  # the same-host link (link_firmware_sim.vehicle.simlink)
            self.sim = SimLinkPort(f"unix://{tmp_path / 'sim.sock'}", accept=frozenset({"HIL_ACTUATOR_CONTROLS"}))
        self.t = 0.0
        self.height_m = 2.0  # where the fake GPS puts the link
        self.vel_m_s = np.zeros(3)  # and its velocity
        self.vehicle.poll(0.01)  # accept the simulator connection

    def tick(self, gps=False, ahrs=False, **baro_mag):
        """One lockstep tick: sensors in, actuators out (returns the thrusts); ``baro_mag``: the
        HIL_SENSOR's ``mag_flu_gauss`` / ``baro_alt_m``."""
        self.t = round(self.t + 0.002, 6)
        msgs = []
        if gps:
            msgs.append(encode_hil_gps(self.t, np.array([0.0, 0.0, self.height_m]), self.vel_m_s, ORIGIN))
        if ahrs:
            msgs.append(encode_ahrs(self.t, LEVEL))
        msgs.append(encode_hil_sensor(self.t, np.array([0.0, 0.0, 9.80665]), np.zeros(3), **baro_mag))
        self.sim.send_many(msgs)
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            self.vehicle.poll(0.01)
            for msg in self.sim.read():
                t_us, thrust = decode_actuators(msg, 8.0)
                assert t_us == int(round(self.t * 1e6))
                return thrust
        raise AssertionError("no actuator answer")

    def start(self, seconds=0.2):
        self.tick(gps=True, ahrs=True)
        for k in range(int(seconds / 0.002)):
            self.tick(gps=k % 50 == 0, ahrs=k % 10 == 0)

    def gcs_send(self, msg):
        # udpin learns its peer from the vehicle's first valid datagram (a heartbeat)
        deadline = time.monotonic() + 2.0
        while not self.gcs.transport.connected:
            assert time.monotonic() < deadline, "no heartbeat reached the GCS port"
            self.tick()
            self.gcs.read()
        self.gcs.send(msg)

    def gcs_collect(self, seconds=0.3):
        """Run ``seconds`` of simulated time, returning what reached the GCS."""
        out = []
        for _ in range(int(round(seconds / 0.002))):
            self.tick()
            out += self.gcs.read()
        end = time.monotonic() + 0.05
        while time.monotonic() < end:  # drain what is still in flight
            self.vehicle.poll(0.005)
            out += self.gcs.read()
        return out

    def close(self):
        self.vehicle.close()
        self.sim.close()
        self.gcs.close()
        if self.companion is not None:
            self.companion.close()

