"""The slung load's pose estimator: a load carried by cables from several vehicles, its pose from
their cameras and their own state estimates (the slung-load report's eq. 4 and eq. 8).

* :mod:`.model`: the load's state on SE(3), its dynamics (eq. 8, cable tensions estimated) and the
  camera measurement (eq. 4);
* :mod:`.filter`: the error-state EKF, the UKF with sigma points on the manifold, the unfiltered
  baseline, late images rolled back and replayed;
* :mod:`.pipeline`: a camera frame through the marker pipeline (:mod:`companion.vision`) to an
  eq. 4 measurement;
* :mod:`.metrics`: the pose and PnP errors, NEES and timing summaries.

Pure: no sockets, clocks or threads. numpy only, except :mod:`.pipeline` (OpenCV through
:mod:`companion.vision.pnp`, the ``vision`` extra).
"""
