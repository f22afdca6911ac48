"""Scenes: builtin and file scenes load; every kind of mistake is refused naming its key."""

from __future__ import annotations

import textwrap
import tomllib
import warnings
from pathlib import Path

import meshio
import numpy as np
import pytest

from service.fem.material import NeoHookean
from service.phantoms import grid_tets
from service.scene import MODEL_ID_RULE, MaterialSpec, SceneError, builtin_scene, load_scene, parse_scene, resolve_scene
from tests.conftest import LIVER, needs_liver

REPO = Path(__file__).resolve().parents[1]

GOOD = """
name = "block-1"

[mesh]
path = "meshes/block.vtu"
scale = 0.001

[material]
law = "neo-hookean"
E = 4500
nu = 0.49

[boundary]
{boundary}

[training]
samples = 10
max_force = 0.5
patch_nodes = [2, 6]
{training}
"""


@pytest.fixture()
def folder(tmp_path) -> Path:
    """A scene folder with a 4 x 2 x 2 hex block in millimetres (10 mm cells) in meshes/."""
    nodes, tets = grid_tets((4, 2, 2), 10.0)
    (tmp_path / "meshes").mkdir()
    meshio.write(tmp_path / "meshes" / "block.vtu", meshio.Mesh(nodes, [("tetra", tets)]))
    return tmp_path


def write(
    folder: Path,
    boundary: str = "fixed_box = [[-1, -1, -1], [0.001, 1, 1]]",
    training: str = "",
    text: str | None = None,
) -> Path:
    path = folder / "scene.toml"
    path.write_text(text if text is not None else GOOD.format(boundary=boundary, training=training))
    return path


def error_of(folder: Path, **kw) -> str:
    with pytest.raises(SceneError) as info:
        scene = load_scene(write(folder, **kw))
        mesh, _ = scene.build_mesh()
        scene.region_nodes(mesh)
    return str(info.value)


# -- loading ----------------------------------------------------------------------------------


@pytest.mark.parametrize("name, n_nodes, n_fixed", [("beam", 500, 25), ("phantom", None, None)])
def test_builtin_scenes_load(name, n_nodes, n_fixed):
    scene = builtin_scene(name)
    assert scene.name == name and scene.material.E == 4500.0 and scene.material.nu == 0.49
    assert scene.mesh.generator == name
    mesh, loaded = scene.build_mesh()
    assert loaded.source is None and loaded.kept is None
    if n_nodes:
        assert mesh.n_nodes == n_nodes and mesh.fixed.size == n_fixed
    region = scene.region_nodes(mesh)
    np.testing.assert_array_equal(region, mesh.free_surface_nodes)
    assert resolve_scene(name).name == name


def test_good_scene_loads_with_relative_paths_and_defaults(folder):
    scene = load_scene(write(folder))
    assert scene.mesh.path == (folder / "meshes" / "block.vtu").resolve()
    assert scene.origin.endswith("scene.toml")
    t = scene.training
    assert (t.seed, t.load_steps, t.multi_patch, t.normal_fraction, t.members) == (0, 5, 0.2, 0.5, 1)
    assert scene.training.patch_nodes == (2, 6)
    mesh, loaded = scene.build_mesh()
    assert mesh.n_nodes == 45 and not loaded.tetrahedralised
    np.testing.assert_allclose(np.ptp(mesh.nodes, axis=0), [0.04, 0.02, 0.02])  # scaled to m
    assert resolve_scene(folder / "scene.toml").name == "block-1"


def test_fixed_box_selects_after_scaling(folder):
    scene = load_scene(write(folder, boundary="fixed_box = [[0.015, -1, -1], [0.025, 1, 1]]"))
    mesh, _ = scene.build_mesh()
    assert mesh.fixed.size == 9 and np.allclose(mesh.nodes[mesh.fixed, 0], 0.02)


def test_fixed_nodes_file_text_and_npy(folder):
    (folder / "fixed.txt").write_text("# clamp\n0\n1\n3\n")
    mesh, _ = load_scene(write(folder, boundary='fixed_nodes_file = "fixed.txt"')).build_mesh()
    assert mesh.fixed.tolist() == [0, 1, 3]
    np.save(folder / "fixed.npy", np.array([3, 4, 6, 7]))
    scene = load_scene(write(folder, boundary='fixed_nodes_file = "fixed.npy"\nfree_nodes = [7]'))
    assert scene.build_mesh()[0].fixed.tolist() == [3, 4, 6]


def test_an_npy_id_past_int64_is_named_as_it_is_not_wrapped_round(folder):
    """A uint64 2^64 - 1 was cast first and refused as 'got [-1]', an id the file does not hold."""
    np.save(folder / "fixed.npy", np.array([0, 1, 2**64 - 1], np.uint64))
    msg = error_of(folder, boundary='fixed_nodes_file = "fixed.npy"')
    assert msg == (
        f"{folder / 'scene.toml'}: [boundary] fixed_nodes_file: {folder / 'fixed.npy'} holds node ids past any "
        "mesh's nodes (at most 2^63 - 1): [18446744073709551615]"
    ), msg
    np.save(folder / "fixed.npy", np.array([0, 1, 3], np.uint64))  # a uint64 file of real ids is read
    assert load_scene(write(folder, boundary='fixed_nodes_file = "fixed.npy"')).build_mesh()[0].fixed.tolist() == [
        0,
        1,
        3,
    ]


@pytest.mark.parametrize("content", ["", "# clamp: none yet\n"])
@pytest.mark.parametrize("section, key", [("boundary", "fixed_nodes_file"), ("training", "region_file")])
def test_an_id_file_with_no_id_is_one_error_naming_it(folder, section, key, content):
    """numpy's two-line `UserWarning: loadtxt: input contained no data` came before the error."""
    (folder / "ids.txt").write_text(content)
    kw = (
        {"boundary": 'fixed_nodes_file = "ids.txt"'}
        if section == "boundary"
        else {"training": 'region_file = "ids.txt"'}
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any warning fails the test
        msg = error_of(folder, **kw)
    assert msg == f"{folder / 'scene.toml'}: [{section}] {key}: {folder / 'ids.txt'} holds no node id", msg


def test_an_id_file_of_two_columns_is_refused_not_flattened(folder):
    """SCENES.md: one id a line. Pairs (an edge list, ids beside coordinates) were read as ids."""
    (folder / "fixed.txt").write_text("0 1\n3 4\n")
    msg = error_of(folder, boundary='fixed_nodes_file = "fixed.txt"')
    assert msg.endswith(
        f"[boundary] fixed_nodes_file: {folder / 'fixed.txt'} holds rows of 2 ids: node ids go one id a line"
    )
    (folder / "region.txt").write_text("12 13 14\n")  # one line of three ids is no list of them either
    assert "holds rows of 3 ids" in error_of(folder, training='region_file = "region.txt"')
    np.save(folder / "fixed.npy", np.array([[0, 1], [3, 4]]))
    assert "fixed.npy holds rows of 2 ids" in error_of(folder, boundary='fixed_nodes_file = "fixed.npy"')
    np.save(folder / "fixed.npy", np.array([[0, 1, 3]]))  # an array's one row of ids is a list of them
    assert load_scene(write(folder, boundary='fixed_nodes_file = "fixed.npy"')).build_mesh()[0].fixed.tolist() == [
        0,
        1,
        3,
    ]
    np.save(folder / "fixed.npy", np.array([[0], [1], [3]]))  # a column of ids is one id a row
    assert load_scene(write(folder, boundary='fixed_nodes_file = "fixed.npy"')).build_mesh()[0].fixed.tolist() == [
        0,
        1,
        3,
    ]


def test_a_scene_and_an_id_file_saved_with_a_bom_load(folder):
    """Windows editors save UTF-8 with a byte-order mark: the scene was "not valid TOML:
    Invalid statement (at line 1, column 1)" and an id file's first id unreadable."""
    (folder / "fixed.txt").write_text("\ufeff0\n1\n3\n", encoding="utf-8")
    path = write(folder, boundary='fixed_nodes_file = "fixed.txt"')
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    scene = load_scene(path)
    assert scene.name == "block-1" and scene.build_mesh()[0].fixed.tolist() == [0, 1, 3]


def test_a_body_held_at_a_point_or_along_a_line_is_refused(folder):
    """It could still turn about the fixed nodes: the static problem would be singular."""
    assert "at one point" in error_of(folder, boundary="fixed_nodes = [4]")
    assert "on one line" in error_of(folder, boundary="fixed_nodes = [0, 1, 2]")
    assert "no node" in error_of(folder, boundary="fixed_nodes = [0, 1, 3]", training="region = []")


def test_regions(folder):
    scene = load_scene(write(folder, training="region_box = [[0.03, -1, -1], [1, 1, 1]]"))
    mesh, _ = scene.build_mesh()
    region = scene.region_nodes(mesh)
    assert region.size and (mesh.nodes[region, 0] >= 0.03).all()
    assert np.isin(region, mesh.free_surface_nodes).all()
    sphere = "region_sphere = {centre = [0.04, 0.01, 0.02], radius = 0.0101}"
    scene = load_scene(write(folder, training=sphere))
    mesh, _ = scene.build_mesh()
    assert sorted(map(tuple, mesh.nodes[scene.region_nodes(mesh)].round(3))) == [
        (0.03, 0.01, 0.02),
        (0.04, 0.0, 0.02),
        (0.04, 0.01, 0.01),
        (0.04, 0.01, 0.02),
        (0.04, 0.02, 0.02),
    ]
    ids = mesh.free_surface_nodes[:4].tolist()
    scene = load_scene(write(folder, training=f"region = {ids}"))
    assert scene.region_nodes(scene.build_mesh()[0]).tolist() == ids


def test_ids_are_mapped_when_unused_nodes_are_dropped(tmp_path):
    nodes, tets = grid_tets((2, 1, 1), 1.0)
    nodes = np.vstack([[[9.0, 9, 9]], nodes])  # an unused node 0 shifts every id by one
    meshio.write(tmp_path / "m.vtu", meshio.Mesh(nodes, [("tetra", tets + 1)]))
    text = (
        GOOD.replace("meshes/block.vtu", "m.vtu")
        .replace("scale = 0.001", "")
        .replace("patch_nodes = [2, 6]", "patch_nodes = [1, 1]")  # a one-node region: one-node loads
        .format(boundary="fixed_nodes = [1, 2, 3, 4]", training="region = [12]")
    )
    scene = load_scene(write(tmp_path, text=text))
    mesh, loaded = scene.build_mesh()
    assert loaded.kept is not None and mesh.fixed.tolist() == [0, 1, 2, 3]
    assert scene.region_nodes(mesh).tolist() == [11]
    bad = text.replace("fixed_nodes = [1, 2, 3, 4]", "fixed_nodes = [0, 1]")
    with pytest.raises(SceneError, match=r"\[boundary\] fixed_nodes: nodes \[0\] belong to no tet"):
        load_scene(write(tmp_path, text=bad)).build_mesh()


# -- errors name the key ----------------------------------------------------------------------


def edited(old: str, new: str, boundary: str = "fixed_nodes = [0, 1, 3]", training: str = "") -> str:
    """The good scene with one piece of text replaced."""
    text = GOOD.format(boundary=boundary, training=training)
    assert old in text
    return text.replace(old, new)


def test_unknown_key(folder):
    msg = error_of(folder, training="epochs = 3")
    assert "scene.toml: [training] epochs: unknown key" in msg
    text = GOOD.format(boundary="fixed_nodes = [0]", training="") + "\n[extras]\na = 1\n"
    assert "scene.toml: [extras]: unknown table" in error_of(folder, text=text)


def test_nu_too_large(folder):
    msg = error_of(folder, text=edited("nu = 0.49", "nu = 0.6"))
    assert msg.endswith("scene.toml: [material] nu: must be within [0, 0.49999], got 0.6")


@pytest.mark.parametrize(
    "old, new, expected",
    [
        # each passed validation and failed only in the build: "first steps did not converge"
        ("E = 4500", "E = 1e308", "[material] E: must be within [1, 1e+12] Pa, got 1e+308"),
        ("E = 4500", "E = 1e-3", "[material] E: must be within [1, 1e+12] Pa, got 0.001"),
        ("nu = 0.49", "nu = 0.499999999", "[material] nu: must be within [0, 0.49999], got 0.499999999"),
    ],
)
def test_non_physical_materials_are_refused_with_their_range(folder, old, new, expected):
    msg = error_of(folder, text=edited(old, new))
    assert msg.endswith(f"scene.toml: {expected}") and "\n" not in msg


@pytest.mark.parametrize(
    "E, nu", [(1e-3, 0.3), (1.0 - 1e-9, 0.3), (1.0, 0.3), (1e12, 0.3), (1.01e12, 0.3), (1e4, 0.49999), (1e4, 0.4999999)]
)
def test_a_scene_takes_the_materials_the_fem_takes(E, nu):
    """One range: a material the FEM's law refuses (E = 1e-3 was taken by it and refused by a
    scene) is refused by a scene, and one it takes is taken."""
    try:
        NeoHookean(E, nu)
    except ValueError:
        with pytest.raises(ValueError, match="must be within"):
            MaterialSpec(E=E, nu=nu)
    else:
        assert (MaterialSpec(E=E, nu=nu).E, MaterialSpec(E=E, nu=nu).nu) == (E, nu)


def test_the_material_range_holds_every_shipped_and_benchmark_scene():
    """The bounds are wide: the scenes the project ships and benchmarks load as they are."""
    for name in ("beam", "phantom"):
        builtin_scene(name)
    benchmarks = sorted((REPO / "benchmarks" / "scenes").glob("*.toml"))
    assert benchmarks
    for path in benchmarks:  # their meshes are in ../shared: the material table alone
        MaterialSpec(**tomllib.loads(path.read_text())["material"])


def test_two_fixed_selections(folder):
    msg = error_of(folder, boundary="fixed_nodes = [0]\nfixed_box = [[0, 0, 0], [1, 1, 1]]")
    assert "[boundary]: give exactly one of fixed_nodes, fixed_nodes_file, fixed_box" in msg
    assert "(got fixed_nodes, fixed_box)" in msg


def test_no_fixed_selection_for_a_file(folder):
    assert "[boundary]: give exactly one of" in error_of(folder, boundary="")


def test_fixed_id_out_of_range(folder):
    msg = error_of(folder, boundary="fixed_nodes = [0, 45]")
    assert "[boundary] fixed_nodes: node ids must lie in 0..44, got [45]" in msg
    msg = error_of(folder, boundary="fixed_nodes = [0, -2]")
    assert "[boundary] fixed_nodes[1]: must be >= 0, got -2" in msg


def test_everything_freed_is_singular(folder):
    msg = error_of(folder, boundary="fixed_nodes = [0]\nfree_nodes = [0]")
    assert "[boundary]: no node is fixed" in msg and "singular" in msg


def test_empty_fixed_box(folder):
    msg = error_of(folder, boundary="fixed_box = [[5, 5, 5], [6, 6, 6]]")
    assert "[boundary] fixed_box: selects no node" in msg


def test_missing_material(folder):
    text = edited('[material]\nlaw = "neo-hookean"\nE = 4500\nnu = 0.49\n', "")
    assert "scene.toml: [material]: missing table" in error_of(folder, text=text)
    assert "[material] E: missing (required)" in error_of(folder, text=edited("E = 4500\n", ""))


def test_region_not_on_surface(folder):
    nodes, _ = grid_tets((4, 2, 2), 10.0)
    interior = int(np.flatnonzero((nodes == [20.0, 10.0, 10.0]).all(axis=1))[0])
    msg = error_of(folder, training=f"region = [{interior}]")
    assert (f"[training] region: 1 nodes are not free surface nodes (interior or fixed): [{interior}]") in msg
    assert "[training] region: " in error_of(folder, training="region = [0]")  # fixed by the box


@pytest.mark.parametrize(
    "old, new, expected",
    [
        ("[2, 6]", "[6, 2]", "[training] patch_nodes: must be [lo, hi] with lo <= hi"),
        ("[2, 6]", "[0, 2]", "[training] patch_nodes[0]: must be >= 1, got 0"),
        ("samples = 10", "samples = 1.5", "[training] samples: must be a valid integer"),
        ("max_force = 0.5", "max_force = inf", "[training] max_force: must be a finite number"),
        (
            "block-1",
            "a b",
            f"name: {MODEL_ID_RULE}, got 'a b'",
        ),
        ("block.vtu", "nope.vtu", "[mesh] path: file not found"),
        ('"neo-hookean"', '"st-venant"', "[material] law: must be 'neo-hookean'"),
        ("name = ", "name = \nname = ", "not valid TOML"),
        ("E = 4500", "E = true", "[material] E: must be a valid number"),
        ("nu = 0.49", 'nu = "0.3"', "[material] nu: must be a valid number"),
        ("max_force = 0.5", 'max_force = "0.5"', "[training] max_force: must be a valid number"),
        (
            "block-1",
            "-block",
            f"name: {MODEL_ID_RULE}, got '-block'",
        ),
    ],
)
def test_value_errors_name_the_key(folder, old, new, expected):
    assert expected in error_of(folder, text=edited(old, new))


def test_training_options(folder):
    msg = error_of(folder, training="region = [1]\nregion_box = [[0, 0, 0], [1, 1, 1]]")
    assert "[training]: give at most one of region, region_file, region_box" in msg
    msg = error_of(folder, training="multi_patch = 1.5")
    assert "[training] multi_patch: must be <= 1.0, got 1.5" in msg
    msg = error_of(folder, training="region_sphere = {centre = [0, 0, 0], radius = 0}")
    assert "[training] region_sphere.radius: must be > 0.0, got 0" in msg
    assert "[training] members: must be >= 1, got 0" in error_of(folder, training="members = 0")
    assert "[training] members: must be <= 64, got 100000" in error_of(folder, training="members = 100000")
    with pytest.raises(SceneError, match="builtins: beam, phantom"):
        resolve_scene("kidney")


def test_generator_scene_and_mesh_source_exclusive():
    text = textwrap.dedent("""
        name = "b"
        [mesh]
        generator = "beam"
        [material]
        E = 1000
        nu = 0.3
        [boundary]
        fixed_box = [[0.185, -1, -1], [1, 1, 1]]
        [training]
        samples = 1
        max_force = 0.01
        patch_nodes = [1, 1]
        """)
    mesh, _ = parse_scene(text).build_mesh()
    assert mesh.fixed.size == 25 and np.allclose(mesh.nodes[mesh.fixed, 0], 0.19)
    for mesh_keys in (f'generator = "beam"\npath = "{__file__}"', "scale = 2.0"):
        with pytest.raises(SceneError, match=r"<scene>: \[mesh\]: give exactly one of path, gen"):
            parse_scene(text.replace('generator = "beam"', mesh_keys))


@needs_liver()
def test_paper_liver_scene():
    scene = load_scene(REPO / "benchmarks" / "scenes" / "liver_paper.toml")
    mesh, _ = scene.build_mesh()
    dirichlet = np.load(LIVER / "dirichlet-vertices.npy")
    assert mesh.n_nodes == 3046 and mesh.fixed.size == dirichlet.size - 1 and 756 not in mesh.fixed
    region = scene.region_nodes(mesh)
    support = scene.support_nodes(mesh)
    assert support.size == 60 and np.isin(support, mesh.free_surface_nodes).all()
    # the recipe takes nothing from the sequence it is scored on: its loads may act anywhere
    np.testing.assert_array_equal(region, mesh.free_surface_nodes)
    assert scene.matching_faces(mesh).shape == (4745, 3)


def test_a_scene_file_not_in_utf8_is_refused_by_name(folder):
    path = write(folder)
    path.write_bytes(path.read_bytes().replace(b"block-1", b"bl\xe9ck"))
    with pytest.raises(SceneError, match=r"scene.toml: a scene file is TOML in UTF-8"):
        load_scene(path)


def test_a_mesh_in_the_wrong_unit_is_warned_of(folder, caplog):
    """The block is 40 mm long: read as metres (scale 1) it spans 49 m, no organ's size."""
    scene = load_scene(write(folder, text=edited("scale = 0.001", "scale = 1.0")))
    with caplog.at_level("WARNING", logger="service.scene"):
        scene.build_mesh()
    assert "is [mesh] scale right" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="service.scene"):
        load_scene(write(folder)).build_mesh()
    assert "scale right" not in caplog.text


def test_a_boundary_that_fixes_everything_is_named(folder):
    msg = error_of(folder, boundary="fixed_box = [[-1, -1, -1], [1, 1, 1]]")
    assert "[boundary] fixed_box: fixes every node (45 of 45 nodes): nothing is left free to load" in msg


def test_a_region_smaller_than_its_patches(folder):
    from service.build import load_spec

    scene = load_scene(write(folder))
    mesh, _ = scene.build_mesh()
    few = mesh.free_surface_nodes[:3].tolist()
    msg = error_of(folder, training=f"region = {few[:1]}")
    assert "[training] patch_nodes: a load spreads over at least 2 nodes, but the load region holds 1" in msg
    scene = load_scene(write(folder, training=f"region = {few}"))
    mesh, _ = scene.build_mesh()
    spec = load_spec(scene, mesh)
    assert spec.patch_nodes == (2, 3)  # what the loads really take, not the scene's 6


def test_a_misspelt_registration_key_is_refused(folder):
    text = GOOD.format(boundary="fixed_nodes = [0, 1, 3]", training="") + "\n[registration]\nsuport = [5]\n"
    with pytest.raises(SceneError, match=r"\[registration\] suport"):
        load_scene(write(folder, text=text))


@pytest.mark.parametrize("scale, span", [("1e308", "inf"), ("1e-300", "4.9e-299"), ("1e-9", "4.9e-08")])
def test_a_scale_that_puts_the_mesh_past_any_size_blames_the_scale(folder, scale, span):
    """Before: 1e308 made the coordinates inf ('[mesh] path: ... NaN or infinite coordinates') and
    1e-300 every tet degenerate, both blaming the mesh file. Now the scale is named, with the
    span it makes (the block spans 49 units)."""
    msg = error_of(folder, text=edited("scale = 0.001", f"scale = {scale}"))
    assert msg.startswith(
        f"{folder / 'scene.toml'}: [mesh] scale: scale {float(scale):g} makes block.vtu span {span} m"
    )
    assert "\n" not in msg
    text = edited("scale = 0.001", f"scale = {scale}").replace('path = "meshes/block.vtu"', 'generator = "phantom"')
    assert "[mesh] scale: scale" in error_of(folder, text=text)


def test_kept_off_nodes_are_read_and_checked(folder):
    """[training] keep_off / keep_off_file: free surface nodes no training load touches; an
    interior node, both keys, or a region left smaller than a patch are refused by name."""
    from service.build import load_spec

    scene = load_scene(write(folder))
    mesh, _ = scene.build_mesh()
    region = scene.region_nodes(mesh)
    kept = region[:5].tolist()
    scene = load_scene(write(folder, training=f"keep_off = {kept}"))
    np.testing.assert_array_equal(scene.keep_off_nodes(mesh), kept)
    # a region the caller already has is used as given (load_spec's): ids outside it are dropped
    np.testing.assert_array_equal(scene.keep_off_nodes(mesh, region=region[2:]), kept[2:])
    np.save(folder / "off.npy", np.asarray(kept))
    from_file = load_scene(write(folder, training='keep_off_file = "off.npy"'))
    np.testing.assert_array_equal(from_file.keep_off_nodes(mesh), kept)
    spec = load_spec(scene, mesh)
    assert spec.keep_off == tuple(kept) and spec.region == tuple(region.tolist())  # the network's region stays
    assert load_scene(write(folder)).keep_off_nodes(mesh).size == 0
    interior = int(np.setdiff1d(np.arange(mesh.n_nodes), mesh.surface_nodes)[0])
    with pytest.raises(SceneError, match=r"\[training\] keep_off: 1 nodes are not free surface nodes"):
        load_scene(write(folder, training=f"keep_off = [{interior}]")).keep_off_nodes(mesh)
    msg = error_of(folder, training=f'keep_off = {kept}\nkeep_off_file = "off.npy"')
    assert "give at most one of keep_off, keep_off_file" in msg
    few = load_scene(write(folder, training=f"keep_off = {region[1:].tolist()}"))
    with pytest.raises(SceneError, match=r"\[training\] keep_off: leaves 1 of the load region's"):
        few.keep_off_nodes(mesh)
    room = load_scene(write(folder, training=f"keep_off = {region[4:].tolist()}"))
    assert load_spec(room, mesh).patch_nodes == (2, 4)  # what is left to load
    # what is left must hold the smallest patch in one piece: loads spread along the surface
    far = [int(region[np.argmin(mesh.nodes[region, 0])]), int(region[np.argmax(mesh.nodes[region, 0])])]
    scattered = load_scene(write(folder, training=f"keep_off = {np.setdiff1d(region, far).tolist()}"))
    with pytest.raises(
        SceneError, match="leaves 2 of the load region's .* the largest connected piece of them 1 nodes"
    ):
        scattered.keep_off_nodes(mesh)
