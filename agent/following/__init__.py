"""Person following (``docs/following.md``): pure algorithms, numpy arrays and small dataclasses in,
estimates out, time passed in; no threads, files or ports.

Modules: ``coarse`` (the RFID layer: a recursive Bayes filter over bearing sectors and range bins from the
reader's per-antenna reads, with its likelihood table), ``person`` (the laser person detector and the
person's track in the map frame: a constant-velocity Kalman filter with gating), ``follower`` (the
follower's velocity command and states, and the walkers' checks).
"""
