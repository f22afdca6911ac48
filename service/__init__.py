"""elastreg: real-time elastic registration of organ meshes to partial point clouds."""

__version__ = "0.1.0"

import os

# OpenMP's idle threads spin 300,000 times by default (libgomp, which MKL's factorisations share
# with torch): a few ms that take the spare core from a frame's other work. Read when libgomp
# loads, so it is set before anything imports torch; a caller's own setting wins.
os.environ.setdefault("GOMP_SPINCOUNT", "10000")
