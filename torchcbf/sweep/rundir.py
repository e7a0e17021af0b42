"""Run directories: where one command's outputs live, claimed before any work.

A run directory holds ``run.json`` (the manifest: which command, its settings, whether it
finished, the files it wrote) beside its outputs. :meth:`RunDir.claim` checks the location
first (not a file, not under a file, writable) and then:

- an empty or missing folder: a new run;
- a folder holding an unfinished or finished run of the same command with the same
  settings: continued with ``resume=True`` (what is done is kept and skipped);
- anything else that is not empty: refused unless ``overwrite=True``, which first removes
  the files the manifest of the earlier torchcbf run there lists (and its ``.parts``) and
  leaves every other file alone (a folder without a torchcbf manifest loses nothing; a
  ``run.json`` torchcbf did not write is never replaced).

A manifest is torchcbf's only when it says so (``"format": "torchcbf run"``).

So the outputs of two runs never mix. Every file is written through :mod:`torchcbf._io`
(temporary name, then rename).
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from torchcbf import _io
from torchcbf.sim import strict

MANIFEST = "run.json"
#: the mark of a manifest torchcbf wrote
FORMAT = "torchcbf run"
#: held (an exclusive ``flock``) by the process that claimed the folder, until it exits
LOCK = ".torchcbf.lock"
PARTS = ".parts"  # finished units of a scenario run (``torchcbf mppi-cbf``), kept for --resume


class OutputError(ValueError):
    """The output location cannot hold this run (the message says why and what to do)."""


def check_location(out: str | Path) -> Path:
    """``out`` as a folder this process can write: created if missing (OutputError if it is
    a file, lies under a file, or cannot be written)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputError(f"--out {out} is a file, not a folder")
    for parent in out.parents:
        if parent.exists():
            if not parent.is_dir():
                raise OutputError(f"--out {out}: {parent} is a file, not a folder")
            break
    try:
        out.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".probe.", suffix=_io.TMP_SUFFIX + ".probe", dir=out)
        os.close(fd)
        os.unlink(probe)
    except OSError as error:
        raise OutputError(f"--out {out} cannot be written: {error.strerror or error}") from None
    return out


class RunDir:
    """A claimed run directory (see the module docstring).

    Attributes:
        path: the folder.
        kind: the command (``"sweep"``, ``"tune"``, ``"mppi-cbf"``, ...).
        settings: what makes two runs the same run (compared on resume).
        resumed: whether an earlier run's work is continued.
    """

    def __init__(self, path: Path, kind: str, settings: Mapping[str, Any], resumed: bool):
        self.path = path
        self.kind = kind
        self.settings = strict(settings)
        self.resumed = resumed
        self.files: list[str] = []
        self._lock: Any = None

    @classmethod
    def claim(
        cls,
        out: str | Path,
        *,
        kind: str,
        settings: Mapping[str, Any],
        resume: bool = False,
        overwrite: bool = False,
        outputs: tuple[str, ...] = (),
    ) -> RunDir:
        """Check ``out`` and take it for a run of ``kind`` with ``settings`` (OutputError
        when it holds something else and neither flag allows it). ``outputs``: the names the
        run writes as it goes, listed in the manifest from the start (so that an interrupted
        run's files are known to ``overwrite``)."""
        if resume and overwrite:
            raise OutputError("--resume and --overwrite exclude each other")
        path = check_location(out)
        made_lock = not (path / LOCK).exists()
        lock = _lock(path)
        try:
            run = cls._take(path, kind, strict(settings), resume, overwrite, outputs)
        except BaseException:
            if made_lock:  # a folder refused keeps no trace of the attempt
                with contextlib.suppress(OSError):
                    (path / LOCK).unlink()
            if lock is not None:
                lock.close()
            raise
        run._lock = lock
        return run

    @classmethod
    def _take(
        cls,
        path: Path,
        kind: str,
        settings: dict[str, Any],
        resume: bool,
        overwrite: bool,
        outputs: tuple[str, ...],
    ) -> RunDir:
        """:meth:`claim` once the folder is checked and locked."""
        manifest = read_manifest(path)
        if manifest is None and (path / MANIFEST).exists():
            raise OutputError(
                f"--out {path} holds a {MANIFEST} that torchcbf did not write; use another --out"
            )
        entries = [p for p in path.iterdir() if not _io.is_temporary(p) and p.name != LOCK]
        if manifest is not None and resume:
            if manifest.get("kind") != kind:
                raise OutputError(
                    f"--out {path} holds a '{manifest.get('kind')}' run, not a '{kind}' run"
                )
            if manifest.get("settings") != settings:
                changed = sorted(
                    k
                    for k in set(settings) | set(manifest.get("settings", {}))
                    if settings.get(k) != manifest.get("settings", {}).get(k)
                )
                raise OutputError(
                    f"--resume: the run in {path} has other settings ({', '.join(changed)}); "
                    "run it again with the same arguments, or use another --out"
                )
            _io.remove_stale(path)
            run = cls(path, kind, settings, resumed=True)
            run.files = list(dict.fromkeys([*manifest.get("files", []), *outputs]))
            run._write_manifest(complete=False)
            return run
        if entries:
            if not overwrite:
                what = (
                    f"a '{manifest.get('kind')}' run"
                    if manifest is not None
                    else "files that are not a torchcbf run"
                )
                hint = (
                    "--resume to continue it, --overwrite to replace it"
                    if manifest is not None and manifest.get("kind") == kind
                    else "--overwrite to replace torchcbf's outputs there"
                )
                raise OutputError(f"--out {path} holds {what}; use another --out, or {hint}")
            clear(path, manifest)
        foreign = [name for name in outputs if (path / name).exists()]
        if foreign:
            raise OutputError(
                f"--out {path} holds {', '.join(foreign)}, which no torchcbf manifest there "
                "lists (an earlier run whose run.json is gone, or files of yours): move them "
                "away, or use another --out"
            )
        _io.remove_stale(path)
        run = cls(path, kind, settings, resumed=False)
        run.files = list(outputs)
        run._write_manifest(complete=False)
        return run

    def _write_manifest(self, complete: bool) -> None:
        data = {
            "format": FORMAT,
            "kind": self.kind,
            "settings": self.settings,
            "complete": complete,
            "files": self.files,
        }
        _io.write_json(self.path / MANIFEST, data)

    def record(self, *paths: str | Path) -> None:
        """Note output files of this folder in the manifest (rewritten at once)."""
        for p in paths:
            name = Path(p).name
            if name not in self.files:
                self.files.append(name)
        self._write_manifest(complete=False)

    def finish(self) -> None:
        """Mark the run complete and release the folder."""
        self._write_manifest(complete=True)
        self.release()

    def release(self) -> None:
        """Release the folder (the run stays incomplete unless :meth:`finish` said so): a
        run interrupted in this process can be resumed by it."""
        if self._lock is not None:
            self._lock.close()
            self._lock = None


@contextlib.contextmanager
def owned(run: RunDir | None, given: object) -> Iterator[None]:
    """A block in which ``run`` is used: released however the block ends where it was
    claimed by the caller (it is not ``given``, a :class:`RunDir` claimed elsewhere), so a
    run interrupted in a notebook can be resumed there."""
    try:
        yield
    finally:
        if run is not None and run is not given:
            run.release()


def _lock(path: Path) -> Any:
    """An exclusive lock on ``path`` for this process (the open lock file; closed, and so
    released, when the process ends), or OutputError where another process holds it. Where
    ``fcntl`` is missing (Windows) nothing is locked."""
    try:
        import fcntl
    except ImportError:
        return None
    for _ in range(8):
        handle = open(path / LOCK, "a")  # noqa: SIM115 - held open for the life of the run
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            raise OutputError(
                f"--out {path} is in use by another torchcbf run (wait for it, or use another "
                "--out)"
            ) from None
        try:  # the file locked is still the one at the path (a refused claim removes it)
            if os.stat(path / LOCK).st_ino == os.fstat(handle.fileno()).st_ino:
                return handle
        except FileNotFoundError:
            pass
        handle.close()
    raise OutputError(f"--out {path}: its lock file keeps changing; try again")


def read_manifest(path: str | Path) -> dict[str, Any] | None:
    """The manifest of the torchcbf run in ``path`` (None when there is none, it is
    unreadable, or torchcbf did not write it)."""
    try:
        data = json.loads((Path(path) / MANIFEST).read_text())
    except (OSError, ValueError):
        return None
    ours = isinstance(data, dict) and data.get("format") == FORMAT
    return data if ours and isinstance(data.get("kind"), str) else None


def clear(path: Path, manifest: Mapping[str, Any] | None) -> None:
    """Remove the outputs the torchcbf ``manifest`` of ``path`` lists, the manifest and its
    ``.parts`` (nothing without a manifest; other files stay)."""
    if manifest is None:
        return
    listed = [str(n) for n in manifest.get("files", [])]
    names = {MANIFEST} | {n for n in listed if Path(n).name == n and n not in ("", ".", "..")}
    for target in (path / n for n in names):
        with contextlib.suppress(FileNotFoundError):
            target.unlink()
    parts = path / PARTS
    if parts.is_dir():
        for child in parts.iterdir():
            with contextlib.suppress(FileNotFoundError):
                child.unlink()
        with contextlib.suppress(OSError):
            parts.rmdir()
