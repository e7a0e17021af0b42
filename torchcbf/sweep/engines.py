"""Where configurations run: ``local`` (one after the other in this process) or ``ray``
(one Ray task each, on a local Ray cluster started here or one joined at ``address``).

Both engines call the same function with the same arguments and return the results in the
order of the inputs; the simulation is seeded, so the numbers are the same.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
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
            ray.init(address=address, **kwargs)
        else:
            ray.init(num_cpus=num_cpus, **kwargs)
        started = True
    try:
        yield ray
    finally:
        if started:
            ray.shutdown()


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
    """``[fn(**kw) for kw in calls]`` on ``engine``, in input order, with a progress bar."""
    check_engine(engine)
    if engine == "local":
        return [fn(**kw) for kw in tqdm(calls, desc=desc, disable=not progress)]
    with ray_session(address, num_cpus) as ray:
        remote = ray.remote(num_cpus=1)(fn)
        refs = [remote.remote(**kw) for kw in calls]
        with tqdm(total=len(refs), desc=f"{desc} (ray)", disable=not progress) as bar:
            pending = list(refs)
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                bar.update(len(done))
        return ray.get(refs)
