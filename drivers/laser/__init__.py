"""Scanning laser rangefinders: the interface (``base``) and backends (``urg``: Hokuyo SCIP 2.0)."""

from drivers.laser.base import LaserInfo, LaserScanner

__all__ = ["LaserInfo", "LaserScanner"]
