"""The vision consumer's measurements, out on Zenoh for the companions.

Two kinds, each made (pure) from the marker poses of one processed frame
(:class:`~.node.FrameRecord`):

* :func:`neighbour_poses`: a :class:`~companion.messages.NeighbourPose` per pose of a marker the
  ``[[neighbours]]`` list names for that camera (:class:`~.node_config.NeighbourCamera`): the pose
  with its covariance, the capture time and both mounts, on ``<prefix>/link/<observer>/neighbour``
  (:func:`~companion.fleetnet.keys.neighbour_key`), for the companion that steps both links;
* :func:`load_observations`: a :class:`~companion.load.model.LoadObservation` per pose of the slung
  load's marker in a ``[[load.cameras]]`` camera's frame (:class:`~.node_config.LoadMarker`): eq. 4
  of the slung-load report (:func:`~companion.load.measurements.observation_from_pnp`), on
  ``<prefix>/vehicle/<vehicle>/load`` (:func:`~companion.fleetnet.keys.load_key`), for the carrying
  companion's load filter.

Both take the companion's side of the wire as their receivers
(:class:`~companion.fleetnet.inbox.MessageInbox`). :class:`MessagePublisher` puts them on a
session it is given and opens nothing.
"""

from __future__ import annotations

from collections.abc import Hashable, Mapping

import numpy as np

from companion.fleetnet import codec
from companion.load.measurements import observation_from_pnp
from companion.load.model import LoadObservation, Pose3
from companion.messages import NeighbourPose

from .node_config import LoadMarker, NeighbourCamera

__all__ = ["neighbour_poses", "load_observations", "MessagePublisher"]


def neighbour_poses(record, cameras: dict[tuple[str, int], NeighbourCamera]) -> tuple[list[NeighbourPose], int]:
    """The neighbour poses of ``record`` (its camera's poses of the markers ``cameras`` names, by
    ``(camera, marker_id)``) and how many such poses came from a vehicle other than the
    configured observer (left out: a camera name on the wrong vehicle is a configuration error)."""
    out, wrong_vehicle = [], 0
    for pose in record.poses:
        cam = cameras.get((record.camera, pose.marker_id))
        if cam is None:
            continue
        if record.vehicle != cam.observer - 1:
            wrong_vehicle += 1
            continue
        out.append(NeighbourPose(cam.observer - 1, cam.observed - 1, float(record.t_capture_s), int(record.seq),
                                 np.asarray(pose.q_cm_wxyz, dtype=float), np.asarray(pose.t_cm_m, dtype=float),
                                 np.asarray(pose.cov, dtype=float), np.asarray(cam.camera_pos_b_m, dtype=float),
                                 np.asarray(cam.camera_q_bc_wxyz, dtype=float), np.asarray(cam.marker_pos_b_m, dtype=float),
                                 np.asarray(cam.marker_q_bm_wxyz, dtype=float)))
    return out, wrong_vehicle


def load_observations(record, load: LoadMarker) -> tuple[list[LoadObservation], int]:
    """The load observations of ``record`` (its pose of ``load``'s marker, if its camera is one of
    ``load.cameras``) and how many came from a vehicle other than the camera's configured one
    (left out, as in :func:`neighbour_poses`)."""
    cam = next((c for c in load.cameras if c.camera == record.camera), None)
    if cam is None:
        return [], 0
    out, wrong_vehicle = [], 0
    marker = Pose3(np.asarray(load.marker_pos_b_m, dtype=float), np.asarray(load.marker_q_bm_wxyz, dtype=float))
    mount = Pose3(np.asarray(cam.camera_pos_b_m, dtype=float), np.asarray(cam.camera_q_bc_wxyz, dtype=float))
    for pose in record.poses:
        if pose.marker_id != load.marker_id:
            continue
        if record.vehicle != cam.vehicle - 1:
            wrong_vehicle += 1
            continue
        out.append(observation_from_pnp(cam.vehicle - 1, float(record.t_capture_s), pose.R_cm, pose.t_cm_m,
                                        pose.cov, mount, marker))
    return out, wrong_vehicle


class MessagePublisher:
    """Publishes messages on ``session``: one publisher per key of ``keys`` (by any name), declared
    at once so that :attr:`matched` can say whether a companion takes them before the first frame.
    A measurement is small and a late one is useless: each is sent at once, never queued behind
    frames."""

    def __init__(self, session, keys: Mapping[Hashable, str]):
        import zenoh

        self._pubs = {name: session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP,
                                                      priority=zenoh.Priority.INTERACTIVE_HIGH, express=True)
                      for name, key in keys.items()}
        self.published = 0

    @property
    def matched(self) -> bool:
        """Whether every key has a subscriber now (a companion that takes its messages)."""
        return all(bool(p.matching_status.matching) for p in self._pubs.values())

    def publish(self, name: Hashable, msg) -> None:
        """``msg`` on the key named ``name`` (``ValueError`` for a name it was not given)."""
        pub = self._pubs.get(name)
        if pub is None:
            raise ValueError(f"no key {name!r} on this publisher")
        pub.put(codec.encode(msg))
        self.published += 1

    def close(self) -> None:
        for pub in self._pubs.values():
            try:
                pub.undeclare()
            except Exception:  # noqa: BLE001 - the session may be closing already
                pass
        self._pubs = {}
