"""RFID readers: the :class:`RfidReader` interface and its serial backends (chosen by name in the registry:
"id12la", "rdm6300", "mercury")."""

from drivers.rfid.base import RfidReader

__all__ = ["RfidReader"]
