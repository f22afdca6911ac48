"""Exact point-to-surface distance of a point cloud, with its gradient in the vertex positions.

The registration objective of one frame is

    J(x) = 1 / (2 m) * sum_j rho(d(y_j, S(x)))

with y_j (m, 3) the frame's cloud, S(x) the matching triangles at vertex positions x and d the
exact Euclidean point-to-triangle distance. By the envelope theorem the closest point c_j (on
triangle t_j, barycentric weights w_j) may be held fixed when differentiating, so
d(d_j^2)/dx_v = 2 (c_j - y_j) w_jv on the three vertices of t_j: the gradient is one weighted
scatter onto the nodes.

:class:`PointToSurface` is evaluated tens of times per frame, so each point only looks at a few
candidate triangles, chosen when an index is built (from a bounding-volume hierarchy in the
compiled backend, a k-d tree over the centroids in the numpy one) and kept while the surface
moves less than a margin; the candidate rule is exact (docs/distance.md). Indices and
spatial structures are per-session mutable state: one object per session, never shared between
threads.

    geometry.py          one point against one triangle, vectorised over pairs (NumPy)
    kernels.py           the same, and the index's searches, as numba kernels (service/jit.py)
    index.py             the candidate index: built, kept for a frame's returns, looked up
    point_to_surface.py  PointToSurface: the objective, its gradient, the closest points
"""

from ...jit import available as numba_available
from .geometry import closest_point_on_triangles
from .index import NonFinitePositions
from .point_to_surface import Closest, Match, PointToSurface

__all__ = ["Closest", "Match", "NonFinitePositions", "PointToSurface", "closest_point_on_triangles", "numba_available"]
