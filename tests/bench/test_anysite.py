"""The any-site part's draws: calibration sites apart from the reported ones, and which build ran."""

import json
from pathlib import Path

import numpy as np
import pytest

from service.bench.anysite import CALIBRATION_SEED, SITE_SEED, SITES, site_patches, site_region
from service.cli import main
from service.store import load_entry
from tests.conftest import needs_liver

ROOT = Path(__file__).resolve().parents[2]
#: the shipped store (its phantom: the model the any-site rows of the README's phantom came from)
STORE = ROOT / "model_store"


def draws(mesh, region, calibration_sites: int = 4) -> tuple[list, list]:
    """The reported draw's (site, tool, support)s and the calibration draw's, as the part makes them."""
    reported = site_patches(mesh, site_region(mesh, region, SITE_SEED), SITES, np.random.default_rng(SITE_SEED))
    calibration = site_patches(
        mesh, site_region(mesh, region, CALIBRATION_SEED), calibration_sites, np.random.default_rng(CALIBRATION_SEED)
    )
    return reported, calibration


def assert_disjoint(reported: list, calibration: list) -> None:
    """No node of a calibration site's tool or support lies in a reported site's support (which
    holds its tool): the sites the shipped settings were chosen on shared up to 13 of 35 tool nodes."""
    taken = set(np.concatenate([support for _, _, support in reported]).tolist())
    for site, tool, support in calibration:
        assert not taken & set(support.tolist()), f"calibration site {site} overlaps a reported site's support"
        assert set(tool.tolist()) <= set(support.tolist()) and tool.size > 0


def test_calibration_sites_keep_off_the_reported_sites_on_the_phantom():
    """Farthest-point sampling lands on the region's extremities from any first node: the phantom's
    calibration draw (seed 3026) put site 437 15 mm from reported site 455, their tool patches
    sharing 3 of 13 nodes and their supports 24 of 39. The calibration draw now spreads its sites
    over the region less the reported sites' supports; the reported draw is unchanged."""
    entry = load_entry(STORE / "phantom")
    reported, calibration = draws(entry.mesh, entry.region)
    assert [site for site, _, _ in reported] == [554, 455, 69, 20, 225, 613]  # the committed reports' sites
    assert_disjoint(reported, calibration)


@needs_liver()
def test_calibration_sites_keep_off_the_reported_sites_on_the_liver():
    """On the paper's liver (the scene's region: every free surface node) calibration site 2241
    shared 11 of 35 tool nodes with reported site 2071, and 695 13 with 212."""
    from service.scene import load_scene

    scene = load_scene(ROOT / "benchmarks" / "scenes" / "liver_paper.toml")
    mesh, loaded = scene.build_mesh()
    reported, calibration = draws(mesh, scene.region_nodes(mesh, loaded))
    assert [site for site, _, _ in reported] == [2071, 377, 1097, 212, 1476, 2093]
    assert_disjoint(reported, calibration)


def test_a_region_without_room_off_the_reported_sites_is_refused(bar):
    """A calibration draw on a region the reported supports cover says so, rather than drawing
    sites on the reported ones."""
    with pytest.raises(ValueError, match="outside the reported sites' supports"):
        site_region(bar, bar.free_surface_nodes, CALIBRATION_SEED)


@pytest.mark.slow  # 90 s: the phantom's finer-mesh truth at two sites
def test_the_anysite_results_name_the_build_that_ran(tmp_path):
    """results.json named the model only by its id: the any-site rows of two builds of
    liver_paper (validation 0.243 and 0.207 mm) could not be told apart. The part now records the
    entry's manifest creation time and weights checksum beside its id."""
    out = tmp_path / "report"
    assert main(["bench", "anysite", "--smoke", "phantom", "--store", str(STORE), "--out", str(out), "--no-fem"]) == 0
    manifest = json.loads((STORE / "phantom" / "manifest.json").read_text())
    made = json.loads((out / "results.json").read_text())["parts"]["anysite"]["model_entry"]
    assert made == {
        "id": "phantom",
        "created": manifest["created"],
        "weights_sha256": manifest["files"]["weights.safetensors"],
        "validation_mean_mm": manifest["training"]["validation"]["mean_mm"],
    }
    assert manifest["files"]["weights.safetensors"][:12] in (out / "report.md").read_text()


SCENES = ROOT / "benchmarks" / "scenes"
SHIPPED = ROOT / "service" / "scene" / "shipped"


def check_held_out_scene(name: str, scene_arg: str, recipe: Path, tmp_path: Path) -> None:
    """NAME_held_out.toml's keep_off file is what benchmarks/held_out_sites.py writes today from
    `scene_arg`, it holds the supports of all six reported sites and the scene's own (the
    liver's recorded sequence), and the scene is its `recipe` otherwise (its name and that key
    aside)."""
    import subprocess
    import sys
    import tomllib

    from service.scene import load_scene, resolve_scene

    out = tmp_path / "held_out.npy"
    script = [sys.executable, "benchmarks/held_out_sites.py", "--scene", scene_arg, "--out", str(out)]
    subprocess.run(script, cwd=ROOT, check=True, capture_output=True)
    np.testing.assert_array_equal(np.load(out), np.load(SCENES / f"{name}_held_out.npy"))
    scene = load_scene(SCENES / f"{name}_held_out.toml")
    mesh, loaded = scene.build_mesh()
    region, kept = scene.region_nodes(mesh, loaded), scene.keep_off_nodes(mesh, loaded)
    reported, _ = draws(mesh, region)
    for _, _, support in reported:
        assert np.isin(support, kept).all()
    own = resolve_scene(scene_arg).support_nodes(mesh, loaded)
    assert own is None or np.isin(own, kept).all()
    plain, held = tomllib.loads(recipe.read_text()), tomllib.loads((SCENES / f"{name}_held_out.toml").read_text())
    assert held.pop("name") == f"{name}_held_out" and held["training"].pop("keep_off_file")
    del plain["name"]
    assert plain == held


@needs_liver()
def test_the_held_out_liver_keeps_its_reported_sites_and_recorded_support_off(tmp_path):
    recipe = SCENES / "liver_paper.toml"
    check_held_out_scene("liver_paper", str(recipe), recipe, tmp_path)


def test_the_held_out_phantom_keeps_its_reported_sites_off(tmp_path):
    check_held_out_scene("phantom", "phantom", SHIPPED / "phantom.toml", tmp_path)
