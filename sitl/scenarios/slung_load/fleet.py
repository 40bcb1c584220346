"""The slung load as a fleet (``python -m sitl launch``): every vehicle a process with its own
simulated Pixhawk, one companion, the vision consumer, the harness with the load in lockstep.

:class:`SlungLoadFleetTask` is the kind's part (:class:`~sitl.fleet.task.FleetTask`):

* **plant**: the vehicles' chain plant with the slung-load model put in (:mod:`.model`), hovering
  in formation with the load hanging below, as in batch mode;
* **companion**: it runs although the chain's constraint is off (``companion.enabled = false``):
  it arms the vehicles, flies the formation (``trajectory.kind = "formation"``, its targets with
  the cables' feed-forward), takes every vehicle's state over MAVLink and runs the load's EKF
  (:class:`~companion.load.tracker.LoadTracker`) with the fixed lag of batch mode
  (:func:`.estimation.fixed_lag_s`); it opens a Zenoh session for the consumer's measurements on
  group 1's endpoint with the run's throwaway credentials;
* **vision consumer**: the frames the harness renders and publishes; it runs the load's marker
  pipeline (:func:`.estimation.load_pipeline_config`) and publishes each view of the load's
  marker as an eq. 4 observation to the companion (``[load]`` of its config,
  :class:`~companion.vision.node_config.LoadMarker`);
* **truth and metrics**: the load's true pose at every firmware tick, against the companion's
  ``load.npz`` (:func:`.estimation.load_pose_metrics`, as batch mode scores its filters), with the
  companion's filter counters and the observations' wire counts; ``load.npz`` and
  ``load_pose_error.png`` in the run folder.
"""

from __future__ import annotations

import json
import logging
from dataclasses import replace

import numpy as np

from companion.estimation.so3 import rotmat_to_quat
from sitl.fleet.task import FleetTask

from .config import SlungLoadScenario
from .estimation import fixed_lag_s, load_pipeline_config, load_pose_metrics

__all__ = ["SlungLoadFleetTask", "launch_slung_load"]

log = logging.getLogger(__name__)


class SlungLoadFleetTask(FleetTask):
    """The slung load's part in a fleet run (module docstring)."""

    consumer_publishes = True

    def __init__(self, scenario: SlungLoadScenario):
        self.scenario = scenario
        self.truth: dict[str, list] = {"t": [], "p": [], "q": []}
        self._model = None
        self._fw_div = 1

    def companion_runs(self, sc) -> bool:
        return True

    def plant(self, sc):
        from sitl.plant.plant import Plant

        from .flight import vehicles_scenario
        from .model import put_in

        plant = Plant(vehicles_scenario(sc))
        self._model = put_in(plant, sc)
        return plant

    def companion_setup(self, fleet, setup):
        load = replace(setup.load, fixed_lag_s=fixed_lag_s(self.scenario, fleet.plant.dt))
        return replace(setup, load=load)

    def consumer_setup(self, fleet, setup):
        from companion.vision.node_config import LoadCamera, LoadMarker

        sc = self.scenario
        marker = sc.marker_in_load()
        cameras = tuple(LoadCamera(c.name, c.vehicle_index() + 1, tuple(float(x) for x in c.pos_b_m),
                                   tuple(float(x) for x in rotmat_to_quat(c.R_b_c()))) for c in sc.cameras)
        load = LoadMarker(sc.load.marker_id, tuple(float(x) for x in marker.pos_m),
                          tuple(float(x) for x in marker.q_wxyz), cameras)
        return replace(setup, pipeline=load_pipeline_config(sc), load=load)

    def start(self, fleet) -> None:
        self._fw_div = fleet.harness.schedule.fw
        fleet.harness.tick_hooks.append(self._on_tick)

    def _on_tick(self, k: int, t: float) -> None:
        """The load's true pose at every firmware tick (the links' samples are on that grid)."""
        if k % self._fw_div:
            return
        p, q = self._model.load_pose()
        self.truth["t"].append(t)
        self.truth["p"].append(p)
        self.truth["q"].append(q)

    def metrics(self, fleet, plots: bool) -> dict:
        """The companion's load estimate against the truth (module docstring)."""
        sc, out_dir = self.scenario, fleet.out_dir
        folder = out_dir / fleet.companion_folder(None)
        out: dict = {}
        summary_path = folder / "companion_summary.json"
        summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
        out["load_filter_stats"] = summary.get("load")
        out["load_observations_wire"] = summary.get("load_observations_wire")
        try:
            with np.load(folder / "load.npz") as f:
                a = dict(f)
        except OSError as exc:
            log.warning("no load estimate from the companion: %s", exc)
            out["load_pose_err"] = None
            return out
        t_truth = np.asarray(self.truth["t"])
        if not len(t_truth) or "load_t" not in a:
            out["load_pose_err"] = None
            return out
        p_truth, q_truth = np.asarray(self.truth["p"]), np.asarray(self.truth["q"])

        def at(t):
            i = np.clip(np.searchsorted(t_truth, np.asarray(t) - 1e-9), 0, len(t_truth) - 1)
            return p_truth[i], q_truth[i]

        a["load_p_true"], a["load_q_true"] = at(a["load_t"])
        if "load_lag_t" in a:
            a["load_lag_p_true"], a["load_lag_q_true"] = at(a["load_lag_t"])
        out.update(load_pose_metrics(a, sc.load.settle_s, ("ekf",)))
        if "load_lag_t" in a:
            out["load_fixed_lag_s"] = fleet.companion_setup.load.fixed_lag_s
        np.savez_compressed(out_dir / "load.npz", **a)
        if plots:
            from .plots import write_load_plots

            write_load_plots(a, None, out_dir, sc.load.settle_s)
        return out


def launch_slung_load(scenario: SlungLoadScenario, out_dir, **options) -> dict:
    """Fly the slung-load scenario as a fleet (:func:`sitl.fleet.launcher.launch`'s options)."""
    from sitl.fleet.launcher import launch

    return launch(scenario, out_dir, task=SlungLoadFleetTask(scenario), **options)
