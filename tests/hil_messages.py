"""The simulator link's messages for its tests: the kinds each side takes, a random tick of
every kind (a message as the TCP link delivers it: tests/mavlink_wire.py)."""

import numpy as np

from companion.estimation.so3 import quat_normalize
from companion.mavlink.dialect import load_dialect
from link_firmware_sim.geo import GeoOrigin
from link_firmware_sim.vehicle.hil import encode_actuators, encode_ahrs, encode_hil_gps, encode_hil_sensor

D = load_dialect()
#: what the vehicle's side of the link takes, and the simulator's
SENSORS = frozenset({"HIL_SENSOR", "HIL_GPS", "SKELETON_AHRS_REFERENCE"})
ACTUATORS = frozenset({"HIL_ACTUATOR_CONTROLS"})


def random_messages(rng: np.random.Generator) -> list:
    """One message of each kind of the link (HIL_GPS, SKELETON_AHRS_REFERENCE, HIL_SENSOR with a
    magnetometer and a barometer sample, HIL_ACTUATOR_CONTROLS), with random values."""
    origin = GeoOrigin()
    t = float(rng.uniform(0, 100))
    return [
        encode_hil_gps(t, rng.normal(size=3) * 50, rng.normal(size=3), origin),
        encode_ahrs(t, quat_normalize(rng.normal(size=4))),
        encode_hil_sensor(t, rng.normal(size=3) + [0, 0, 9.8], rng.normal(size=3),
                          mag_flu_gauss=rng.normal(size=3) * 0.3, baro_alt_m=float(rng.uniform(0, 500))),
        encode_actuators(t, rng.uniform(-10, 10, size=8), 8.0, bool(rng.integers(2))),
    ]
