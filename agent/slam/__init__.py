"""Laser SLAM and localization: occupancy grid, scan matching, particle filters, logs and map files.

Algorithm cores (pure numpy and OpenCV arithmetic, no I/O, no printing, seeded randomness):

* ``pose``: SE(2) poses as arrays (compose, inverse, between).
* ``scan``: the laser's geometry and the gate that rejects bad scans with a counted reason.
* ``grid``: log-odds occupancy grid in copy-on-write tiles; scan integration (ray casting by polygon fill).
* ``matcher``: distance-field (likelihood-field) scan matching: Gauss-Newton, correlative search.
* ``motion``: GMapping's odometry motion model.
* ``proposal``: GMapping's improved proposal, batched over particles.
* ``fix``: absolute pose fixes (VLP) as measurements in the weights.
* ``rbpf``: the Rao-Blackwellized particle filter SLAM (per-particle or shared maps).
* ``mcl``: localization only, on a saved map, started from a fix.
* ``metrics``: relative-pose error, trajectory error, wall thickness.
* ``render``: map and trajectory pictures as arrays.

At the edges, and the only modules here that touch files: ``logs`` (BreezySLAM and radish log readers),
``mapio`` (ROS map_server PGM + YAML, PNG, atomic writes). ``replay`` runs a log through the filter.
``docs/slam.md`` has the design, the choices and the measurements.
"""
