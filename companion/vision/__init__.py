"""Vision measurement (the report ``004_946c2b2ab3d872ae.txt``): cameras, ArUco markers, PnP.

Pure code: images in, poses and covariances out; no sockets, clocks or threads.

* :mod:`.geometry` -- camera intrinsics (from a field of view), the pinhole projection of the
  report's eq. 1 and its Jacobian, the camera-axes conventions, the report's error metrics
  (eq. 2 translation error, eq. 3 geodesic angle). numpy only.
* :mod:`.frame` -- :class:`~.frame.CameraFrame`, one image with a typed, versioned header
  (what a camera delivers, in the SITL or on the onboard computer). numpy only.
* :mod:`.markers` -- ArUco dictionaries, marker images, detection with corner refinement (OpenCV).
* :mod:`.pnp` -- PnP (IPPE square, P3P, SQPnP, iterative), the IPPE two-fold ambiguity, a
  covariance per detection, and the image-to-pose pipeline (OpenCV).

OpenCV (``cv2``) is imported only by :mod:`.markers` and :mod:`.pnp`; it belongs to the ``vision``
extra, never to the onboard base install, so importing this package (or :mod:`.geometry`,
:mod:`.frame`) does not need it.
"""
