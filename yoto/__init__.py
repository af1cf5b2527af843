"""YOTO: 6-DoF object pose from one simultaneous pair of GelSight tactile contacts."""

__version__ = "0.1.0"
