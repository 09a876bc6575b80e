"""vlp-agent: the on-board process (CLI, config, runtime loop) and its algorithms (VLP, SLAM, fusion)."""

__version__ = "0.1.0"
