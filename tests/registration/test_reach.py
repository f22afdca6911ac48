"""How far from its model a cloud may lie: the session's check (check_reach) on the bar's box."""

import numpy as np
import pytest

from service.registration.reach import Box, check_reach
from service.synthetic import sample_surface


def test_a_cloud_in_metres_against_a_model_in_millimetres_is_refused(bar):
    """The bar built in millimetres (4,243 mm corner to corner) and its cloud in metres: near the
    origin, inside the model's box, it passed the reach and was registered to nonsense. A cloud
    spanning under 1/200 of the model's size is refused in one line naming the unit mistake; a
    camera's partial view (a few percent of it) and a cloud of 2-3 points are not."""
    mm = Box(1e3 * bar.nodes)
    metres, _, _ = sample_surface(bar.nodes, bar.surface_faces, 4000, np.random.default_rng(0))
    with pytest.raises(ValueError, match="spans 4.2.*is the cloud in metres while the model is in millimetres") as err:
        check_reach(mm, metres)
    assert "\n" not in str(err.value)
    view = 1e3 * metres[np.linalg.norm(metres - metres[0], axis=1) < 0.03 * np.sqrt(18)]  # 3 % of its size
    assert len(view) >= 4 and np.linalg.norm(np.ptp(view, axis=0)) > mm.size / 200
    check_reach(mm, view)
    for few in (metres[:1], metres[:2], metres[:3]):
        check_reach(mm, few)
    check_reach(Box(bar.nodes), metres)  # the same cloud against the bar in metres


def test_a_point_past_the_squares_range_reads_its_distance(bar):
    """A point 1e300 m off: its squared distance overflowed, and the detail read "the farthest
    inf m". Its distance is read without squares; past a double's range, the detail says so."""
    box = Box(bar.nodes)
    near = bar.nodes[:3]
    with pytest.raises(ValueError, match=r"the farthest 1e\+300 m;"):
        check_reach(box, np.vstack([near, [[0.0, 1e300, 0.0]]]))
    np.testing.assert_allclose(box.offsets(np.array([[0.0, 0.5, 3e300 + 0.5]])), [3e300])
    with pytest.raises(ValueError, match="the farthest beyond float range;"):
        check_reach(box, np.vstack([near, [[1.7e308, -1.7e308, 0.0]]]))
    with pytest.raises(ValueError, match=r"the median point is 1e\+300 m from"):
        check_reach(box, np.tile([0.0, 0.5, 1e300], (3, 1)))
