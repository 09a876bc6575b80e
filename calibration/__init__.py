"""The calibration wizard and its steps: ``vlp-agent calibrate`` (docs/calibration.md).

One module per step (``intrinsics``, ``mount``, ``leds``, ``vlp_error``, ``laser``, ``wheels``, ``servos``),
each with the measurement as pure functions and a ``run`` that collects the data from the robot (or the
simulated robot), checks the result against stated thresholds and saves its files atomically with a backup
of the previous version (``files``). ``wizard`` is the interactive menu over the same steps. The package never
prints: it talks through a :class:`~calibration.report.Console` that the command module provides.
"""
