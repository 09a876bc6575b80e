"""Pure byte codecs for every wire the agent speaks: no I/O, standard library only.

Each codec takes bytes in and gives typed frozen dataclasses (or "need more data") out, resyncs on junk,
bounds its buffer, and raises its own :class:`~firmware_protocol.errors.ProtocolError` subclass carrying
the offending bytes.
"""
