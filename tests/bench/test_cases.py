"""The cases' scoring: what a summary says of the frames it is over."""

import math

from service.bench.cases import FrameRecord, summarise
from service.bench.markdown import write_report

NAN = float("nan")


def frames(good: int, failed: int) -> list[FrameRecord]:
    """`good` frames at 0.5 mm and `failed` ones whose answer held a NaN (as score() records them)."""
    ok = [FrameRecord("c", "network", k, 0.5, 10.0, 10.0, 5, 6, "converged", True, True) for k in range(good)]
    return ok + [FrameRecord("c", "network", good + k, NAN, NAN, 10.0, 5, 6, "non_finite", False, False)
                 for k in range(failed)]  # fmt: skip


def test_a_failed_frame_is_counted_and_makes_the_worst_frame_infinite(tmp_path):
    """summarise() took nanmean/nanmax: two failed frames of ten dropped out of "mean TRE" and
    "worst frame TRE" and the liver table said nothing of them. They are now counted, the worst
    frame's TRE is infinite, and the table says both."""
    s = summarise(frames(8, 2))
    assert s["failed_frames"] == 2 and s["frames"] == 10 and not s["all_finite"]
    assert math.isinf(s["tre_max_mm"]) and s["tre_mean_mm"] == 0.5  # the mean: over the frames that did not fail
    clean = summarise(frames(8, 0))
    assert clean["failed_frames"] == 0 and clean["tre_max_mm"] == 0.5
    out = tmp_path / "report"
    (out / "figures").mkdir(parents=True)
    machine = dict.fromkeys(("cpu", "cores", "gpu", "commit", "sparse_solver", "torch", "numpy", "scipy"), "-")
    results = {"machine": machine, "started": "-", "seconds": 1.0,
               "parts": {"liver": {"records": frames(8, 2), "summaries": [s]}}}  # fmt: skip
    write_report(results, out)
    lines = (out / "report.md").read_text().splitlines()
    head = next(line for line in lines if line.startswith("| case |")).split(" | ")
    row = next(line for line in lines if line.startswith("| c |")).split(" | ")
    assert row[head.index("worst frame TRE (mm)")] == "inf" and row[head.index("failed frames")] == "2"
