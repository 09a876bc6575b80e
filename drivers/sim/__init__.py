"""The simulated world that the fake devices draw their data from: floor plan, ceiling LEDs, the robot,
people with RFID tags, and ground truth for all of it (``world``: the description, ``worldfile``: TOML
loading, ``simulation``: the moving state, ``raycast``: laser geometry, ``render``: the camera)."""
