"""Vision measurement (the report ``004_946c2b2ab3d872ae.txt``): cameras, ArUco markers, PnP.

Pure code: images in, poses and covariances out; no sockets, clocks or threads -- except the
shells :mod:`.camera_wire` (on a caller's Zenoh session) and :mod:`.node` (the consumer's sources
and loop).

* :mod:`.geometry` -- camera intrinsics (from a field of view), the pinhole projection of the
  report's eq. 1 and its Jacobian, the camera-axes conventions, the report's error metrics
  (eq. 2 translation error, eq. 3 geodesic angle). numpy only.
* :mod:`.frame` -- :class:`~.frame.CameraFrame`, one image with a typed, versioned header
  (what a camera delivers, in the SITL or on the onboard computer). numpy only.
* :mod:`.markers` -- ArUco dictionaries, marker images, detection with corner refinement (OpenCV).
* :mod:`.pnp` -- PnP (IPPE square, P3P, SQPnP, iterative), the IPPE two-fold ambiguity, a
  covariance per detection, and the image-to-pose pipeline (OpenCV).
* :mod:`.frame_codec`, :mod:`.camera_wire` -- frames as bytes (versioned header + image) and over
  Zenoh on ``<prefix>/camera/<vehicle>/image``.
* :mod:`.node_config`, :mod:`.node` and ``python -m companion.vision`` -- the vision consumer: frames
  from Zenoh or a ``cv2.VideoCapture`` source through the pipeline, a per-frame log and a summary.

OpenCV (``cv2``) is imported only by :mod:`.markers` and :mod:`.pnp` (and, when used, by the codec's
PNG/JPEG path and the consumer's ``VideoCapture`` source); it belongs to the ``vision``
extra, never to the onboard base install, so importing this package (or :mod:`.geometry`,
:mod:`.frame`) does not need it.
"""
