"""The slung load: a load carried by cables from several vehicles, its pose estimated from their
cameras and their own state estimates (the slung-load report's eq. 4 and eq. 8), and the
formation that carries it.

* :mod:`.model`: the load's state on SE(3), its dynamics (eq. 8, cable tensions estimated), the
  typed inputs (vehicle samples, camera observations);
* :mod:`.measurements`: eq. 4, the load's attitude the marker shows, the taut cables' lengths;
* :mod:`.estimate`: the filters' tuning, estimate, prior and process noise;
* :mod:`.kalman`: the error-state EKF's and the manifold UKF's prediction and correction;
* :mod:`.filter`: the time line of vehicle samples and images, late images rolled back and
  replayed;
* :mod:`.unfiltered`: the camera-only baseline, the pose solved from the latest images;
* :mod:`.pipeline`: a camera frame through the marker pipeline (:mod:`companion.vision`) to an
  eq. 4 measurement;
* :mod:`.metrics`: the pose and PnP errors, NEES and timing summaries;
* :mod:`.tracker`: the filters as a carrying companion keeps them, fed with its link states and
  the vision consumer's observations, with their log;
* :mod:`.config`: the ``[load]`` table (:class:`~.config.LoadConfig`: the box, the cables, the
  marker pipeline's settings, the filters' tuning, the formation's circle);
* :mod:`.formation`: the formation carrying the load around its circle, every vehicle's target
  with its cable's feed-forward force (the companion's target source for
  ``trajectory.kind = "formation"``).

Pure: no sockets, clocks or threads. numpy only, except :mod:`.pipeline` (OpenCV through
:mod:`companion.vision.pnp`, the ``vision`` extra).
"""
