"""Where configurations run: ``local`` (one after the other in this process) or ``ray``
(one Ray task each, on a local Ray cluster started here or one joined at ``address``).

Both engines call the same function with the same arguments; the simulation is seeded, so
the numbers are the same. :func:`run_each` hands every result over as soon as it is done,
and a call that raises becomes a failed :class:`Outcome` carrying its error (the same text
on both engines) while the other calls go on.
"""

from __future__ import annotations

import signal
import socket
import threading
import traceback
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from tqdm.auto import tqdm

ENGINES = ("local", "ray")


def check_engine(engine: str) -> str:
    """``engine`` if it is one of :data:`ENGINES` (ValueError otherwise)."""
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
    return engine


@contextmanager
def ray_session(address: str | None = None, num_cpus: int | None = None) -> Iterator[Any]:
    """``ray`` connected to ``address`` (an existing cluster), or to a local cluster started
    here with ``num_cpus`` CPUs and shut down on exit. An already initialised Ray is used
    as it is."""
    try:
        import ray
    except ImportError as error:
        raise ImportError('engine="ray" needs Ray: pip install "torchcbf[ray]"') from error
    started = False
    if not ray.is_initialized():
        kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
        if address is not None:
            check_address(address)
            kwargs["address"] = address
        else:
            kwargs["num_cpus"] = num_cpus
        main = threading.current_thread() is threading.main_thread()
        sigterm = signal.getsignal(signal.SIGTERM) if main else None
        ray.init(**kwargs)
        # Ray installs a SIGTERM handler that exits (sys.exit); the caller's own (the
        # command line's: Ctrl-C's answer; or SIG_IGN) is put back, the default is not (it
        # would end the process without unwinding, leaving Ray's processes behind)
        if sigterm is not None and sigterm is not signal.SIG_DFL:
            signal.signal(signal.SIGTERM, sigterm)
        started = True
    try:
        yield ray
    finally:
        if started:
            ray.shutdown()


def check_address(address: str, *, timeout: float = 5.0) -> None:
    """Raise ``ValueError`` for an address Ray does not take (it takes ``"auto"``,
    ``"local"``, ``host:port`` and ``ray://host:port``), or where nothing answers at a
    ``host:port`` within ``timeout`` seconds: Ray itself retries such an address for
    minutes."""
    if address in ("auto", "local"):
        return
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not port.isdigit() or not host:
        raise ValueError(
            f"address must be 'auto', 'local', host:port or ray://host:port, got {address!r}"
        )
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except OSError as error:
        raise ValueError(
            f"no Ray cluster answers at {address} ({error.strerror or error}); start one with "
            "`ray start --head` or leave out the address to run a local one"
        ) from None


@dataclass(frozen=True)
class Outcome:
    """The result of one call: ``value`` when ``ok``, else ``error`` (``"Type: message"``)
    and the ``traceback`` text."""

    ok: bool
    value: Any = None
    error: str | None = None
    traceback: str | None = None


def guarded(fn: Callable[..., Any], kwargs: dict[str, Any]) -> Outcome:
    """``fn(**kwargs)`` as an :class:`Outcome`; an ``Exception`` becomes a failed one
    (``KeyboardInterrupt`` and ``SystemExit`` pass through)."""
    try:
        return Outcome(True, fn(**kwargs))
    except Exception as error:  # noqa: BLE001 - every failure of one call is recorded
        return Outcome(
            False, error=f"{type(error).__name__}: {error}", traceback=traceback.format_exc()
        )


def run_each(
    fn: Callable[..., Any],
    calls: Sequence[dict[str, Any]],
    on_result: Callable[[int, Outcome], None],
    *,
    engine: str = "local",
    address: str | None = None,
    num_cpus: int | None = None,
    progress: bool = True,
    desc: str = "sweep",
) -> None:
    """Call ``fn(**calls[i])`` for every ``i`` on ``engine`` and ``on_result(i, outcome)``
    in this process as each finishes (input order on the local engine, completion order on
    Ray). A call that raises, or whose Ray worker dies, is a failed outcome; the rest go on.
    """
    check_engine(engine)
    if engine == "local":
        for i, kw in enumerate(tqdm(calls, desc=desc, disable=not progress)):
            on_result(i, guarded(fn, kw))
        return
    if not calls:
        return
    with ray_session(address, num_cpus) as ray:
        remote = ray.remote(num_cpus=1)(guarded)
        refs = {remote.remote(fn, kw): i for i, kw in enumerate(calls)}
        with tqdm(total=len(refs), desc=f"{desc} (ray)", disable=not progress) as bar:
            pending = list(refs)
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                for ref in done:
                    try:
                        outcome = ray.get(ref)
                    except ray.exceptions.RayError as error:  # the task's worker died
                        outcome = Outcome(False, error=f"{type(error).__name__}: {error}")
                    on_result(refs[ref], outcome)
                    bar.update(1)


def run_all(
    fn: Callable[..., Any],
    calls: Sequence[dict[str, Any]],
    *,
    engine: str = "local",
    address: str | None = None,
    num_cpus: int | None = None,
    progress: bool = True,
    desc: str = "sweep",
) -> list[Any]:
    """``[fn(**kw) for kw in calls]`` on ``engine``, in input order, with a progress bar
    (RuntimeError naming the first failed call, after all have run)."""
    outcomes: dict[int, Outcome] = {}
    run_each(
        fn,
        calls,
        outcomes.__setitem__,
        engine=engine,
        address=address,
        num_cpus=num_cpus,
        progress=progress,
        desc=desc,
    )
    for i in range(len(calls)):
        if not outcomes[i].ok:
            raise RuntimeError(f"call {i} failed: {outcomes[i].error}")
    return [outcomes[i].value for i in range(len(calls))]
