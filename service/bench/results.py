"""What a benchmark run keeps on disk besides report.md: results.json (merged with the parts of
an earlier run of the same kind, full or --smoke, that this one did not redo) and each part's
rows as CSV."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
from pathlib import Path

import numpy as np

#: the parts a report holds, in the order `elastreg bench` runs them
PARTS = ("fem", "liver", "beam", "pareto", "stability", "anysite", "minutes")
#: the minutes part's rows, written into a run's scratch folder after each build (hours each)
MINUTES_ROWS = "minutes_rows.json"
#: what every minutes row holds: what merge(), latest() and --resume read
MINUTES_KEYS = ("scene", "minutes", "commit", "cpu", "started")


def jsonable(x):
    """What json cannot write by itself: dataclasses, NumPy scalars and arrays, paths."""
    if dataclasses.is_dataclass(x):
        return dataclasses.asdict(x)
    if isinstance(x, (np.integer, np.floating, np.bool_)):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(type(x).__name__)


def write_csv(path: Path, rows: list[dict]) -> None:
    """Rows (dicts or dataclasses) as CSV, list and dict cells as JSON; nothing for no rows."""
    if not rows:
        return
    rows = [dataclasses.asdict(r) if dataclasses.is_dataclass(r) else r for r in rows]
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: json.dumps(v, default=jsonable) if isinstance(v, (list, dict)) else v for k, v in r.items()})


def write_results(results: dict, out: Path) -> None:
    """results.json: every part's rows and records, what the report is drawn from."""
    (out / "results.json").write_text(json.dumps(results, indent=1, default=jsonable))


def write_minutes_rows(folder: Path, rows: list[dict]) -> None:
    """minutes_rows.json: the minutes part's rows, also written into the run's scratch folder after
    each build, so that an hour-long build's row survives a later failure or a kill (the folder
    set aside, :func:`.swap.set_aside`)."""
    (folder / MINUTES_ROWS).write_text(json.dumps(rows, indent=1, default=jsonable))


def minutes_row_problem(row, keys: tuple[str, ...] = MINUTES_KEYS) -> str | None:
    """What keeps `row` from being a minutes part's row (one line), or None: its `keys` (a
    report's oldest rows lack the stamps a resumed row is checked by), and its budget a finite
    positive number (a NaN, negative or true one crashed the plot)."""
    if not isinstance(row, dict) or not all(k in row for k in keys):
        return f"a row lacks one of {', '.join(keys)}"
    m = row["minutes"]
    if isinstance(m, bool) or not isinstance(m, (int, float)) or not math.isfinite(m) or m <= 0:
        return f"its row for {row['scene']} has minutes {m!r}, not a positive finite number"
    return None


def read_minutes_rows(path: Path) -> list[dict]:
    """The minutes rows a stopped run set aside: `path` its folder (``NAME.interrupted-TIME``) or
    its minutes_rows.json; ValueError, one line, where it holds none or a row is not one."""
    file = path / MINUTES_ROWS if path.is_dir() else path
    try:
        rows = json.loads(file.read_text())
    except OSError as exc:
        raise ValueError(f"cannot read {file}: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise ValueError(f"{file} is not JSON ({exc})") from None
    if not isinstance(rows, list):
        raise ValueError(f"{file} holds no minutes part's rows (a list of rows, each with {', '.join(MINUTES_KEYS)})")
    for r in rows:
        if problem := minutes_row_problem(r):
            raise ValueError(f"{file} holds no minutes part's rows: {problem}")
    return rows


def merge_previous(results: dict, out: Path | None) -> dict:
    """Keep the parts of the report already in `out` that this run did not redo, so that
    ``elastreg bench beam`` refreshes one part without rerunning the hour-long rest (none where
    `out` is None: ``--replace``). Each part remembers the run that made it, and whether that
    was a --quick one (None: not recorded). Only a report of the same kind is kept from: a smoke
    run's tiny-model figures never sit beside a full run's (``results["smoke"]``: the smoke
    model)."""
    from .cases import FrameRecord

    stamp = {"started": results["started"], "commit": results["machine"]["commit"], "cpu": results["machine"]["cpu"],
             "quick": bool(results.get("quick"))}  # fmt: skip
    results["made_by"] = {part: stamp for part in results["parts"]}
    prior = None if out is None else prior_run(out)
    if prior is None or prior.get("smoke") != results.get("smoke"):
        return results
    machine = prior.get("machine", {})
    old_stamp = {"started": prior.get("started"), "commit": machine.get("commit"), "cpu": machine.get("cpu"),
                 "quick": prior.get("quick")}  # fmt: skip
    for part, value in prior.get("parts", {}).items():
        if part in results["parts"] or part not in PARTS:
            continue
        if isinstance(value, dict) and "records" in value:  # per-frame records: back to objects
            value["records"] = [FrameRecord(**r) for r in value["records"]]
        results["parts"][part] = value
        # a stamp from before stamps named the CPU: taken to be the prior run's machine
        results["made_by"][part] = {"cpu": machine.get("cpu"), **prior.get("made_by", {}).get(part, old_stamp)}
    return results


#: a stand-in machine for drawing a kept part on its own (prior_problem)
_NO_MACHINE = dict.fromkeys(("cpu", "cores", "gpu", "commit", "sparse_solver", "torch", "numpy", "scipy"), "-")


def prior_problem(out: Path, redone: list[str], smoke: str | None) -> str | None:
    """Why the report in `out` cannot be merged with a run of the parts `redone` (one line), or
    None: each part the run would keep (the minutes part's rows, which it extends, too) is
    merged and drawn on its own into a throwaway folder before any work; a results.json of the
    wrong shape crashed only once every part had run, and the new report was lost."""
    import tempfile

    from .markdown import write_report

    prior = prior_run(out)
    if prior is None or prior.get("smoke") != smoke:
        return None  # nothing kept from it: the run replaces it whole
    if not isinstance(prior.get("parts", {}), dict):
        return "its parts are not a mapping of part names to their results"
    kept = [p for p in prior.get("parts", {}) if p in PARTS and (p not in redone or p == "minutes")]
    minutes = prior["parts"].get("minutes") if "minutes" in kept else {"rows": []}
    if not isinstance(minutes, dict) or not isinstance(minutes.get("rows"), list):
        return "its minutes part holds no list of rows"
    for r in minutes["rows"]:
        if problem := minutes_row_problem(r, ("scene", "minutes")):
            return f"its minutes part: {problem}"
    stub = {"started": "-", "smoke": smoke, "seconds": 0.0, "machine": _NO_MACHINE, "parts": {}}
    try:
        merged = merge_previous(dict(stub), out)
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
        return f"it cannot be merged ({_one_line(exc)})"
    for part in kept:
        alone = {**merged, "parts": {part: merged["parts"][part]}, "made_by": {}}
        with tempfile.TemporaryDirectory() as tmp:
            (Path(tmp) / "figures").mkdir()
            try:
                write_report(alone, Path(tmp))
            except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
                return f"its {part} part cannot be drawn ({_one_line(exc)})"
    return None


def _one_line(exc: Exception) -> str:
    return f"{type(exc).__name__}: " + " ".join(str(exc).split())


def prior_run(out: Path) -> dict | None:
    """The results.json of the report already in `out`, or None (none there, or unreadable).
    Its ``smoke`` names the model of a --smoke run; a full run's has none (nor has a report
    from before smoke runs were marked: all were full runs)."""
    try:
        prior = json.loads((out / "results.json").read_text())
    except (OSError, ValueError):
        return None
    return prior if isinstance(prior, dict) else None


def prior_part(out: Path, part: str) -> dict | None:
    """A part of the report already in `out`, or None."""
    return (prior_run(out) or {}).get("parts", {}).get(part)
