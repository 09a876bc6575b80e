"""Fake devices that speak the real wire bytes, served on pseudo-terminals (or in-process) over the
simulated world. Imported only by the simulation wiring, the ``vlp-agent fake`` command and tests."""
