"""fusionlog: multi-sensor state estimation experiments logged to MCAP and Rerun."""

__version__ = "0.1.0"
