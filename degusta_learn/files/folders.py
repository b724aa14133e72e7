"""Output folders written whole or not at all: the one mechanism of evaluate, compare, render, data generate
and every model export.

Usage:
    from degusta_learn.files.folders import OutputKind, write_folder

    EVAL = OutputKind("evaluation report", ("metrics.json", "per_episode.csv", "report.md"))
    with write_folder("runs/eval", EVAL) as tmp:    # tmp: an empty staging folder beside runs/eval
        (tmp / "report.md").write_text(...)         # write every file here
    # on success runs/eval holds exactly the new set; on any exception it is untouched

How it works. The whole output set is written into a staging folder `.NAME.PID-RAND.tmp` beside the
target. On success it is swapped in: the old target is renamed to `.NAME.PID-RAND.old.tmp`, the staging
folder to the target, and the old folder is removed. On an exception (KeyboardInterrupt and SIGTERM
included) the staging folder is removed and the target is untouched. After a SIGKILL the next run of any
command writing that target cleans the leftovers: a staging folder whose process is gone is removed, and
an old folder whose swap was cut short is renamed back when the target is missing (so a kill never loses
the previous outputs).

Whose folder. A target is replaced whole only when it is *ours*: empty, or every entry's name is one
the command writes (`OutputKind.patterns`) and `OutputKind.check` (if any) accepts it. A folder holding
anything else (a user's notes beside their predictions) is never deleted: with `merge=True` the new
entries are renamed in one by one and the command's own stale entries moved out (foreign files stay);
with `merge=False` (data generate) the command is refused with a one-line message.
`keep` names entries of the old folder carried into the new one (hard links, so no byte is copied and a
crash at any point leaves every kept file in place): compare's resumable `predictions/`.
"""

from __future__ import annotations

import contextlib
import fnmatch
import os
import re
import shutil
import signal
import tempfile
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from degusta_learn.errors import DegustaError, Terminated
from degusta_learn.files.atomic import UMASK
from degusta_learn.files.locks import hold
from degusta_learn.files.paths import path_problem, refuse_shipped, shown_path
from degusta_learn.files.write_errors import write_failure


@dataclass(frozen=True)
class OutputKind:
    """What a command writes into its output folder, and whether a foreign folder may receive it."""

    what: str
    """Names the output in messages, e.g. "evaluation report"."""
    patterns: tuple[str, ...]
    """fnmatch patterns of the top-level entries the command writes."""
    check: Callable[[Path], bool] | None = None
    """Extra proof that an existing folder is ours (datasets: meta.json names a degusta generator)."""
    merge: bool = True
    """A folder holding foreign entries: True = rename our entries in beside them; False = refuse."""

    def owns_name(self, name: str) -> bool:
        return any(fnmatch.fnmatchcase(name, p) for p in self.patterns)

    def foreign(self, folder: Path) -> list[str]:
        """Entries of `folder` this command does not write (sorted)."""
        return sorted(p.name for p in folder.iterdir() if not self.owns_name(p.name))


_STAGE = r"\.{name}\.(\d+)-[a-z0-9_]+\.tmp"
_OLD = r"\.{name}\.(\d+)-[a-z0-9_]+\.old\.tmp"
_LEGACY = r"\.{name}\.[a-z0-9_]{{8}}\.tmp"  # data generate before this module: mkdtemp, no pid
_LEGACY_OLD = r"\.{name}\.old-\.{name}\.[a-z0-9_]{{8}}\.tmp"


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    return True


def _all_ours(folder: Path, kind: OutputKind) -> bool:
    try:
        return folder.is_dir() and not folder.is_symlink() and not kind.foreign(folder)
    except OSError:
        return False


def clean_stale(target: Path, kind: OutputKind) -> list[str]:
    """Remove (or restore) what an interrupted write of `target` left beside it; returns what was done."""
    name = re.escape(target.name)
    stage, old = re.compile(_STAGE.format(name=name)), re.compile(_OLD.format(name=name))
    legacy, legacy_old = re.compile(_LEGACY.format(name=name)), re.compile(_LEGACY_OLD.format(name=name))
    done = []
    try:
        siblings = sorted(target.parent.iterdir())
    except OSError:
        return done
    for p in siblings:
        if p.is_symlink() or not p.is_dir():
            continue
        m = stage.fullmatch(p.name) or old.fullmatch(p.name)
        if m and _alive(int(m.group(1))):
            continue  # another run is writing this target right now
        is_old = bool(old.fullmatch(p.name)) or bool(legacy_old.fullmatch(p.name) and _all_ours(p, kind))
        is_stage = bool(stage.fullmatch(p.name)) or bool(legacy.fullmatch(p.name) and _all_ours(p, kind))
        if is_old and not target.exists() and not target.is_symlink():
            with contextlib.suppress(OSError):
                p.rename(target)  # the swap was cut between its two renames: put the previous outputs back
                done.append(f"restored {target} from {p.name}")
                continue
        if is_old or is_stage:
            shutil.rmtree(p, ignore_errors=True)
            done.append(f"removed {p.name}")
    return done


def check_target(target: str | os.PathLike, kind: OutputKind, replace: bool = True,
                 allow_shipped: bool = False) -> Path:
    """Clean leftovers of an interrupted run and refuse a target we may not write; returns the target.

    `replace=False`: an existing non-empty folder is refused (data generate without --overwrite). A folder inside
    the package's shipped models or configs is refused (`guard.refuse_shipped`) unless `allow_shipped` (a
    pretraining run asked by name to replace the shipped base).
    """
    if not str(target).strip():
        raise DegustaError("the output folder path is empty; give the folder to write")
    _refuse_path_problem(target)
    if not allow_shipped:
        refuse_shipped(target)
    target = Path(target)
    if target.is_symlink():
        try:
            target = target.resolve(strict=True)
        except (OSError, RuntimeError) as e:
            raise DegustaError(f"{target}: cannot follow the link ({e})") from None
    for parent in target.parents:
        if parent.is_dir():
            break
        if parent.exists() or parent.is_symlink():
            raise DegustaError(f"{target}: cannot write here: a parent, {parent}, is a file, not a folder")
    clean_stale(target, kind)
    if target.exists() and not target.is_dir():
        raise DegustaError(f"{target}: exists and is not a folder")
    if target.is_dir():
        try:
            entries = list(target.iterdir())
        except OSError as e:
            raise DegustaError(f"{target}: cannot read the folder ({e.strerror or e})") from None
        if entries and not replace:
            raise DegustaError(f"{target}: folder exists and is not empty (pass --overwrite to replace it)")
        foreign = kind.foreign(target) if entries else []
        if entries and not kind.merge:
            if foreign:
                raise DegustaError(f"{target}: refusing to replace a folder that is not a {kind.what} degusta wrote "
                                   f"(it holds {_names(foreign)}); choose another folder or remove it yourself")
            if kind.check is not None and not kind.check(target):
                raise DegustaError(f"{target}: refusing to replace a folder that is not a {kind.what} degusta wrote "
                                   "(no degusta generator signature in its meta.json); choose another folder or "
                                   "remove it yourself")
    return target


def _refuse_path_problem(target: str | os.PathLike, key: str | None = None) -> None:
    """One line (naming `key` when given) for a target no folder can be made at (paths.path_problem: a NUL byte, a
    name or path too long, a parent that is a file, non-UTF-8, a broken link ...), before `pathlib` is asked anything."""
    problem = path_problem(target)
    if problem:
        raise DegustaError(f"{f'{key}: ' if key else ''}{shown_path(target)}: {problem}")


def _names(names: Sequence[str]) -> str:
    shown = ", ".join(repr(n) for n in names[:3])
    return shown + (f" and {len(names) - 3} more" if len(names) > 3 else "")


def _link_tree(src: Path, dst: Path) -> None:
    """Hard-link (copy where links fail) `src` to `dst`: a file or a folder tree."""
    def link(s, d):
        try:
            os.link(s, d, follow_symlinks=False)
        except OSError:
            shutil.copy2(s, d, follow_symlinks=False)

    if src.is_dir() and not src.is_symlink():
        shutil.copytree(src, dst, symlinks=True, copy_function=link)
    else:
        link(src, dst)


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """While staging, SIGTERM raises KeyboardInterrupt so the staging folder is removed (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    try:
        previous = signal.getsignal(signal.SIGTERM)
    except (ValueError, AttributeError):
        yield
        return
    if previous not in (signal.SIG_DFL, None):
        yield
        return

    def handler(signum, frame):
        raise Terminated(signum)

    signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def write_folder(target: str | os.PathLike, kind: OutputKind, keep: Sequence[str] = (),
                 replace: bool = True, allow_shipped: bool = False) -> Iterator[Path]:
    """Yield an empty staging folder; on success its content becomes `target` whole (see module docstring).

    `keep`: entries of an existing target carried into the new one (hard links) unless the body writes
    them itself. An OSError while writing (or a failed write torch / safetensors report in their own exception
    types, `write_errors.write_failure`) becomes a DegustaError naming the target.
    The target is locked for the whole write (`locks.hold`: `.NAME.degusta-lock` beside it): a second writer of
    the same folder, in any process, is refused in one line naming the first.
    """
    target = check_target(target, kind, replace, allow_shipped)
    with hold(target, kind.what), _write_folder(target, kind, keep, replace) as stage:
        yield stage


@contextlib.contextmanager
def _write_folder(target: Path, kind: OutputKind, keep: Sequence[str], replace: bool) -> Iterator[Path]:
    target = check_target(target, kind, replace)  # again, under the lock: a writer that just finished counts
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=f".{target.name}.{os.getpid()}-", suffix=".tmp", dir=target.parent))
        stage.chmod(0o777 & ~UMASK)  # mkdtemp makes it private; an output folder is an ordinary folder
    except OSError as e:
        raise DegustaError(f"{target}: cannot create the output folder ({e.strerror or e})") from None
    try:
        with _sigterm_as_interrupt():
            if target.is_dir():
                for name in keep:
                    if (target / name).exists() or (target / name).is_symlink():
                        _link_tree(target / name, stage / name)
            try:
                yield stage
            except OSError as e:
                raise DegustaError(f"{target}: cannot write the {kind.what} ({e})") from None
            except Exception as e:  # noqa: BLE001 - only a failed write (torch's RuntimeError, SafetensorError)
                cause = write_failure(e)
                if cause is None:
                    raise
                raise DegustaError(f"{target}: cannot write the {kind.what} ({cause})") from None
            try:
                _commit(stage, target, kind)
            except OSError as e:
                raise DegustaError(f"{target}: cannot put the new {kind.what} in place ({e})") from None
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def _commit(stage: Path, target: Path, kind: OutputKind) -> None:
    if not target.exists():
        stage.rename(target)
        return
    if not kind.foreign(target) and (kind.check is None or not any(target.iterdir()) or kind.check(target)):
        old = stage.with_name(stage.name[: -len(".tmp")] + ".old.tmp")
        target.rename(old)
        try:
            stage.rename(target)
        except BaseException:
            with contextlib.suppress(OSError):
                old.rename(target)
            raise
        shutil.rmtree(old, ignore_errors=True)
        return
    if not kind.merge:  # checked up front; the folder changed under us
        raise DegustaError(f"{target}: the folder changed while the {kind.what} was written; nothing was replaced")
    # A folder that also holds foreign files: our entries are renamed in one by one; our stale ones move out.
    trash = stage / ".replaced"
    trash.mkdir()
    new = [p for p in stage.iterdir() if p != trash]
    for entry in target.iterdir():
        if kind.owns_name(entry.name) and not (stage / entry.name).exists():
            entry.rename(trash / entry.name)
    for src in new:
        dest = target / src.name
        if (src.is_dir() or dest.is_dir()) and (dest.exists() or dest.is_symlink()):
            dest.rename(trash / src.name)  # a folder is swapped, not merged
        os.replace(src, dest)
