"""Atomic directory outputs that never replace data they did not write.

An output is built in a temporary sibling, then renamed into place: an interrupted writer leaves
either the previous complete directory or nothing, never a half-written directory under the
final name (DESIGN.md, "Training on Ray").

Every output holds a manifest (:data:`MANIFEST`) naming its owner, the stage or writer that made
it. An existing path is replaced only when it is an empty directory or a directory whose manifest
names the same owner. Anything else (a user's real dataset, an unrelated directory, a file,
another stage's output) is refused with a ``ValueError`` and left exactly as it was.

Temporary and previous copies are siblings named ``.<name>.tmp-<host>-<pid>-<random>`` and
``.<name>.old-<host>-<pid>-<random>``. The next writer of the same output removes the ones whose
creating process on this host has died, and, when a kill between the two renames left no final
directory, renames the previous copy back. Copies of live processes or of other hosts are never
touched, so concurrent writers do not disturb each other.

A single file is replaced the same way, without a manifest: :func:`replace_file`.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import socket
import tempfile
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

#: File inside every output naming its owner. Its content depends on the owner only, so
#: identical runs give byte-identical outputs (DVC hashes, pipelines.identity fingerprints).
MANIFEST = ".motionforge-output.json"
MANIFEST_FORMAT = 1


def manifest_owner(directory: Path) -> str | None:
    """The owner named by ``directory``'s manifest; None without a readable one."""
    try:
        manifest = json.loads((Path(directory) / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    owner = manifest.get("owner") if isinstance(manifest, dict) else None
    return owner if isinstance(owner, str) else None


def _write_manifest(directory: Path, owner: str) -> None:
    manifest = {"format": MANIFEST_FORMAT, "owner": owner}
    (directory / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n", encoding="utf-8")


def _refusal(final: Path, owner: str) -> str | None:
    """Why ``owner`` may not replace ``final``; None when it may."""
    if final.is_symlink():
        return "it is a symbolic link"
    if not final.exists():
        above = next((parent for parent in final.parents if parent.exists()), None)
        if above is not None and not above.is_dir():
            return f"{above} is a file, not a directory"
        return None
    if not final.is_dir():
        return "it is a file" if final.is_file() else "it exists and is not a directory"
    found = manifest_owner(final)
    if found == owner:
        return None
    if found is not None:
        return f"it holds the output of {found}, not of {owner}"
    if any(final.iterdir()):
        return f"it is a directory that {owner} did not write (no {MANIFEST} inside)"
    return None


def _check_replaceable(final: Path, owner: str) -> None:
    reason = _refusal(final, owner)
    if reason is not None:
        raise ValueError(f"refusing to replace {final}: {reason}; move it away or choose another output path")


def _host_id() -> str:
    """Short fixed-length id of this host, part of temporary names (pids mean nothing elsewhere)."""
    return hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def _stale_copies(final: Path, kind: str) -> list[Path]:
    """``final``'s ``.tmp`` or ``.old`` siblings made on this host by processes that have died."""
    pattern = re.compile(rf"\.{re.escape(final.name)}\.{kind}-([0-9a-f]{{8}})-(\d+)-[a-z0-9_]+")
    if not final.parent.is_dir():
        return []
    host = _host_id()
    stale = []
    for sibling in final.parent.iterdir():
        match = pattern.fullmatch(sibling.name)
        if match and match[1] == host and not _process_alive(int(match[2])) and sibling.is_dir():
            stale.append(sibling)
    return stale


def _tidy_interrupted_writes(final: Path, owner: str) -> None:
    """Remove temporary copies of dead writers; restore a previous output a killed swap left aside."""
    for tmp in _stale_copies(final, "tmp"):
        shutil.rmtree(tmp, ignore_errors=True)
    previous = [old for old in _stale_copies(final, "old") if manifest_owner(old) == owner]
    if previous and not final.exists() and not final.is_symlink():
        newest = max(previous, key=lambda p: p.stat().st_mtime_ns)
        newest.rename(final)
        warnings.warn(f"restored {final} from {newest.name}, left by an interrupted write", stacklevel=3)
    if manifest_owner(final) == owner:  # copies left by finished swaps whose clean-up was killed
        for old in _stale_copies(final, "old"):
            shutil.rmtree(old, ignore_errors=True)


def check_output(final: Path, *, owner: str) -> None:
    """Tidy leftovers of interrupted writes of ``final``, then raise ValueError unless ``owner`` may replace it.

    :func:`atomic_directory` does this on entry; a stage calls it first as well, so that a
    refused path costs no work.
    """
    final = Path(final)
    _tidy_interrupted_writes(final, owner)
    _check_replaceable(final, owner)


@contextmanager
def atomic_directory(final: Path, *, owner: str) -> Iterator[Path]:
    """Yield an empty temporary directory that replaces ``final`` when the block succeeds.

    ``owner`` (the stage or writer) is recorded in the output's manifest. ``final`` must be
    absent, an empty directory or an earlier output of the same owner: otherwise ValueError,
    on entry and again before the swap. On any exception the temporary directory is removed
    and ``final`` is left untouched.
    """
    final = Path(final)
    check_output(final, owner=owner)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.tmp-{_host_id()}-{os.getpid()}-", dir=final.parent))
    umask = os.umask(0)
    os.umask(umask)
    tmp.chmod(0o777 & ~umask)  # mkdtemp makes 0700; the final directory gets normal permissions
    try:
        yield tmp
        _write_manifest(tmp, owner)  # last, so it replaces one a nested writer left in tmp
        _check_replaceable(final, owner)  # something may have appeared there meanwhile
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = final.with_name(f".{final.name}.old-{tmp.name[len(f'.{final.name}.tmp-'):]}")
    if final.exists():
        final.rename(old)
    try:
        tmp.rename(final)
    except OSError:
        if old.exists():
            old.rename(final)  # put the previous complete directory back
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    shutil.rmtree(old, ignore_errors=True)
    if old.exists():
        warnings.warn(f"could not remove the previous {final.name} at {old}", stacklevel=3)


def replace_file(path: Path, write: Callable[[Path], object]) -> None:
    """``write(tmp)`` into a temporary sibling of ``path`` (same suffix, for writers that go by it), then
    rename it onto ``path``: a failed write leaves the previous file, or none, never half of one."""
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
