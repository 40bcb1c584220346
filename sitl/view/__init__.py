"""The browser 3D view of a run, live (``python -m sitl fly ... --view``, ``launch ... --view``) or
replayed (``python -m sitl view RUN_DIR``), served by viser on a local port.

:mod:`.frame` (what one instant shows), :mod:`.timeline` (a finished run by time), :mod:`.spec`
(the fixed scene) and :mod:`.live` (a flying run's newest rows) are pure; :mod:`.scene`,
:mod:`.panel` and :mod:`.app` are the viser shell (the ``view`` extra); :mod:`.browser` drives a
headless Chromium for the tests and the screenshots.
"""
