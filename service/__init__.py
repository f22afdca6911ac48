"""elastreg: real-time elastic registration of organ meshes to partial point clouds."""

__version__ = "0.1.0"
