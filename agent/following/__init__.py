"""Person following (``docs/following.md``): pure algorithms, numpy arrays and small dataclasses in,
estimates out, time passed in; no threads, files or ports.

* ``coarse``: the RFID layer: a recursive Bayes filter over bearing sectors and range bins from the
  reader's per-antenna reads, with its likelihood table.
* ``lbp``: local binary patterns, the texture feature.
* ``meanshift``: multi-feature mean shift (colour and LBP texture under a silhouette kernel), with scale,
  occlusion, coasting and re-acquisition; the colour-only baseline is the same code.
* ``prelocate``: the head-shoulder pre-locator (OpenCV 4.x HOG people detector or the upper-body cascade
  shipped with OpenCV; no model download) that starts and re-acquires the tracker.
* ``fine``: the two together: the pre-locator starts the tracker in the coarse layer's band and feeds it
  re-acquisition hints while the target is hidden.
* ``synthetic``: a seeded scene with exact ground truth (a same-colour passer-by crossing the target).
* ``otb``: OTB-style sequences and their scores, for ``vlp-agent eval track``.
* ``person``: the laser person detector and the person's track in the map frame (a constant-velocity
  Kalman filter with gating).
* ``follower``: the follower's velocity command and states, and the walkers' checks.
"""
