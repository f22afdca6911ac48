"""Training data: the load sampler, path solves, and resumable generation (in-process and Dask)."""

import os
import re
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from service.fem.material import NeoHookean
from service.surrogate.data import (
    LoadSpec,
    done_indices,
    generate,
    load_dataset,
    path_file,
    sample_path_load,
    solve_path,
    write_path,
)
from service.surrogate.pathfiles import VERIFIED
from tests.conftest import small_disk

MAT = NeoHookean(4500.0, 0.45)


@pytest.fixture(scope="module")
def spec(bar):
    region = bar.free_surface_nodes[bar.nodes[bar.free_surface_nodes, 0] > 1.0]
    return LoadSpec(region=tuple(region.tolist()), max_force=60.0, patch_nodes=(3, 6), steps=3, multi_patch=0.3)


def test_loads_stay_in_the_region_and_under_the_cap(bar, spec):
    rng = np.random.default_rng(0)
    for _ in range(50):
        g = sample_path_load(bar, spec, rng)
        assert g.shape == (len(spec.region), 3)
        assert np.linalg.norm(g.sum(axis=0)) <= spec.max_force + 1e-9
        loaded = np.count_nonzero(np.abs(g).sum(1))
        assert 3 <= loaded <= 12  # one or two patches of 3..6 nodes


def test_pulls_dominate_when_asked(bar, spec):
    from dataclasses import replace

    pulls = replace(spec, pull_fraction=1.0, normal_fraction=0.9, multi_patch=0.0)
    rng = np.random.default_rng(1)
    normals = bar.vertex_normals[np.asarray(spec.region)]
    outward = [np.sum(sample_path_load(bar, pulls, rng) * normals) > 0 for _ in range(30)]
    assert all(outward)


def test_a_path_is_a_pure_function_of_its_index(bar, spec):
    a, b = solve_path(bar, MAT, spec, 7), solve_path(bar, MAT, spec, 7)
    np.testing.assert_array_equal(a["forces"], b["forces"])
    np.testing.assert_array_equal(a["u"], b["u"])
    assert len(a["forces"]) == spec.steps  # every step converged
    np.testing.assert_allclose(a["forces"][0] * 3, a["forces"][2], rtol=1e-5)  # equal steps


def test_a_newton_cap_stops_a_path_at_the_first_step_that_needs_more(bar, spec):
    """A timed build's cap: the steps before the first costly one are kept, and they are the
    uncapped path's samples to the bit."""
    free = solve_path(bar, MAT, spec, 7)
    its = free["newton_iterations"]
    cap = int(its.max()) - 1  # the path's hardest step no longer fits
    first_over = int(np.argmax(its > cap))
    capped = solve_path(bar, MAT, spec, 7, max_newton=cap)
    assert len(capped["forces"]) == first_over < len(free["forces"])
    np.testing.assert_array_equal(capped["u"], free["u"][:first_over])
    np.testing.assert_array_equal(capped["newton_iterations"], its[:first_over])
    generous = solve_path(bar, MAT, spec, 7, max_newton=int(its.max()))
    np.testing.assert_array_equal(generous["u"], free["u"])


def test_generation_resumes_without_losing_or_redoing_paths(tmp_path, bar, spec):
    out = tmp_path / "data"
    assert len(list(generate(bar, MAT, spec, out, 6, workers=0, progress=False))) == 6
    before = {i: path_file(out, i).stat().st_mtime_ns for i in range(6)}
    path_file(out, 2).unlink()  # an interrupted run: one path lost...
    (out / ".path_000004.tmp.npz").write_bytes(b"half written")  # ...one half-written
    redone = [r["index"] for r in generate(bar, MAT, spec, out, 6, workers=0, progress=False)]
    assert redone == [2]
    assert done_indices(out) == set(range(6))
    assert all(path_file(out, i).stat().st_mtime_ns == before[i] for i in (0, 1, 3, 4, 5))
    F, U, P = load_dataset(out)
    assert F.shape == (18, len(spec.region), 3) and U.shape == (18, bar.n_nodes, 3)
    np.testing.assert_array_equal(np.unique(P), np.arange(6))


def killed_mid_write(data_dir, index: int):
    """The temporary that write_path leaves when its process is killed (its own mkstemp name)."""
    fd, name = tempfile.mkstemp(prefix=f".{path_file(data_dir, index).stem}-", suffix=".tmp.npz", dir=data_dir)
    os.write(fd, b"half written")
    os.close(fd)
    return Path(name)


def test_a_build_removes_the_temporaries_of_one_killed_mid_write(tmp_path, bar, spec):
    """A build killed mid-write left .path_NNNNNN-XXXXXXXX.tmp.npz files that nothing removed:
    the next generation on the folder removes them, and nothing else."""
    out = tmp_path / "data"
    out.mkdir()
    left = [killed_mid_write(out, i) for i in (0, 5)]
    kept = [out / ".path_000004.tmp.npz", out / "notes.tmp.npz", out / ".path_000001-abc.tmp.npz"]
    for path in kept:
        path.write_bytes(b"not write_path's")
    assert len(list(generate(bar, MAT, spec, out, 2, workers=0, progress=False))) == 2
    assert not any(path.exists() for path in left)
    assert all(path.exists() for path in kept)
    assert done_indices(out) == {0, 1}


def test_a_build_leaves_the_temporaries_of_another_writing_the_folder(tmp_path, bar, spec):
    """Two builds of one scene share its data folder: one that starts while the other writes
    must not take the other's path in flight for a leftover."""
    out = tmp_path / "data"
    first = generate(bar, MAT, spec, out, 6, workers=0, progress=False)
    next(first)  # the first build holds the folder, between two of its paths
    in_flight = killed_mid_write(out, 3)  # as its next write would be
    list(generate(bar, MAT, spec, out, 2, workers=0, progress=False))  # a second build, meanwhile
    assert in_flight.exists()
    first.close()  # the first build ends (or is killed): its temporaries are leftovers now
    list(generate(bar, MAT, spec, out, 2, workers=0, progress=False))
    assert not in_flight.exists()


def test_dask_cluster_gives_the_same_samples(tmp_path, bar, spec):
    # more paths than a worker keeps in flight (PATHS_PER_THREAD): the topped-up ones count too
    local = list(generate(bar, MAT, spec, tmp_path / "a", 8, workers=0, progress=False))
    dask = list(generate(bar, MAT, spec, tmp_path / "b", 8, workers=1, progress=False))
    assert sorted(r["index"] for r in local) == sorted(r["index"] for r in dask) == list(range(8))
    Fa, Ua, _ = load_dataset(tmp_path / "a")
    Fb, Ub, _ = load_dataset(tmp_path / "b")
    np.testing.assert_array_equal(Fa, Fb)
    np.testing.assert_allclose(Ua, Ub, atol=1e-9)


def test_twisting_patches_carry_a_torque(bar, spec):
    from dataclasses import replace

    twist = replace(spec, twist_fraction=1.0, multi_patch=0.0)
    rng = np.random.default_rng(3)
    region = np.asarray(spec.region)
    for _ in range(10):
        g = sample_path_load(bar, twist, rng)
        loaded = np.abs(g).sum(1) > 0
        x = bar.nodes[region[loaded]]
        torque = np.cross(x - x.mean(0), g[loaded]).sum(0)
        assert np.linalg.norm(torque) > 0.1 * np.linalg.norm(g[loaded], axis=1).sum() * np.ptp(x, axis=0).max() / 4
        tangential = np.abs(np.sum(g[loaded] * bar.vertex_normals[region[loaded]], axis=1))
        assert np.all(tangential <= 1e-9 + 0.7 * np.linalg.norm(g[loaded], axis=1))


def test_no_twist_keeps_the_random_stream(bar, spec):
    """twist_fraction = 0 draws nothing more: existing data sets stay reproducible."""
    a = sample_path_load(bar, spec, np.random.default_rng(11))
    from dataclasses import replace

    b = sample_path_load(bar, replace(spec, twist_fraction=0.0), np.random.default_rng(11))
    np.testing.assert_array_equal(a, b)


def test_two_builds_writing_one_path_never_trip_over_each_others_temporaries(tmp_path):
    """Two runs of one scene share its data folder: each write has a temporary of its own."""
    from concurrent.futures import ThreadPoolExecutor

    from service.surrogate.data import done_indices, load_dataset, write_path

    result = {"index": 3, "forces": np.ones((2, 4, 3)), "u": np.zeros((2, 5, 3)), "newton_iterations": np.ones(2)}
    with ThreadPoolExecutor(4) as pool:
        list(pool.map(lambda _: write_path(tmp_path, result), range(200)))
    assert done_indices(tmp_path) == {3}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["path_000003.npz", VERIFIED]
    size = path_file(tmp_path, 3).stat().st_size
    lines = (tmp_path / VERIFIED).read_text().splitlines()
    assert len(lines) == 200 and all(line.startswith(f"path_000003.npz {size} ") for line in lines)  # never torn
    F, _, _ = load_dataset(tmp_path)
    assert F.shape == (2, 4, 3)


def test_a_full_data_folder_is_an_os_error_that_names_the_path(tmp_path, bar, spec):
    """A path written through its temporary's fd on a full disk said only "[Errno 28] No space
    left on device", no file: now the path's file is named, and no temporary is left."""
    import errno

    with small_disk(tmp_path / "disk", 64 * 1024) as disk:
        with pytest.raises(OSError) as caught:
            for _ in generate(bar, MAT, spec, disk / "data", 200, workers=0, progress=False):
                pass
        written = done_indices(disk / "data")
        assert caught.value.errno == errno.ENOSPC
        assert caught.value.filename == str(path_file(disk / "data", len(written)))
        assert str(path_file(disk / "data", len(written))) in str(caught.value)
        left = sorted(p.name for p in (disk / "data").iterdir() if p.name != VERIFIED)
        assert left == [path_file(disk, i).name for i in sorted(written)]


def test_a_timed_generation_of_very_many_paths_keeps_to_its_clock(tmp_path, bar, spec):
    """A timed build's `samples` is an upper bound: 200,000 paths asked of one worker must not
    spend the clock submitting them all to Dask (it took ~30 s before the first path)."""
    import time

    from distributed import LocalCluster

    # a cluster of its own: local workers that generate() starts do not pay off in 10 s
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        until = time.perf_counter() + 10.0
        got = list(generate(bar, MAT, spec, tmp_path / "d", 200_000, scheduler=cluster.scheduler_address,
                            progress=False, until=until))  # fmt: skip
        over = time.perf_counter() - until
    assert over < 6.0  # slack: a loaded machine
    whole = [r["index"] for r in got if not r["cut"]]  # those the clock stopped are yielded, never written
    assert len(whole) >= 1 and set(whole) == done_indices(tmp_path / "d")


def test_a_path_starts_only_where_the_slowest_so_far_says_it_ends_in_time(bar, spec):
    """In-process generation started a path just before its clock and ran it to its end: 5 s
    past a 0.3-minute build's data share on a 3,003-node liver. A path now starts only where
    the slowest of the paths solved so far (their measured solve seconds) ends by the clock;
    the first starts on any time left."""
    from service.surrogate.data import path_fits

    took = [solve_path(bar, MAT, spec, i)["seconds"] for i in range(3)]
    slowest, now = max(took), 100.0
    assert slowest > 0
    assert path_fits(now + slowest, took, now=now)
    assert not path_fits(now + 0.99 * slowest, took, now=now)  # the old test: still before the clock
    assert path_fits(now + 1e-9, [], now=now) and not path_fits(now - 1e-9, [], now=now)
    assert path_fits(None, took, now=now)


def test_a_timed_generation_in_this_process_begins_no_path_its_slowest_says_ends_late(tmp_path, bar, spec):
    """A real in-process generation under a 2 s clock begins each path after the first only
    where, asked for at `asked`, the slowest path before it (their solve seconds) ends by the
    clock: the generation checks after it is asked, so this holds on any load. The old loop
    began a path on any time left, its last within a path's time of the clock (the end-to-end
    margin this test once had passed either way: bar paths take milliseconds)."""
    import time

    until = time.perf_counter() + 2.0
    paths = generate(bar, MAT, spec, tmp_path / "d", 1_000_000, workers=0, progress=False, until=until)
    took: list[float] = []
    late = []
    while True:
        asked = time.perf_counter()  # the path asked for now begins after this, if at all
        result = next(paths, None)
        if result is None:
            break
        if took and asked + max(took) > until:
            late.append((len(took), until - asked, max(took)))
        took.append(result["seconds"])
    assert not late, f"paths begun with less time left than the slowest took: {late[:3]}"
    assert len(took) >= 2 and len(took) == len(done_indices(tmp_path / "d"))


_LISTED: dict[str, int] = {}  # folder -> listings seen while it is watched
_OPENED: dict[str, int] = {}  # folder -> its finished path files opened while it is watched


def _count_listings(event: str, args: tuple) -> None:
    """An audit hook (the interpreter's own events, nothing of ours replaced): directory listings
    of the watched folders, and opens of the finished path files in them. Hooks cannot be
    removed, so it counts only what is watched."""
    if _LISTED and event in ("os.scandir", "os.listdir") and args and args[0] is not None:
        key = os.fsdecode(os.fspath(args[0]))
        if key in _LISTED:
            _LISTED[key] += 1
    if _OPENED and event == "open" and isinstance(args[0], (str, bytes, os.PathLike)):
        path = Path(os.fsdecode(os.fspath(args[0])))
        if str(path.parent) in _OPENED and re.fullmatch(r"path_\d{6}\.npz", path.name):
            _OPENED[str(path.parent)] += 1


sys.addaudithook(_count_listings)


@pytest.mark.parametrize("missing", [(), (17, 311)])
def test_resuming_lists_the_data_folder_twice_however_many_paths_it_holds(tmp_path, bar, spec, missing):
    """The paths on disk are listed once (and the folder once more for a killed build's
    temporaries): once per path index made a resume quadratic (4000 finished paths took 37 s
    to find nothing to do, a fresh 6-million-path --samples 207 s). And a file whose headers a
    resume checked is never opened by the next: each was opened on every resume (5000 files,
    730 ms of a timed build's data share)."""
    out = tmp_path / "data"
    out.mkdir()
    write_path(out, {**solve_path(bar, MAT, spec, 0), "index": 0})
    for i in range(1, 400):  # copies of one path: each opens as a path file, only the names differ
        shutil.copyfile(path_file(out, 0), path_file(out, i))
    assert list(generate(bar, MAT, spec, out, 400, workers=0, progress=False)) == []  # checks the 399 copies
    for i in missing:
        path_file(out, i).unlink()
    _LISTED[str(out)] = _OPENED[str(out)] = 0
    try:
        redone = [r["index"] for r in generate(bar, MAT, spec, out, 400, workers=0, progress=False)]
    finally:
        listings, opened = _LISTED.pop(str(out)), _OPENED.pop(str(out))
    assert redone == list(missing)
    assert listings == 2  # the finished paths, the temporaries: never once per path
    assert opened == 0  # checked before, or written by this build: none opened again


def test_a_path_file_damaged_in_its_data_is_set_aside_and_left_out(tmp_path, bar, spec, caplog):
    """A file whose headers are sound but whose data are not (a flipped byte: the CRC) passes the
    generation's look at the headers; loading it raised BadZipFile on every later build, and a
    lone .npy under a path's name an AttributeError."""
    out = tmp_path / "data"
    list(generate(bar, MAT, spec, out, 3, workers=0, progress=False))
    raw = bytearray(path_file(out, 1).read_bytes())
    raw[len(raw) // 2] ^= 0xFF  # inside u's data
    path_file(out, 1).write_bytes(bytes(raw))
    with path_file(out, 2).open("wb") as f:  # a lone array under a path's name (np.load took it)
        np.save(f, np.zeros(3))
    F, U, P = load_dataset(out)
    np.testing.assert_array_equal(np.unique(P), [0])
    assert (out / "path_000001.npz.damaged").read_bytes() == bytes(raw)  # kept, not deleted
    assert (out / "path_000002.npz.damaged").exists()
    assert done_indices(out) == {0}
    warnings = [r.getMessage() for r in caplog.records if r.name.endswith("pathfiles")]
    assert len(warnings) == 2 and str(path_file(out, 1)) in warnings[0], warnings
    assert "set aside as path_000001.npz.damaged" in warnings[0]


@pytest.mark.skipif(sys.platform == "win32", reason="RLIMIT_NOFILE is POSIX's")
@pytest.mark.parametrize("check", ["headers", "data"])
def test_an_os_error_while_reading_a_path_file_is_raised_not_taken_for_damage(tmp_path, bar, spec, check):
    """At the open-file limit (EMFILE; EIO and ENOMEM alike) every intact path file was renamed
    *.damaged and its path solved again: an OS error says nothing of the file, so it propagates."""
    import errno
    import resource

    from service.surrogate.pathfiles import intact_indices

    out = tmp_path / "data"
    list(generate(bar, MAT, spec, out, 3, workers=0, progress=False))
    read = {
        "headers": lambda: intact_indices(out, [0, 1, 2], len(spec.region), bar.n_nodes, spec.steps),
        "data": lambda: load_dataset(out, [0, 1, 2]),
    }[check]
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    held: list[int] = []
    resource.setrlimit(resource.RLIMIT_NOFILE, (min(256, hard), hard))
    try:
        with pytest.raises(OSError) as raised:
            while True:  # every descriptor taken: the next open fails with EMFILE
                held.append(os.open(os.devnull, os.O_RDONLY))
        assert raised.value.errno == errno.EMFILE
        with pytest.raises(OSError) as raised:
            read()
    finally:
        for fd in held:
            os.close(fd)
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
    assert raised.value.errno == errno.EMFILE and str(path_file(out, 0)) in str(raised.value)
    assert done_indices(out) == {0, 1, 2} and not list(out.glob("*.damaged"))  # nothing set aside


def test_kept_off_nodes_carry_no_training_load_and_the_rest_still_do(bar, spec):
    """[training] keep_off: no patch centres on or spreads over a kept-off node, and loads still
    reach the nodes left (the sites a held-out test scores were never loaded in training)."""
    from dataclasses import replace

    region = np.asarray(spec.region)
    kept = region[region.size // 2 :]
    off = replace(spec, keep_off=tuple(kept.tolist()))
    on_kept = np.isin(region, kept)
    reached = np.zeros(region.size, bool)
    for i in range(60):
        g = sample_path_load(bar, off, np.random.default_rng([0, i]))
        loaded = np.abs(g).sum(axis=1) > 0
        assert not loaded[on_kept].any()
        assert 3 <= loaded.sum() <= 12
        reached |= loaded
    assert reached[~on_kept].mean() > 0.8
    # without kept-off nodes the draws are those of a spec from before the field
    plain = [sample_path_load(bar, spec, np.random.default_rng([0, i])) for i in range(5)]
    empty = [sample_path_load(bar, replace(spec, keep_off=()), np.random.default_rng([0, i])) for i in range(5)]
    np.testing.assert_array_equal(plain, empty)


def test_a_spec_without_kept_off_nodes_keeps_its_data_folders_key():
    """The data folder's key of a spec with no keep_off is the one the field's absence gave, so
    the data of builds made before it stay found; kept-off nodes make a folder of their own."""
    from dataclasses import replace

    from service.build import data_key

    spec = LoadSpec(region=(1, 2, 3), max_force=2.0, patch_nodes=(2, 3), seed=4)
    assert data_key("abc", MAT, spec) == "767a69887666"  # computed by the code before keep_off
    assert data_key("abc", MAT, replace(spec, keep_off=(2,))) != "767a69887666"


def test_a_patch_stays_on_one_side_of_kept_off_nodes(bar):
    """The k nodes nearest a centre were measured along the surface through kept-off nodes, so a
    patch beside a held-out band wrapped round it and loaded both sides (36 of 964 phantom
    patches): a load no grasper makes. Now the surface is walked around kept-off nodes only."""
    from dataclasses import replace

    x = bar.nodes[:, 0]
    region = bar.free_surface_nodes[x[bar.free_surface_nodes] > 1.0]
    band = region[(x[region] >= 2.0) & (x[region] <= 2.5)]  # two rings: the piece x = 1.5 is one ring
    spec = LoadSpec(region=tuple(region.tolist()), max_force=60.0, patch_nodes=(3, 20), multi_patch=0.0)
    off = replace(spec, keep_off=tuple(band.tolist()))
    sides = set()
    for i in range(80):
        g = sample_path_load(bar, off, np.random.default_rng([0, i]))
        at = x[region[np.abs(g).sum(axis=1) > 0]]
        assert (at < 2.0).all() or (at > 2.5).all(), f"path {i} loads both sides of the band: {sorted(set(at))}"
        sides.add(bool((at < 2.0).all()))
    assert sides == {True, False}  # both pieces are loaded
