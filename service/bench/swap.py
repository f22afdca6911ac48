"""The report folder's swap: a run writes its whole new report in a locked scratch folder beside
``--out`` (``.bench-NAME-XXXXXXXX``), then puts it in place at once, so that a run stopped at
any instant (Ctrl-C, SIGKILL, a crash) leaves ``--out`` the old report or the new one, never a
mix; the next run clears what such a run left (:func:`recover`), a stopped minutes run's rows set
aside beside ``--out`` (:func:`set_aside`), never removed.

In place at once: one exchange of the two folders (Linux's renameat2 RENAME_EXCHANGE) where the
file system has it; elsewhere two renames, the old folder to ``.bench-NAME.old`` and the new to
``NAME``, for which a run stopped between them leaves ``--out`` missing until the next restores
it. Where the folder cannot be swapped (a mount point, an overlayfs lower layer, the working
directory, a parent the user cannot write), the files are moved in one by one, as before.

A run holds a lock beside ``--out`` (``.bench-NAME.lock``, :func:`hold`) from before it reads
``--out`` until it ends, so a second run into the same folder is refused, not merged over."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import stat
import time
from collections.abc import Iterator
from pathlib import Path

from ..folders import RANDOM, exchange, locked_folder, same_folder, try_lock
from .results import MINUTES_ROWS

SCRATCH_PREFIX = ".bench-"


class Busy(RuntimeError):
    """Another run is writing this report folder (its scratch folder is locked)."""


def _scratch_name(out: Path) -> re.Pattern[str]:
    return re.compile(rf"{re.escape(SCRATCH_PREFIX + out.name)}-{RANDOM}")


def backup_of(out: Path) -> Path:
    """Where the two renames keep the old report while the new one goes in."""
    return out.parent / f"{SCRATCH_PREFIX}{out.name}.old"


def hold(out: Path) -> tuple[Path, int] | None:
    """Lock `out` against other runs until :func:`release` (or this process's end) by a file
    beside it, ``.bench-NAME.lock`` (inside it, ``.bench-lock``, where its parent cannot be
    written): the file and its descriptor; None where no such file can be made (no parent yet)
    or the system has no locks; :class:`Busy` where another run holds it. Without it two runs
    that started together both read the old report, and the later one's swap dropped the other's
    parts (or mixed its files in)."""
    for path in (out.parent / f"{SCRATCH_PREFIX}{out.name}.lock", out / f"{SCRATCH_PREFIX}lock"):
        for _ in range(8):
            try:
                fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
            except OSError:
                break  # the next place, if any
            got = try_lock(fd)
            if got is False:
                os.close(fd)
                raise Busy(f"another elastreg bench is writing {out} (it holds {path})")
            if got is None:
                os.close(fd)
                return None
            if same_folder(path, fd):  # else its holder removed it between the open and the lock
                return path, fd
            os.close(fd)
        else:
            raise Busy(f"{path} keeps changing hands: other elastreg benches are writing {out}")
    return None


def release(held: tuple[Path, int] | None) -> None:
    """Remove the lock file, then drop the lock: a run waiting on the removed file tries again."""
    if held is None:
        return
    with contextlib.suppress(OSError):
        os.remove(held[0])
    os.close(held[1])


def _held(path: Path) -> bool:
    """Whether another process holds the lock of the folder `path` (a live run's)."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
    try:
        return try_lock(fd) is False
    finally:
        os.close(fd)  # drops the lock if this process took it


def set_aside(scratch: Path, out: Path, kind: str = "interrupted") -> Path:
    """Move the scratch folder of a run stopped with minutes rows (hours of builds; `kind`
    interrupted) or of a finished report that could not go in (unplaced) beside `out`, as
    ``NAME.KIND-YYYYMMDD-HHMMSS`` (its last row's or its results' time), a name no run clears;
    its new path. OSError where it cannot be moved."""
    made = scratch / (MINUTES_ROWS if kind == "interrupted" else "results.json")
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(made.stat().st_mtime))
    aside = out.parent / f"{out.name}.{kind}-{stamp}"
    if aside.exists() or aside.is_symlink():  # two stopped in one second: the scratch's random part too
        aside = aside.with_name(f"{aside.name}-{scratch.name[-8:]}")
    os.rename(scratch, aside)
    return aside


def keep_unplaced(scratch: Path, out: Path) -> Path:
    """Keep the finished report in `scratch` that could not be put in `out` from every later run:
    set aside beside `out` (NAME.unplaced-TIME), else, for a scratch inside `out` (a parent the
    user cannot write), renamed there to ``.bench-unplaced-TIME``, which no run clears or
    replaces; its path (`scratch` itself where neither rename can be done)."""
    try:
        return set_aside(scratch, out, "unplaced")
    except OSError:
        if scratch.parent != out:
            return scratch
    stamp = time.strftime("%Y%m%d-%H%M%S")
    inside = out / f"{SCRATCH_PREFIX}unplaced-{stamp}-{scratch.name[-8:]}"
    try:
        os.rename(scratch, inside)
    except OSError:
        return scratch
    return inside


def _clear(scratch: Path, out: Path, what: str) -> str:
    """Remove a dead run's scratch folder, or set it aside where it holds minutes rows; one line."""
    if not (scratch / MINUTES_ROWS).is_file():
        shutil.rmtree(scratch)
        return f"removed {scratch}, the scratch folder of a run stopped {what}"
    try:
        aside = set_aside(scratch, out)
    except OSError as exc:
        if scratch.parent != out:  # beside `out`, where this run makes its own: refused, nothing lost
            raise
        # inside `out` (no folder can be made beside it): left there, which no run removes
        why = exc.strerror or exc
        return f"kept {scratch}, a run stopped {what}, for its minutes rows (not moved beside {out}: {why})"
    return f"moved {scratch}, a run stopped {what}, to {aside}: its {MINUTES_ROWS} holds the rows built so far"


def recover(out: Path) -> list[str]:
    """Clear what a run into `out` stopped at any instant left, before this run touches `out`:
    its scratch folder (removed, or set aside where it holds minutes rows), the old report the
    two renames put aside (put back where `out` is missing, else removed), and an older version's
    scratch folder inside `out`. One line a folder, for the user; :class:`Busy` where a live run
    is writing `out`."""
    notes: list[str] = []
    if not out.parent.is_dir():
        return notes
    scratch = _scratch_name(out)
    for path in sorted(out.parent.iterdir()):
        if scratch.fullmatch(path.name) and path.is_dir() and not path.is_symlink():
            if _held(path):
                raise Busy(f"another elastreg bench is writing {out} (its scratch folder {path} is locked)")
            notes.append(_clear(path, out, "before its report went in"))
    backup = backup_of(out)
    if backup.is_dir() and not backup.is_symlink():
        if not out.exists():
            os.rename(backup, out)
            notes.append(f"restored {out} from {backup}, where a run stopped while swapping reports had put it")
        elif out.is_dir() and _held(out):
            raise Busy(f"another elastreg bench is writing {out} (it is putting its report in place)")
        else:
            shutil.rmtree(backup)
            notes.append(f"removed {backup}, the old report of a run stopped once its own was in {out}")
    if out.is_dir():  # versions before this module, and runs that cannot swap, write theirs inside `out`
        for path in sorted(out.glob(f"{SCRATCH_PREFIX}*")):
            if (
                re.fullmatch(rf"{re.escape(SCRATCH_PREFIX)}{RANDOM}", path.name)
                and path.is_dir()
                and not path.is_symlink()
            ):
                if _held(path):  # a live run's, which moves its files in one by one
                    raise Busy(f"another elastreg bench is writing {out} (its scratch folder {path} is locked)")
                notes.append(_clear(path, out, "before its files were moved"))
    return notes


def holds_cwd(out: Path) -> bool:
    """Whether `out` is, or holds, this process's working directory (``--out .``): a swap would
    leave the caller's shell in the old, deleted folder."""
    cwd, real = Path(os.path.realpath(os.getcwd())), Path(os.path.realpath(out))
    return cwd == real or real in cwd.parents


def scratch_folder(out: Path) -> tuple[Path, int, str | None]:
    """A new folder for a run's report and a descriptor holding its lock until closed (the kernel
    drops it when the process dies: :func:`recover` then removes it), and a note where it is not
    the swap's: beside the folder `out`, with `out`'s group and permissions; inside `out`, whose
    files :func:`put_in_place` then moves in one by one, where `out` holds the working directory
    or no folder can be made beside it (a parent the user cannot write)."""
    if holds_cwd(out):
        path, fd = _locked_folder(out, SCRATCH_PREFIX)
        return path, fd, f"{out} holds the working directory, so the report's files are moved into it one by one"
    try:
        path, fd = _locked_folder(out.parent, f"{SCRATCH_PREFIX}{out.name}-")
    except OSError as exc:
        path, fd = _locked_folder(out, SCRATCH_PREFIX)
        why = exc.strerror or exc
        return path, fd, f"no scratch folder beside {out} ({why}), so the report's files are moved into it one by one"
    st = os.stat(out)
    with contextlib.suppress(PermissionError):  # a group the runner is not in keeps the runner's
        os.chown(fd, -1, st.st_gid)
    # after the chown, which clears setgid; ACLs and extended attributes are not carried over
    os.chmod(fd, stat.S_IMODE(st.st_mode))  # mkdtemp's 0700 would become the report's
    return path, fd, None


def _locked_folder(parent: Path, prefix: str) -> tuple[Path, int]:
    """A new folder in `parent` named `prefix` and 8 random characters, locked (where locks exist)."""
    path, fd, _ = locked_folder(parent, prefix)
    return path, fd


def carry_over(old: Path, new: Path) -> None:
    """Give `new` every file of the report folder `old` it lacks (the parts a run kept, files
    not its own): hard links, copies where the file system has none; `new` is written by now,
    so nothing writes through a link into the old report."""
    for src in sorted(old.rglob("*")):
        rel = src.relative_to(old)
        if rel.parts[0].startswith(SCRATCH_PREFIX) or src.is_dir() and not src.is_symlink():
            continue
        dest = new / rel
        if dest.exists() or dest.is_symlink():
            continue
        dest.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(src, dest, follow_symlinks=False)
        except OSError:
            shutil.copy2(src, dest, follow_symlinks=False)


def put_in_place(new: Path, out: Path, whole: bool) -> str | None:
    """Make the finished report folder `new` the folder `out` (`whole`: nothing else of `out`
    kept) and remove the old one; a note where that could not be done at once (`out` a mount
    point, EBUSY; an overlayfs lower-layer folder, EXDEV) and the files were moved in one by one."""
    if new.parent == out:  # a scratch folder inside `out`: no swap
        move_in(new, out, whole)
        return None
    backup = backup_of(out)
    try:
        with _signals_held():
            exchanged = out.exists() and exchange(new, out)
            if not exchanged:
                _two_renames(new, out, backup)
    except OSError as exc:
        inner, fd = _locked_folder(out, SCRATCH_PREFIX)  # on `out`'s file system, so each move is a rename
        try:
            try:
                os.rename(new, inner)  # onto the empty folder
            except OSError:  # another file system (a mount point)
                shutil.copytree(new, inner, symlinks=True, dirs_exist_ok=True)
            move_in(inner, out, whole)
        except OSError as failed:
            failed.kept = inner if not new.exists() else new  # type: ignore[attr-defined]
            raise
        finally:
            os.close(fd)
        shutil.rmtree(inner, ignore_errors=True)
        shutil.rmtree(new, ignore_errors=True)  # copied
        return (
            f"could not swap the report into {out} at once ({exc.strerror or exc}): its files were moved in one by one"
        )
    shutil.rmtree(new if exchanged else backup, ignore_errors=True)  # exchanged: `new` names the old report
    return None


def _two_renames(new: Path, out: Path, backup: Path) -> None:
    """The old folder aside, the new in its place; the old put back where the second fails."""
    if out.exists():
        os.rename(out, backup)
    try:
        os.rename(new, out)
    except OSError:
        if backup.exists():
            os.rename(backup, out)
        raise


def move_in(new: Path, out: Path, whole: bool) -> None:
    """What versions before the swap did: move the files of the report folder `new` into `out`
    one by one, results.json last (renames in one file system: each file changes whole); `whole`:
    then remove what else `out` holds (scratch folders aside), as the swap would have."""
    files = sorted(
        (
            Path(d, f).relative_to(new)
            for d, dirs, names in os.walk(new)
            for f in names + [x for x in dirs if Path(d, x).is_symlink()]
        ),
        key=lambda rel: rel.name == "results.json",
    )
    for rel in files:
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        os.replace(new / rel, out / rel)
    if not whole:
        return
    kept = set(files)
    for d, dirs, names in os.walk(out, topdown=False):
        rel_dir = Path(d).relative_to(out)
        if rel_dir.parts and rel_dir.parts[0].startswith(SCRATCH_PREFIX):
            continue
        for name in names + [x for x in dirs if Path(d, x).is_symlink()]:
            if rel_dir / name not in kept and not (not rel_dir.parts and name.startswith(SCRATCH_PREFIX)):
                os.remove(Path(d, name))
        if rel_dir.parts and not os.listdir(d):
            os.rmdir(d)


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """Ctrl-C and SIGTERM wait out the renames (microseconds), then act as they would have."""
    caught: list[int] = []
    before = {s: signal.signal(s, lambda n, _frame: caught.append(n)) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in before.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)
        for n in caught:
            signal.raise_signal(n)
