"""The harness's faults of a fleet run, one interface for the scenario and for requests at run time.

A :class:`HarnessFault` is a vehicle (``vehicle_off``: its Pixhawk loses power) or a companion
(``companion_off``: its onboard computer does) switched off at a simulated time, and on again
``restart_after_s`` of simulated time later (0: it stays off). The scenario's ``[faults.link]``
and ``faults.kill_companion_group`` are such faults (:func:`scripted_faults`); the fault socket
(:mod:`.fault_socket`, ``python -m sitl fault KIND RUN_DIR ...``) adds more while the fleet flies.
:class:`FleetFaults` plays them all the same way at every firmware tick and keeps each one's
timeline for the metrics:

* a vehicle off: its process SIGKILLed and the harness's link to it closed (its rotors stop, the
  physics runs on); at the restart a new vehicle process (folder ``link<i>-restart``, then
  ``-restart2``...) is connected as soon as it listens (``rejoined_at_s``). A restart the scenario
  scripts has its process started with the fleet, waiting in ``--standby``; one asked for at run
  time starts at the kill, so its outage lasts at least that process's start-up;
* a companion off: its process SIGKILLed; at the restart a new one starts (folder
  ``companion-g<G>-restart``, then ``-restart2``...).

A fault on a vehicle or companion that is already off is refused, as is one on a link or group
the fleet does not have.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from sitl.metrics import vehicle_down_windows

__all__ = ["FAULT_KINDS", "HarnessFault", "scripted_faults", "restart_folder", "FleetFaults"]

log = logging.getLogger(__name__)

FAULT_KINDS = ("vehicle_off", "companion_off")
#: the longest restart delay a request may ask for [simulated s]
RESTART_MAX_S = 3600.0


@dataclass(frozen=True)
class HarnessFault:
    """``kind`` (:data:`FAULT_KINDS`) on ``target`` (a link for ``vehicle_off``, a group for
    ``companion_off``; 1-based; group 1 is a centralised fleet's one companion) at simulated time
    ``at_s`` (``None``: at once), on again ``restart_after_s`` later (0: never). ``source``:
    ``"scenario"`` or ``"request"``."""

    kind: str
    target: int
    restart_after_s: float = 0.0
    at_s: float | None = None
    source: str = "scenario"

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"kind {self.kind!r}: one of {', '.join(FAULT_KINDS)}")
        if isinstance(self.target, bool) or not isinstance(self.target, int) or self.target < 1:
            raise ValueError(f"target must be a link or group number >= 1, got {self.target!r}")
        r = self.restart_after_s
        if isinstance(r, bool) or not isinstance(r, (int, float)) or not 0.0 <= r <= RESTART_MAX_S:
            raise ValueError(f"restart_after_s must be a number of seconds in [0, {RESTART_MAX_S:g}], got {r!r}")
        a = self.at_s
        if a is not None and (isinstance(a, bool) or not isinstance(a, (int, float)) or not math.isfinite(a) or a < 0):
            raise ValueError(f"at_s must be a simulated time >= 0 (or absent: at once), got {a!r}")

    @classmethod
    def from_request(cls, request) -> "HarnessFault":
        """A fault from a run-time request: a JSON object with ``kind``, ``target`` and optionally
        ``restart_after_s`` and ``at_s``. ``ValueError`` saying what is wrong otherwise."""
        if not isinstance(request, dict):
            raise ValueError("a request is a JSON object with kind, target and optionally restart_after_s, at_s")
        unknown = set(request) - {"kind", "target", "restart_after_s", "at_s"}
        if unknown:
            raise ValueError(f"unknown keys: {', '.join(sorted(map(str, unknown)))}")
        if "kind" not in request or "target" not in request:
            raise ValueError("a request needs kind and target")
        return cls(request["kind"], request["target"], request.get("restart_after_s", 0.0), request.get("at_s"),
                   source="request")


def scripted_faults(sc) -> list[HarnessFault]:
    """The harness faults of scenario ``sc``'s ``[faults]`` table."""
    f = sc.faults
    out = []
    if f.link.kill:
        out.append(HarnessFault("vehicle_off", f.link.kill, f.link.restart_after_s, f.link.kill_at_s))
    if f.kill_companion_group:
        out.append(HarnessFault("companion_off", f.kill_companion_group, f.restart_after_s, f.kill_at_s))
    return out


def restart_folder(base: str, k: int) -> str:
    """The run folder of the ``k``-th restarted process (from 1) of the one in ``base``."""
    return f"{base}-restart" if k == 1 else f"{base}-restart{k}"


class FleetFaults:
    """The harness faults of ``fleet`` (a :class:`~sitl.fleet.launcher.Fleet`): :meth:`add` one,
    :meth:`tick` at every firmware tick; :attr:`timelines` what each did (simulated seconds)."""

    def __init__(self, fleet):
        self.fleet = fleet
        n = fleet.n
        #: per link / group: the process now running, and how many restarts it has had
        self._vehicle = [(f"link {i + 1}", 0) for i in range(n)]
        self._companion = {}
        if fleet.companion:
            if fleet.sc.companion.distributed:
                self._companion = {g: (fleet.companion_name(g), 0)
                                   for g in range(len(fleet.sc.companion.group_layout(n)))}
            else:
                self._companion = {0: (fleet.companion_name(None), 0)}
        self._pending: list[tuple[HarnessFault, dict]] = []
        self.timelines: list[dict] = []
        self.refused = 0

    # -- adding ---------------------------------------------------------------------------------
    def refusal(self, fault: HarnessFault) -> str | None:
        """Why ``fault`` cannot be played on this fleet (``None``: it can)."""
        if fault.kind == "vehicle_off":
            what, key, count = f"link {fault.target}", "link", self.fleet.n
            if fault.target > count:
                return f"{what}: the fleet has links 1..{count}"
        else:
            what, key, count = f"the companion of group {fault.target}", "group", len(self._companion)
            if not count:
                return "this fleet runs no companion"
            if fault.target > count:
                return f"group {fault.target}: the fleet has companions 1..{count}"
        for tl in self.timelines:
            if tl["kind"] == fault.kind and tl[key] == fault.target:
                if any(tl is other for _, other in self._pending):
                    return f"{what} has a fault in play (off at {tl['off_at_s']:g} s)"
                if not tl["restart_after_s"]:
                    return f"{what} is off for good (since {tl['killed_at_s']:g} s)"
        return None

    def add(self, fault: HarnessFault, now_s: float) -> dict:
        """Play ``fault`` (at ``now_s`` if it has no time, or at its time if that is later);
        returns its timeline. ``ValueError`` (counted in :attr:`refused`) if it cannot be played."""
        why = self.refusal(fault)
        if why is not None:
            self.refused += 1
            raise ValueError(why)
        at = now_s if fault.at_s is None else max(float(fault.at_s), now_s)
        key = "link" if fault.kind == "vehicle_off" else "group"
        tl = {"kind": fault.kind, key: fault.target, "source": fault.source, "off_at_s": round(at, 3),
              "restart_after_s": float(fault.restart_after_s)}
        if fault.source == "request":
            tl["requested_at_s"] = round(now_s, 3)
        if fault.kind == "vehicle_off" and fault.restart_after_s and fault.source == "scenario":
            # a scripted restart: its process loaded now, waiting to be released at the kill
            tl["standby"] = self._start_vehicle(fault.target - 1, standby=True)
        self._pending.append((fault, tl))
        self.timelines.append(tl)
        return tl

    # -- playing --------------------------------------------------------------------------------
    def tick(self, t: float) -> None:
        """Every firmware tick at simulated time ``t``: what is due of every fault."""
        still = []
        for fault, tl in self._pending:
            done = self._vehicle_tick(fault, tl, t) if fault.kind == "vehicle_off" else self._companion_tick(fault, tl, t)
            if not done:
                still.append((fault, tl))
        self._pending = still

    def _start_vehicle(self, i: int, standby: bool) -> str:
        name, k = self._vehicle[i]
        k += 1
        new = f"link {i + 1} (restarted)" if k == 1 else f"link {i + 1} (restart {k})"
        self.fleet.start_vehicle(i, new, restart_folder(f"link{i + 1}", k), standby=standby)
        self._vehicle[i] = (name, k)
        return new

    def _switched_off(self, tl: dict, t: float, name: str) -> bool:
        """Process ``name`` SIGKILLed if ``tl``'s fault (not yet played) is due at ``t`` (its
        ``killed_at_s``, and when on the companion's wall clock); whether it was."""
        if t < tl["off_at_s"]:
            return False
        self.fleet.procs.kill(name)
        tl.update(killed_at_s=round(t, 3), killed_at_monotonic=time.monotonic())
        return True

    def _vehicle_tick(self, fault: HarnessFault, tl: dict, t: float) -> bool:
        fleet, i = self.fleet, fault.target - 1
        if "killed_at_s" not in tl:
            if not self._switched_off(tl, t, self._vehicle[i][0]):
                return False
            fleet.harness.detach(i)
            log.warning("fault: killed link %d's firmware at t = %.2f s (rotors stopped)", i + 1, t)
            if not fault.restart_after_s:
                return True
            # The replacement opens its ports and waits for the simulator like PX4's SITL (silent
            # until the lockstep connects): its power comes back when the harness attaches it,
            # restart_after_s of simulated time after the kill. The physics does not wait for it
            # (the companion, on wall time, would take the other links' silence for an outage): a
            # host slower than that lengthens the outage, and says so.
            new = tl.pop("standby", None)
            if new is not None:
                fleet.procs.release(new)
            else:
                new = self._start_vehicle(i, standby=False)
            self._vehicle[i] = (new, self._vehicle[i][1])
        if "restarted_at_s" not in tl:
            if t < tl["killed_at_s"] + fault.restart_after_s:
                return False
            tl["restarted_at_s"] = round(t, 3)
            log.warning("fault: link %d's firmware powered on again at t = %.2f s", i + 1, t)
        if "rejoined_at_s" not in tl:
            if not fleet.sim_listening(i):
                return False
            fleet.harness.attach(i, fleet.sim_url(i, "harness"))
            tl["rejoined_at_s"] = round(t, 3)
            late = t - tl["restarted_at_s"]
            (log.warning if late > 0.05 else log.info)(
                "fault: link %d re-joined the lockstep at t = %.2f s%s", i + 1, t,
                f" ({late:.2f} s of simulated time after its power-on: its process was still starting)"
                if late > 0.05 else "")
        if np.any(fleet.plant.rotors.command_n.reshape(fleet.n, -1)[i] != 0):
            tl["rotors_on_at_s"] = round(t, 3)
            return True
        return False

    def _companion_tick(self, fault: HarnessFault, tl: dict, t: float) -> bool:
        fleet, g = self.fleet, fault.target - 1
        if "killed_at_s" not in tl:
            if not self._switched_off(tl, t, self._companion[g][0]):
                return False
            log.warning("fault: killed the companion of group %d at t = %.2f s", g + 1, t)
            return not fault.restart_after_s
        if t < tl["killed_at_s"] + fault.restart_after_s:
            return False
        name, k = self._companion[g]
        k += 1
        group = g if fleet.sc.companion.distributed else None
        new = f"{fleet.companion_name(group)} (restarted)" if k == 1 else f"{fleet.companion_name(group)} (restart {k})"
        fleet.start_companion(group, restart_folder(fleet.companion_folder(group), k), new)
        self._companion[g] = (new, k)
        tl.update(restarted_at_s=round(t, 3), restarted_at_monotonic=time.monotonic())
        log.warning("fault: restarted the companion of group %d at t = %.2f s", g + 1, t)
        return True

    # -- the metrics ----------------------------------------------------------------------------
    def windows(self, end_s: float) -> list[dict]:
        """Every fault's outage window: a vehicle down (killed until back in the lockstep, or the
        end of the run), a companion down (killed until restarted, or the end)."""
        out = []
        layout = self.fleet.sc.companion.group_layout(self.fleet.n) if self.fleet.sc.companion.distributed else None
        for tl in self.timelines:
            if "killed_at_s" not in tl:
                continue
            if tl["kind"] == "vehicle_off":
                out += vehicle_down_windows(tl, end_s)
            else:
                links = ([i + 1 for i in layout[tl["group"] - 1]] if layout is not None
                         else list(range(1, self.fleet.n + 1)))
                out.append({"kind": "companion_down", "start_s": tl["killed_at_s"],
                            "end_s": tl.get("restarted_at_s", end_s), "links": links})
        return out

    def first(self, kind: str, source: str | None = None) -> dict:
        """The first timeline of ``kind`` (from ``source``, if given) that started; ``{}``: none."""
        return next((tl for tl in self.timelines if tl["kind"] == kind and "killed_at_s" in tl
                     and (source is None or tl["source"] == source)), {})
