"""The root of the project's one exception tree, and the protocol branch of it.

The tree is split by whose fault an error is:

* :class:`ProtocolError` (here): the bytes on a wire are wrong. Carries the bytes and a reason.
* ``drivers.errors.DeviceError`` and its children: a device misbehaves, vanishes or is too slow.
* ``drivers.errors.ConfigError``: a file a person wrote (config, world, calibration) is wrong.

It lives in ``firmware_protocol`` because that package sits at the bottom of the dependency order
(``firmware_protocol`` <- ``drivers`` <- ``agent``), so every layer can share one root.
"""

from __future__ import annotations


class VlpAgentError(Exception):
    """Base of every error that vlp-agent raises on purpose."""


class ProtocolError(VlpAgentError):
    """Bytes that do not follow a protocol.

    ``data`` holds the offending bytes (a frame, a line, or the start of the junk) so that a log line
    can show exactly what came over the wire.
    """

    def __init__(self, reason: str, data: bytes = b"") -> None:
        self.reason = reason
        self.data = bytes(data)
        shown = self.data[:64].hex(" ")
        more = "" if len(self.data) <= 64 else f" ... ({len(self.data)} bytes)"
        super().__init__(f"{reason} [{shown}{more}]" if self.data else reason)
