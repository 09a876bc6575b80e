"""Device drivers: one interface per device kind, real backends chosen by name, and fakes that speak the
same bytes as the hardware (``drivers.fakes``) over the simulated world (``drivers.sim``)."""
