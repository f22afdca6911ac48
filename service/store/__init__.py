"""The model store: one folder per trained model, checked before it is trusted.

    <store>/<id>/manifest.json        what it is: scene, material, mesh facts, network layout,
                                      training figures, validation metrics, code version,
                                      the command that rebuilds it, and a SHA-256 per file
    <store>/<id>/mesh.npz             nodes, tets, fixed nodes, the load region
    <store>/<id>/weights.safetensors  the network's tensors (normalisation buffers included)
    <store>/.<id>-XXXXXXXX.build/     a build writing its entry (locked by that process; stale
                                      ones, whose writer is gone, are removed: remove_stale_builds)
    <store>/.<id>-XXXXXXXX/           the same, unlocked (older versions; file systems without
                                      locks): removed once a day old and shown to be a write cut
                                      off (a complete entry under such a name is kept)

Loading checks the manifest's shape and every name in it before any other file is opened (the
file names must be exactly the two above, regular files inside the entry's folder: a manifest
naming ``../../../dev/zero`` is refused without reading it; what it records twice, the material
and load distribution it serves beside its scene's, must agree), reads each file once into
memory and hashes those very bytes against the manifest (then builds from them: nothing maps a
file, so a file truncated or rewritten under a running server changes nothing it serves), checks
the mesh arrays against the recorded mesh hash, compares the manifest's network
with the weights' shapes (laid out on torch's meta device, so a manifest claiming a huge network
allocates nothing), then builds it and loads the weights strictly; any mismatch, and any file
the system will not let us read or whose own format refuses it, is a :class:`StoreError` naming
the entry, the file and what is wrong. :func:`open_store` isolates entries: whatever goes wrong with one (a StoreError,
or any other exception) skips it with one logged line while the others load (the traceback of
an unexpected exception only at DEBUG). Weights are read with safetensors: no pickle anywhere.
An entry goes in with the modes the writer's umask gives a new folder and file: another user
serves what one builds.

Its modules, each one idea: files (the names, checksums, StoreError), builds (build folders,
their locks, stale ones removed, an entry moved aside put back), write (write_entry, network_table), manifest
(the manifest's checks), network (the network a manifest describes, fitted to the mesh), load
(load_entry, check_store, open_store).
"""

from __future__ import annotations

from .builds import UNLOCKED_BUILD_AGE_S, _build_folder, remove_stale_builds
from .files import FORMAT_VERSION, MANIFEST, MESH, WEIGHTS, StoreError, sha256
from .load import Entry, check_store, load_entry, open_store
from .network import network_from_manifest
from .write import check_entry_place, network_table, write_entry

__all__ = [
    "FORMAT_VERSION",
    "MANIFEST",
    "MESH",
    "UNLOCKED_BUILD_AGE_S",
    "WEIGHTS",
    "Entry",
    "StoreError",
    "_build_folder",  # a test's second process starts a build with it, as write_entry does
    "check_entry_place",
    "check_store",
    "load_entry",
    "network_from_manifest",
    "network_table",
    "open_store",
    "remove_stale_builds",
    "sha256",
    "write_entry",
]
