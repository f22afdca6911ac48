"""Error against run time: which points the Pareto front ranks."""

from service.bench.pareto import pareto_front, plot


def test_a_point_with_failed_frames_is_not_ranked(tmp_path):
    """A point whose frames partly failed had its mean TRE over the others and could lead the
    front (here the faster point, 0.5 mm on its finite frames): it is now left off the front,
    and drawn apart in the chart."""
    rows = [{"method": "network", "knob": "gtol", "value": 1e-2, "tre_mm": 0.5, "force_error_pct": 5.0, "ms": 5.0,
             "failed_frames": 2},
            {"method": "network", "knob": "gtol", "value": 1e-4, "tre_mm": 0.6, "force_error_pct": 6.0, "ms": 8.0,
             "failed_frames": 0}]  # fmt: skip
    assert [r["value"] for r in pareto_front(rows)] == [1e-4]
    assert [r["value"] for r in pareto_front(rows, "force_error_pct")] == [1e-4]
    plot(rows, tmp_path / "pareto.png", "a sweep")
    assert (tmp_path / "pareto.png").stat().st_size > 1000
