"""The manifest's checks: its shape, its names and numbers, and what it records twice, before
any other file of the entry is opened."""

from __future__ import annotations

import math

from ..fem.material import NeoHookean
from ..scene import MODEL_ID
from .files import FORMAT_VERSION, MANIFEST, MESH, WEIGHTS, StoreError, _is_digest


def _check_manifest(manifest, name: str) -> None:
    """The manifest's shape and names, before any other file is opened."""
    if not isinstance(manifest, dict):
        raise StoreError(f"{name}: {MANIFEST} must hold a JSON object")
    version = manifest.get("format_version")
    if version != FORMAT_VERSION:
        raise StoreError(f"{name}: manifest format {version!r} is not supported (expected {FORMAT_VERSION})")
    files = manifest.get("files")
    if not isinstance(files, dict) or set(files) != {MESH, WEIGHTS}:
        listed = sorted(files)[:4] if isinstance(files, dict) else files
        raise StoreError(
            f"{name}: the manifest must list {MESH} and {WEIGHTS} under files, and nothing else "
            f"(it lists {listed!r:.200})"
        )
    if not all(_is_digest(d) for d in files.values()):
        raise StoreError(f"{name}: each file's checksum must be a SHA-256 hex digest")
    entry_id = manifest.get("id")
    if not isinstance(entry_id, str) or not MODEL_ID.fullmatch(entry_id):
        raise StoreError(f"{name}: the manifest's id must match {MODEL_ID.pattern}, got {entry_id!r:.80}")
    for key in ("mesh", "material", "network", "scene"):
        if not isinstance(manifest.get(key), dict):
            raise StoreError(f"{name}: the manifest has no {key!r} object")
    if not isinstance(manifest["scene"].get("material"), dict):
        raise StoreError(f"{name}: the manifest's scene has no 'material' object")
    material = manifest["material"]
    if not all(
        isinstance(material.get(k), (int, float)) and not isinstance(material.get(k), bool) for k in ("E", "nu")
    ):
        raise StoreError(f"{name}: the manifest's material needs numbers E and nu")
    if material.get("law", NeoHookean.law) != NeoHookean.law:
        raise StoreError(f"{name}: the manifest's material law {material['law']!r:.40} is not {NeoHookean.law!r}")
    try:
        NeoHookean.of(material)
    except ValueError as exc:
        raise StoreError(f"{name}: the manifest's material: {exc}") from None
    _check_twice(manifest, name)
    renumbered = manifest["mesh"].get("renumbered", False)
    if not isinstance(renumbered, bool):
        raise StoreError(f"{name}: the manifest's mesh.renumbered must be true or false, got {renumbered!r:.40}")
    _check_network(manifest["network"], name)


#: what a manifest records twice: a value the entry serves (or its data were drawn with) and
#: where the scene it was built from set it
_TWICE = (
    *((("material", k), ("scene", "material", k)) for k in ("law", "E", "nu")),
    (("training", "load_distribution", "steps"), ("scene", "training", "load_steps")),
    *(
        (("training", "load_distribution", k), ("scene", "training", k))
        for k in ("max_force", "seed", "multi_patch", "normal_fraction", "pull_fraction", "twist_fraction")
    ),
)
_ABSENT = object()


def _at(tree, path: tuple[str, ...]):
    for key in path:
        if not isinstance(tree, dict) or key not in tree:
            return _ABSENT
        tree = tree[key]
    return tree


def _check_twice(manifest: dict, name: str) -> None:
    """Each value the manifest records twice is the same both times: a material.E edited from
    4500 to 45000 was served at ten times the stiffness the network learnt, beside a scene that
    said 4500. A copy an older entry lacks is not compared."""
    for field, source in _TWICE:
        value, given = _at(manifest, field), _at(manifest, source)
        if value is _ABSENT or given is _ABSENT or value == given:  # 60 and 60.0 are one number
            continue
        raise StoreError(
            f"{name}: the manifest's {'.'.join(field)} {value!r:.40} is not the {given!r:.40} of the scene it was "
            f"built from ({'.'.join(source)}): changed after the build"
        )


def _whole(value, minimum: int = 1) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= minimum


def _check_network(spec: dict, name: str) -> None:
    """The manifest's network object: a layout this code builds, and whole numbers where the
    build reads them (a string "512" was read as the widths [5, 1, 2])."""
    layout = spec.get("layout")
    if layout not in ("reduced", "paper"):
        raise StoreError(f"{name}: the manifest's network layout {layout!r:.40} is not 'reduced' or 'paper'")
    keys = ("n_in", "n_out") if layout == "paper" else ("n_in",)
    for key in keys:
        if not _whole(spec.get(key)):
            raise StoreError(
                f"{name}: the manifest's network.{key} must be a whole number >= 1, got {spec.get(key)!r:.40}"
            )
    hidden = spec.get("hidden")
    if not (isinstance(hidden, list) and all(_whole(h) for h in hidden)):
        raise StoreError(
            f"{name}: the manifest's network.hidden must be a list of layer widths (whole numbers >= 1), "
            f"got {hidden!r:.40}"
        )
    if not _whole(spec.get("members", 1)):
        raise StoreError(
            f"{name}: the manifest's network.members must be a whole number >= 1, got {spec.get('members')!r:.40}"
        )


def _max_force(manifest: dict, name: str) -> float | None:
    """The scene's largest tool force (N; the error estimate's prior), None in an entry built
    before it was recorded; present, it must be a positive finite number."""
    training = manifest.get("training", {})
    spec = training.get("load_distribution", {}) if isinstance(training, dict) else None
    if not isinstance(spec, dict):
        raise StoreError(f"{name}: the manifest's training.load_distribution must be an object")
    value = spec.get("max_force")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
        raise StoreError(f"{name}: the manifest's max_force must be a positive number of newtons, got {value!r:.40}")
    return float(value)


def _tool_patch(manifest: dict, name: str) -> int | None:
    """The most nodes one sampled load spread over (the scene's patch_nodes' upper end), None
    in an entry that records none; present, [low, high] whole numbers, 1 <= low <= high."""
    spec = manifest.get("training", {}).get("load_distribution", {})  # checked by _max_force
    value = spec.get("patch_nodes")
    if value is None:
        return None
    if not (
        isinstance(value, list) and len(value) == 2
        and all(isinstance(v, int) and not isinstance(v, bool) for v in value) and 1 <= value[0] <= value[1]
    ):  # fmt: skip
        raise StoreError(f"{name}: the manifest's patch_nodes must be [low, high] node counts, got {value!r:.40}")
    return int(value[1])
