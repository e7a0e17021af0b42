"""Files written whole or not at all: every output goes to a temporary name in its folder
and is renamed over the final name once complete (``os.replace`` is atomic on one file
system), so an interrupted or killed run never leaves a half-written file under a final
name. The temporary names start with ``.`` and hold ``.tmp`` before the final name's suffix
(so a library that reads the format from the suffix writes the right one); :func:`remove_stale`
clears those a killed run left behind.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

TMP_SUFFIX = ".tmp"


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path beside ``path``; renamed to ``path`` when the block ends without an
    exception, removed otherwise. Write to it with any library (``savefig``, ``torch.save``)."""
    path = Path(path)
    # named here: a failure further down would name the temporary file instead
    if not path.parent.is_dir():
        raise FileNotFoundError(f"no folder {path.parent} to write {path.name} into")
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a folder, not a file to write")
    tmp_path = None
    deferred = _DeferredCtrlC()
    try:
        fd, tmp = tempfile.mkstemp(
            prefix=f".{path.name}.", suffix=TMP_SUFFIX + path.suffix, dir=path.parent
        )
        os.close(fd)
        tmp_path = Path(tmp)
        deferred.deliver()  # a Ctrl-C from now on raises here, where the file is removed
        yield tmp_path
        os.chmod(tmp_path, 0o666 & ~_umask())  # as open() would create it, not mkstemp's 0600
        with open(tmp_path, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp_path, path)
    except BaseException:
        deferred.deliver()
        if tmp_path is not None:
            with contextlib.suppress(OSError):
                tmp_path.unlink()
        raise


class _DeferredCtrlC:
    """SIGINT and SIGTERM held back while a temporary file is created, so that a Ctrl-C
    cannot land between its creation and the handler that removes it; :meth:`deliver` puts
    the previous handlers back and hands a signal that arrived meanwhile to its own. Only
    the main thread can change handlers, and only a handler set from Python can be put
    back; otherwise nothing is held back."""

    def __init__(self) -> None:
        self.previous: dict[int, Any] = {}
        self.received: list[tuple[int, Any]] = []
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                if signal.getsignal(signum) is not None:
                    self.previous[signum] = signal.signal(signum, self._record)

    def _record(self, signum: int, frame: Any) -> None:
        self.received.append((signum, frame))

    def deliver(self) -> None:
        previous, self.previous = self.previous, {}
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        if self.received:
            signum, frame = self.received[0]
            handler = previous.get(signum)
            if callable(handler):
                handler(signum, frame)
            elif handler == signal.SIG_DFL:
                os.kill(os.getpid(), signum)


def _umask() -> int:
    """The process's umask, read without changing it where the system says it (Linux's
    ``/proc/self/status``; setting it to read it races with other threads creating files)."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def save_figure(fig: Any, path: str | Path, **options: Any) -> Path:
    """Save a matplotlib figure to ``path`` atomically (``savefig(**options)``, dpi 120 by
    default) and close it."""
    import matplotlib.pyplot as plt

    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, **{"dpi": 120, "format": Path(path).suffix[1:] or "png", **options})
    finally:
        plt.close(fig)
    return Path(path)


def write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return write_bytes(path, text.encode("utf-8"))


def write_json(path: str | Path, data: Any) -> Path:
    """Write ``data`` as strict JSON (no NaN or Infinity literals: ValueError) atomically."""
    return write_text(path, json.dumps(data, indent=2, allow_nan=False) + "\n")


def append_line(path: str | Path, line: str) -> None:
    """Append one line to ``path`` and flush it to disk (an append-only journal: a killed
    run can leave at most its last line incomplete, which :func:`read_lines` skips)."""
    if "\n" in line:
        raise ValueError("append_line takes a single line")
    with open(path, "a", encoding="utf-8") as f:
        f.write(line + "\n")
        f.flush()
        os.fsync(f.fileno())


def read_lines(path: str | Path) -> list[str]:
    """The complete lines of a journal written by :func:`append_line` (a last line without
    its newline, cut by a kill, is left out)."""
    path = Path(path)
    if not path.exists():
        return []
    text = path.read_text(encoding="utf-8")
    lines = text.split("\n")
    return [line for line in lines[:-1] if line]  # the part after the last newline is cut


def remove_stale(folder: str | Path) -> list[Path]:
    """Remove the temporary files of :func:`atomic_path` left in ``folder`` by a killed run."""
    removed = []
    for path in Path(folder).glob(".*"):
        if not is_temporary(path):
            continue
        with contextlib.suppress(OSError):
            path.unlink()
            removed.append(path)
    return removed


def is_temporary(path: str | Path) -> bool:
    """Whether ``path`` names a temporary file of :func:`atomic_path`."""
    # ".NAME." + mkstemp's 8 random characters + ".tmp" + NAME's suffix (none for a name
    # without one): a user's ".draft.tmp.md" is not one
    return (
        re.fullmatch(rf"\..+\.[a-z0-9_]{{8}}{re.escape(TMP_SUFFIX)}(\.[^.]+)?", Path(path).name)
        is not None
    )
