"""Build folders: a build writes its entry in a locked hidden folder of the store; the folders
of builds whose process is gone are removed, and an entry a build moved aside is put back."""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import shutil
import stat
import tempfile
import time
from pathlib import Path

from ..folders import RANDOM, locked_folder, same_folder, try_lock
from ..scene import MODEL_ID
from .files import _MAX_MANIFEST, MANIFEST, MESH, WEIGHTS, _digest, _is_digest, log

#: an entry moved aside while its replacement goes in: ..ID-XXXXXXXX (no build's temporary
#: folder, .ID-XXXXXXXX.build, nor any entry starts so)
_ASIDE = ".."
#: a build's temporary folder ends so: a hidden folder of the user's is never taken for one
_BUILDING = ".build"
_BUILD_FOLDER = re.compile(rf"\.{MODEL_ID.pattern.strip('^$')}-{RANDOM}{re.escape(_BUILDING)}")
#: a build's folder with no lock: written before the lock came in (ea8e4fa), or where the file
#: system has none (_build_folder). A user's `.liver-original` or `.liver-20240501` has such a
#: name too: only a write cut off (_cut_off) is ever removed
_UNLOCKED_BUILD_FOLDER = re.compile(rf"\.{MODEL_ID.pattern.strip('^$')}-{RANDOM}")
#: an unlocked build folder untouched this long has no writer: write_entry fills one in seconds
UNLOCKED_BUILD_AGE_S = 24 * 3600.0


def _build_folder(store: Path, entry_id: str) -> tuple[Path, int | None]:
    """A new folder for a build of `entry_id` to write in, and a descriptor of it holding its
    lock until closed (the kernel drops it when the process dies: a folder nobody locks has no
    writer left). Where locks are missing the folder is named .ID-XXXXXXXX, which a cleaner takes
    only once it has not changed for a day, and the descriptor is None."""
    path, fd, locked = locked_folder(store, f".{entry_id}-", _BUILDING)
    if locked:
        return path, fd
    os.close(fd)
    with contextlib.suppress(OSError):
        path.rmdir()
    return Path(tempfile.mkdtemp(prefix=f".{entry_id}-", dir=store)), None


def _stale(path: Path, fd: int) -> bool:
    """Whether the build folder `path`, open as `fd`, has no writer left (see remove_stale_builds)."""
    if _BUILD_FOLDER.fullmatch(path.name):  # its lock tells; no locks here: nothing can tell
        return bool(try_lock(fd)) and same_folder(path, fd)
    if try_lock(fd) is False or not same_folder(path, fd):
        return False
    try:
        with os.scandir(fd) as listing:
            inside = {e.name: e.stat(follow_symlinks=False) for e in listing}
    except OSError:
        return False
    if not inside:  # nothing to reclaim, and nothing shows it was a build's
        return False
    if any(name not in (MANIFEST, MESH, WEIGHTS) or not stat.S_ISREG(st.st_mode) for name, st in inside.items()):
        return False  # a folder of the user's that happens to have such a name
    newest = max([os.fstat(fd).st_mtime, *(st.st_mtime for st in inside.values())])
    if time.time() - newest <= UNLOCKED_BUILD_AGE_S:
        return False
    cut_off = _cut_off(fd, set(inside))
    if cut_off is False:
        log.warning(
            "model store %s: kept %s: named like an older version's build folder, but it holds a complete entry "
            "(rename it if it is yours, remove it if not)",
            path.parent,
            path.name,
        )
    return bool(cut_off)


def _cut_off(fd: int, names: set[str]) -> bool | None:
    """Whether the entry's files `names`, in the folder open as `fd`, are a write that never
    finished, as write_entry leaves one killed or cut by a power loss: True with no manifest (it
    is written last), a manifest that is not JSON (cut short) or a file it lists missing or not
    matching its checksum; False for a complete entry (a user's copy as well as a build's);
    None where nothing can tell (an unreadable file, a manifest unlike any a build writes)."""
    if MANIFEST not in names:
        return True
    try:
        with _open_at(fd, MANIFEST) as f:
            raw = f.read(_MAX_MANIFEST + 1)
    except OSError:
        return None
    if len(raw) > _MAX_MANIFEST:
        return None
    try:
        manifest = json.loads(raw)
    except ValueError:  # not JSON, nor UTF-8
        return True
    files = manifest.get("files") if isinstance(manifest, dict) else None
    if not isinstance(files, dict) or set(files) != {MESH, WEIGHTS} or not all(map(_is_digest, files.values())):
        return None  # unlike any manifest a build writes: not a write cut off
    for fname, digest in files.items():
        if fname not in names:
            return True
        try:
            with _open_at(fd, fname) as f:
                if _digest(f) != digest:
                    return True
        except OSError:
            return None
    return False


def _open_at(fd: int, name: str):
    """The regular file `name` in the folder open as `fd`, open for reading: never through a
    link, nor waiting on a FIFO put in its place."""
    f = os.open(name, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK, dir_fd=fd)
    if not stat.S_ISREG(os.fstat(f).st_mode):
        os.close(f)
        raise OSError(errno.EINVAL, f"{name} is not a regular file")
    return open(f, "rb")


def remove_stale_builds(store: Path) -> list[str]:
    """Remove the folders of builds whose process is gone (killed, or the machine lost power
    mid-write): a .ID-XXXXXXXX.build folder whose lock nobody holds; a live build's lock keeps
    its folder. A folder named .ID-XXXXXXXX (XXXXXXXX: tempfile's 8 characters of [a-z0-9_]) has
    no lock to tell (versions before the lock wrote it, and a build still does where the file
    system has no locks), and a user's backup may be named so (.liver-original, .liver-20240501):
    it is removed only when it is a real folder (not a link) that holds nothing but an entry's
    regular files, nothing in it has changed for UNLOCKED_BUILD_AGE_S (a day; a build fills its
    folder in seconds), and those files are shown to be a write cut off: no manifest, a manifest
    that is not JSON, or a file it lists missing or not matching its checksum. A complete entry
    under such a name is kept, with one warning naming it at each scan; an empty folder, or one
    holding anything else, is kept silently. Any other name (an aside entry, ..ID-*, a hidden
    folder of the user's) is never touched. One logged line per folder removed; returns their
    names. A store this process cannot write (a read-only mount, another owner's) keeps them,
    untouched: one warning says how many and how to clean them, and nothing fails."""
    store = Path(store)
    removed: list[str] = []
    try:
        names = sorted(
            p.name
            for p in store.iterdir()
            if _BUILD_FOLDER.fullmatch(p.name) or _UNLOCKED_BUILD_FOLDER.fullmatch(p.name)
        )
    except OSError:
        return removed
    writable = os.access(store, os.W_OK)  # else rmtree would empty a folder it cannot then remove
    left: list[str] = []
    for name in names:
        path = store / name
        try:  # never through a link: O_NOFOLLOW
            fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
        except OSError:
            continue
        try:
            if not _stale(path, fd):
                continue
            if not writable:
                left.append(name)
                continue
            try:
                shutil.rmtree(path)
            except FileNotFoundError:  # a build removing the entry it swapped out, at the same time
                pass
            except OSError as exc:
                log.error("model store %s: cannot remove %s, a stale build's folder: %s", store, name, exc)
                continue
            what = "a build whose process is gone" if _BUILD_FOLDER.fullmatch(name) else "a build's write cut off"
            log.warning("model store %s: removed %s, the folder of %s", store, name, what)
            removed.append(name)
        finally:
            os.close(fd)
    if left:
        log.warning(
            "model store %s is read-only here: %d stale build folder(s) left (%s); remove them as a user who can "
            "write it, by hand once no build runs or by `elastreg serve` or a build into it",
            store,
            len(left),
            ", ".join(left[:3]) + (", ..." if len(left) > 3 else ""),
        )
    return removed


def _restore_aside(store: Path) -> None:
    """Put back an entry a build moved aside (..ID-XXXXXXXX) where the process died before its
    replacement went in: the store serves the old entry rather than none."""
    for path in store.iterdir():
        if not path.name.startswith(_ASIDE):
            continue
        entry_id = path.name[len(_ASIDE) :].rsplit("-", 1)[0]
        final = store / entry_id
        if path.is_dir() and not final.exists() and MODEL_ID.fullmatch(entry_id):
            try:
                os.replace(path, final)
                log.warning("model %s: restored the entry a build had moved aside (%s)", entry_id, path.name)
            except OSError as exc:
                log.error("model %s: cannot restore %s: %s", entry_id, path.name, exc)
