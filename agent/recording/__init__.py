"""The flight recorder: every sample the agent's devices and loops produce, as MCAP (docs/recording.md).

``schemas`` (the channels' JSON schemas) and ``messages`` (samples -> channel messages) are pure;
``writer`` is the recorder the runtime feeds (bounded queue, writer thread, chunks by time, rotation, a
total cap, a free-disk guard); ``reader`` reads a recording back, up to where a cut file stops being whole.
"""
