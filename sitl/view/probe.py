"""JavaScript that looks into the view's three.js scene from a browser (tests, screenshots).

:data:`OBSERVE_SCENES` (run before the page's scripts) keeps every three.js ``Scene`` the page
makes, through three.js's developer-tools hook; :func:`links_shown_js` counts the given link
positions that some node of those scenes holds: its position in its parent's frame, which for the
view's ``/links/link<i>`` nodes is the run's world frame; :data:`DISMISS_NOTICES` closes the
notices over the scene, :data:`NEXT_FRAMES` waits until it is drawn.
"""

from __future__ import annotations

import json

import numpy as np

__all__ = ["OBSERVE_SCENES", "DISMISS_NOTICES", "NEXT_FRAMES", "links_shown_js"]

OBSERVE_SCENES = """
window.__THREE_DEVTOOLS__ = new EventTarget();
window.__skeletonScenes = [];
window.__THREE_DEVTOOLS__.addEventListener('observe', (e) => {
  if (e.detail && e.detail.isScene) window.__skeletonScenes.push(e.detail);
});
"""

#: closes the client's notices (viser's "software WebGL rendering" one in a headless browser)
DISMISS_NOTICES = "document.querySelectorAll('.mantine-Notification-root button').forEach((b) => b.click())"

#: a promise that resolves after the page has drawn two more frames (what the scene holds is on screen)
NEXT_FRAMES = "new Promise((done) => requestAnimationFrame(() => requestAnimationFrame(() => done(true))))"


def links_shown_js(p_w_m: np.ndarray, tol_m: float = 1e-3) -> str:
    """An expression whose value is how many of the positions ``p_w_m`` (n, 3) a node of the
    page's scenes stands at (each position counted once)."""
    points = json.dumps(np.asarray(p_w_m, dtype=float).round(6).tolist())
    return f"""(() => {{
  const want = {points}, tol = {float(tol_m)};
  const found = new Set();
  for (const scene of window.__skeletonScenes || []) {{
    scene.traverse((o) => {{
      const e = o.position;
      want.forEach((p, i) => {{
        if (Math.abs(e.x - p[0]) < tol && Math.abs(e.y - p[1]) < tol && Math.abs(e.z - p[2]) < tol) found.add(i);
      }});
    }});
  }}
  return found.size;
}})()"""
