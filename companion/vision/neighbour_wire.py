"""A chain camera's views of its neighbour's marker, as neighbour poses on Zenoh.

:func:`neighbour_poses` (pure) turns the marker poses of one processed frame
(:class:`~.node.FrameRecord`) into :class:`~companion.messages.NeighbourPose` messages, one per
pose of a marker the consumer's ``[[neighbours]]`` list names for that camera
(:class:`~.node_config.NeighbourCamera`): the pose with its covariance, the capture time, and both
mounts. :class:`NeighbourPublisher` puts them on ``<prefix>/link/<observer>/neighbour``
(:func:`~companion.fleetnet.keys.neighbour_key`), where the companion that steps both links takes
them (:class:`~companion.fleetnet.neighbour_inbox.NeighbourInbox`). It takes an open session
and opens nothing.
"""

from __future__ import annotations

import numpy as np

from companion.fleetnet import codec
from companion.fleetnet.keys import neighbour_key
from companion.messages import NeighbourPose

from .node_config import NeighbourCamera

__all__ = ["neighbour_poses", "NeighbourPublisher"]


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


class NeighbourPublisher:
    """Publishes neighbour poses on ``session`` under ``prefix``: one publisher per observing link
    of ``observers`` (0-based), declared at once so that :attr:`matched` can say whether a
    companion takes them before the first frame; a pose of another link is refused."""

    def __init__(self, session, prefix: str, observers):
        import zenoh

        self.session = session
        self.prefix = prefix
        # a pose is small and a late one is useless: sent at once, never queued behind frames
        self._pubs = {i: session.declare_publisher(neighbour_key(prefix, i), congestion_control=zenoh.CongestionControl.DROP,
                                                   priority=zenoh.Priority.INTERACTIVE_HIGH, express=True)
                      for i in sorted(set(observers))}
        self.published = 0

    @property
    def matched(self) -> bool:
        """Whether every observer's key has a subscriber now (a companion that takes its poses)."""
        return all(bool(p.matching_status.matching) for p in self._pubs.values())

    def publish(self, pose: NeighbourPose) -> None:
        pub = self._pubs.get(pose.observer)
        if pub is None:
            raise ValueError(f"link {pose.observer + 1} is not an observer of this publisher")
        pub.put(codec.encode(pose))
        self.published += 1

    def close(self) -> None:
        for pub in self._pubs.values():
            try:
                pub.undeclare()
            except Exception:  # noqa: BLE001 - the session may be closing already
                pass
        self._pubs = {}
