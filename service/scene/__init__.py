"""Scenes (SCENES.md): a TOML file naming a mesh, its material, its clamp and where loads act.

- ``scene.py``: :class:`Scene`, the mesh it names, reading and resolving a scene;
- ``tables.py``: its tables as frozen pydantic models;
- ``ids.py``: its node sets (fixed nodes, load region, support, matching triangles) and id files;
- ``errors.py``: :class:`SceneError`, every message naming its key;
- ``model_id.py``: the rule a model id follows;
- ``shipped/``: the scenes shipped with elastreg (beam.toml, phantom.toml).
"""

from .errors import SceneError
from .ids import read_node_ids
from .model_id import MODEL_ID, MODEL_ID_RULE, check_model_id
from .scene import BUILTIN_SCENES, Scene, builtin_scene, load_scene, parse_scene, resolve_scene
from .tables import MaterialSpec

__all__ = [
    "BUILTIN_SCENES",
    "MODEL_ID",
    "MODEL_ID_RULE",
    "MaterialSpec",
    "Scene",
    "SceneError",
    "builtin_scene",
    "check_model_id",
    "load_scene",
    "parse_scene",
    "read_node_ids",
    "resolve_scene",
]
