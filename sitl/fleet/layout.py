"""The fleet's layout: the ports every process takes (PX4 SITL's instance layout, moved by an
instance offset), the checks of a scenario and an offset against it, the table of the fleet's
addresses, and :class:`FleetError`.

Link ``i`` of a fleet with instance offset K is PX4 SITL instance K + i: simulator TCP 4560+K+i,
onboard UDP 14540+K+i (the companion's end; the vehicle's from 14580+K+i), GCS traffic from
18570+K+i to :data:`GCS_PORT` (or another port); the impaired wire (``[faults.mavlink]``) takes
:data:`WIRE_VEHICLE_SIDE` + K + i and :data:`WIRE_COMPANION_SIDE` + K + i.
"""

from __future__ import annotations

from pathlib import Path

from companion.config import SITL_STATE_PORT
from companion.mavlink.signing import key_passphrase
from sitl.scenario import Scenario

__all__ = ["FleetError", "GCS_PORT", "LOCKSTEP_STARTED", "LOCKSTEP_ENDED", "SIM_LINKS", "WIRE_VEHICLE_SIDE", "WIRE_COMPANION_SIDE", "signing_instructions",
           "COMPANION_KERNELS", "endpoint_table", "check_fleet_scenario", "check_instance_offset", "impaired_links",
           "fleet_ports"]

#: UDP ports of the impaired wire (``[faults.mavlink]``): vehicle i sends to WIRE_VEHICLE_SIDE + i,
#: the companion sees it from WIRE_COMPANION_SIDE + i
WIRE_VEHICLE_SIDE = 15540
WIRE_COMPANION_SIDE = 15580
#: the vehicles' simulator links: PX4's simulator API on TCP (the default), or the same-host link
SIM_LINKS = ("tcp", "unix")
#: the companions' path: their compiled kernels (the default where numba is installed), or the numpy
#: path an onboard computer without numba runs
COMPANION_KERNELS = ("compiled", "numpy")
#: where every vehicle sends its ground-station traffic (PX4 SITL's: QGroundControl listens there)
GCS_PORT = 14550
#: the harness's log lines at the lockstep's start and end (what ``sitl.bench sitl`` times a fleet by)
LOCKSTEP_STARTED = "lockstep started:"
LOCKSTEP_ENDED = "lockstep ended"


class FleetError(RuntimeError):
    """The fleet could not run (a process died, a link stopped answering the simulator)."""


def signing_instructions(sc: Scenario, gcs_port: int = GCS_PORT) -> str:
    """How a ground station joins a signed fleet, as typed: MAVProxy's ``signing key`` takes the
    passphrase itself (its prompt does no shell expansion)."""
    modes = f"MAVLink 2 signing: onboard {sc.signing.link_mode('onboard')}, GCS {sc.signing.link_mode('gcs')}; key file " \
            f"{sc.signing.key_file}"
    try:
        passphrase = key_passphrase(sc.signing.key_file)
    except ValueError as exc:
        return f"{modes} ({exc})"
    if passphrase is None:
        return (f"{modes}: a raw key; MAVProxy and QGroundControl derive theirs from a passphrase "
                "(python -m companion keys new FILE makes one)")
    return (f"{modes}\nMAVProxy: mavproxy.py --master=udpin:127.0.0.1:{gcs_port}, then type at its prompt:\n"
            f"    signing key {passphrase}")


def endpoint_table(sc: Scenario, host: str = "127.0.0.1", instance_offset: int = 0,
                   sim_dir: Path | None = None, gcs_port: int = GCS_PORT) -> str:
    """The fleet's addresses; ``sim_dir``: the same-host simulator link's socket folder (else TCP)."""
    k = instance_offset
    rows = [f"{'link':>4} | {'sysid':>5} | {'simulator (TCP)' if sim_dir is None else 'simulator (UNIX)':>18} | "
            f"{'onboard / companion (UDP)':>28} | {'GCS (UDP)':>24}", "-" * 93]
    for i in range(sc.skeleton.n_links):
        sim = f"{host}:{4560 + k + i}" if sim_dir is None else f"link{i + 1}.sock"
        onboard = f"{host}:{14540 + k + i} <- :{14580 + k + i}"
        gcs = f"{host}:{gcs_port} <- :{18570 + k + i}"
        rows.append(f"{i + 1:>4} | {i + 1:>5} | {sim:>18} | {onboard:>28} | {gcs:>24}")
    if sim_dir is not None:
        rows.append(f"simulator links: UNIX sockets in {sim_dir} (this run only)")
    if sc.companion.distributed:
        for g, links in enumerate(sc.companion.group_layout(sc.skeleton.n_links)):
            rows.append(f"companion of group {g + 1} (links {links[0] + 1}-{links[-1] + 1}): Zenoh "
                        f"{sc.zenoh.group_endpoint(g)}, keys {sc.zenoh_prefix}/...")
    rows.append(f"QGroundControl / MAVProxy: listen on UDP {gcs_port}. MAVSDK: udpin://127.0.0.1:{14540 + k}+i (launch with "
                "--no-companion).")
    if sc.signing.active:
        rows.append(signing_instructions(sc, gcs_port))
    return "\n".join(rows)


def check_fleet_scenario(sc: Scenario) -> None:
    """``ValueError`` for a scenario that names its own companion links (a hardware config):
    fleet mode wires the simulated links itself (PX4 SITL ports)."""
    if sc.companion.links:
        raise ValueError(f"companion.links names hardware endpoints ({sc.companion.links[0].url}, ...); "
                         "fleet mode wires the simulated links itself: use a SITL config")


def check_instance_offset(sc: Scenario, instance_offset: int, gcs_port: int = GCS_PORT) -> None:
    """``ValueError`` unless a fleet shifted by ``instance_offset`` K keeps its companion ports
    14540+K+i clear of the GCS port (14550) and below the vehicles' own 14580+ (PX4's layout leaves
    room for 40 instances), and its impaired wire's 15540+K+i below 15580."""
    n, k = sc.skeleton.n_links, instance_offset
    first, last = SITL_STATE_PORT + k, SITL_STATE_PORT + k + n - 1
    if not 0 < gcs_port < 65536:
        raise ValueError(f"GCS port {gcs_port}: a UDP port is 1-65535")
    if k < 0 or last >= 14580 or first <= gcs_port <= last:
        raise ValueError(f"instance offset {k}: the companion ports of {n} links would be {first}-{last}; they must "
                         f"miss the GCS port {gcs_port} and stay below 14580"
                         + (f" (K + n <= 10, or 11 <= K <= {40 - n})" if gcs_port == GCS_PORT else ""))


def fleet_ports(n: int, instance_offset: int, tcp_sim: bool, companion: bool, wired=()) -> dict[tuple[str, int], str]:
    """The local ports an ``n``-link fleet shifted by ``instance_offset`` binds, ``(protocol,
    port) -> whose``: each vehicle's simulator link (TCP 4560+K+i, when ``tcp_sim``), its
    ground-station and onboard links' own ports (UDP 18570+K+i, 14580+K+i), the companion's
    (UDP 14540+K+i) and the impaired wire's (``wired``: 0-based links) when they run. (The
    ground-station port itself, 14550, is where a ground station listens: not the fleet's.)"""
    k, out = instance_offset, {}
    for i in range(n):
        if tcp_sim:
            out[("tcp", 4560 + k + i)] = f"link {i + 1}'s simulator link"
        out[("udp", 18570 + k + i)] = f"link {i + 1}'s ground-station link"
        out[("udp", 14580 + k + i)] = f"link {i + 1}'s onboard link"
        if companion:
            out[("udp", SITL_STATE_PORT + k + i)] = f"the companion's port for link {i + 1}"
    for i in wired:
        out[("udp", WIRE_VEHICLE_SIDE + k + i)] = f"the impaired wire of link {i + 1}"
        out[("udp", WIRE_COMPANION_SIDE + k + i)] = f"the impaired wire of link {i + 1}"
    return out


def impaired_links(sc: Scenario) -> list[int]:
    """0-based links whose onboard wire goes through :mod:`sitl.fleet.wire` (``[faults.mavlink]``)."""
    m = sc.faults.mavlink
    if not m.active:
        return []
    return [i - 1 for i in m.links] if m.links else list(range(sc.skeleton.n_links))
