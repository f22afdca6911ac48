"""The stability part: what breaks on stiff and extreme cases is reported, never hidden."""

from service.bench.parts import smoke_case
from service.bench.stability import stability_part


def test_a_crashed_row_counts_the_frames_it_made(entry):
    """A row's frames_made was the case's frame count even where the case crashed at its second
    frame: it now counts the frames made, and keeps their records."""
    case = smoke_case(entry)
    far = case.clouds[1] * 1e6  # a registration refuses a cloud far from the model: the base's cases crash here
    case = case.with_clouds([case.clouds[0], far, case.clouds[2]])
    max_force = float(entry.manifest["training"]["load_distribution"]["max_force"])
    part = stability_part(entry, case, frames=2, fem=False, tool_size=4, peak_force=0.3 * max_force,
                          far=0.25 * entry.mesh.size)  # fmt: skip
    crashed = [r for r in part["rows"] if r["crashed"]]
    assert crashed and all(r["frames_made"] == 1 for r in crashed), crashed
    assert all("too far from the model" in r["error"] for r in crashed)
    whole = [r for r in part["rows"] if not r["crashed"]]
    assert whole and all(r["frames_made"] == r["frames"] == 2 for r in whole)
    made = {(r.case, r.method) for r in part["records"]}
    assert all((r["case"], r["method"]) in made for r in crashed)  # the frame before the crash kept
