"""``torch.compile`` for the user code torchcbf evaluates (an MPPI cost), with a first call
short enough for a closed loop and an eager fallback where the backend fails.

Inductor's first CPU compile in a process normally builds and loads a test program for each
vector instruction set the CPU reports (AVX-512, AVX2, ...) and for each of its extensions
(AVX-512 BF16 and VNNI, AMX) before it generates any code: about 9-11 s of an 11-13 s first
call on a 2-core machine, each probe a C++ build plus a Python process that loads it. torch's
own kernels already run with the instruction sets the CPU and the operating system report
(``/proc/cpuinfo``), so during the first call of a compiled function (where it compiles)
inductor is told to trust that report: ``torch._inductor.config.cpp.vec_isa_ok = True`` for
the base sets and, for the extensions, whose probes that option does not cover, the probe
build (``VecISA.check_build``) answers yes for the duration of the call. Nothing is changed
where the user set ``vec_isa_ok`` (or ``TORCHINDUCTOR_VEC_ISA_OK``) themselves. The list is
computed once per process, so the first compile in the process decides it; later calls run
without the patch (it costs about 17 us, which a compiled step called once per horizon step
would pay 80 times). Where the C++ compiler cannot build for a reported extension, the
compile fails and the eager fallback below takes over.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import dis
import inspect
import logging
import operator
import types
from collections.abc import Callable, Iterator, Sequence
from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchcbf._checks import hook_dicts

logger = logging.getLogger("torchcbf")


class Compiled:
    """``fn`` under ``torch.compile(fn, **options)``; eager ``fn`` from the first call on
    whose compilation fails in the backend (a C++ compiler that cannot build the generated
    code, say), with a warning. Errors of ``fn`` itself are raised as they are.

    ``unbacked``: names of ``fn``'s integer arguments that take a new value on each call
    (a step index): traced as unbacked symbols, so one graph serves every value. torch
    otherwise traces the first value as a constant, and 0 and 1 always, before it makes
    the argument dynamic: two or three compiles on the first call of a loop over steps."""

    def __init__(
        self, fn: Callable[..., Any], options: dict[str, Any], *, unbacked: Sequence[str] = ()
    ) -> None:
        self.eager = fn
        self.options = dict(options)
        self.unbacked = tuple(unbacked)
        self.compiled: Callable[..., Any] | None = torch.compile(_own_code(fn), **options)
        self._first = True

    def __getstate__(self) -> dict[str, Any]:
        # the compiled function does not pickle: compile again where it is loaded
        return {"eager": self.eager, "options": self.options, "unbacked": self.unbacked}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["eager"], state["options"], unbacked=state.get("unbacked", ()))

    def __deepcopy__(self, memo: dict[int, Any]) -> Compiled:
        # compile the copy's function (a bound method: of the copied module)
        return Compiled(copy.deepcopy(self.eager, memo), self.options, unbacked=self.unbacked)

    def __call__(self, *args: Any) -> Any:
        if self.compiled is None:
            return self.eager(*args)
        from torch._dynamo.exc import BackendCompilerFailed
        from torch.fx.experimental.symbolic_shapes import GuardOnDataDependentSymNode

        try:
            with _trusting_isa(self._first), _unbacked_arguments(self.unbacked, self._first):
                out = self.compiled(*args)
        except GuardOnDataDependentSymNode:
            if not (self._first and self.unbacked):
                raise
            # the function reads an unbacked argument as a number (indexes a list with the
            # step): trace it as torch would, one value at a time
            self.unbacked = ()
            self.compiled = torch.compile(_own_code(self.eager), **self.options)
            return self(*args)
        except BackendCompilerFailed as err:
            logger.warning("torchcbf: torch.compile failed (%s); running eager", err)
            self.compiled = None
            return self.eager(*args)
        self._first = False
        return out


def _hook_state(dicts: list[dict[int, Any]]) -> tuple[Any, ...]:
    """What a call's hooks in ``dicts`` are, cheaply where there are none: their number and
    largest handle id (handle ids only grow, so a hook registered or removed changes them)
    and, where there are hooks, the hooks as :func:`_freeze` sees a function (itself, its
    closure's contents and the numbers and tensors among its globals), so a hook whose
    captured value changed is seen too."""
    count, top = 0, -1
    for d in dicts:
        if d:
            count += len(d)
            top = max(top, max(d))
    if not count:
        return count, top
    return count, top, tuple(_freeze(d) for d in dicts if d)


def hook_key(*objs: object) -> str:
    """The forward hooks that run when ``objs`` are called, as a string that changes when one
    is registered or removed: the handle ids of the forward and forward-pre hooks of every
    module of ``objs`` (none for an object that is not a module) and of the global module
    hooks. torch.compile does not guard on hooks, so a compiled function takes this as an
    argument and reads it (:func:`read_key`)."""
    modules = [m for obj in objs if isinstance(obj, torch.nn.Module) for m in obj.modules()]
    return ",".join(str(k) for d in hook_dicts(modules) for k in d)


def read_key(key: str) -> None:
    """Read ``key`` (an argument of a function under torch.compile), so that the compiled
    code is guarded on its value: torch.compile guards only on the arguments the code
    reads, and a new value of one it guards traces again. Nothing is done eagerly."""
    len(key)


def _own_code(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` (a function or bound method) with a code object of its own. torch.compile
    keeps its graphs, and its limit on their number, per code object: without a copy every
    instance of a class (each planner, say) shares one cache, so a graph traced for one
    instance is reused for another wherever its guards do not tell them apart (a module's
    forward hooks, which torch.compile does not guard on), and a process with several
    instances soon exceeds the limit and runs eager."""
    bound = isinstance(fn, types.MethodType)
    func = fn.__func__ if bound else fn
    if not isinstance(func, types.FunctionType):
        return fn
    own = types.FunctionType(
        func.__code__.replace(), func.__globals__, func.__name__, func.__defaults__,
        func.__closure__,
    )  # fmt: skip
    own.__kwdefaults__ = func.__kwdefaults__
    own.__qualname__ = func.__qualname__
    return types.MethodType(own, fn.__self__) if bound else own


@contextlib.contextmanager
def _unbacked_arguments(names: tuple[str, ...], first: bool) -> Iterator[None]:
    """torch.compile told to trace the arguments ``names`` as unbacked symbols (beside any
    the user names in ``TORCH_COMPILE_UNBACKED_SOURCES``) during a first call, where this
    torch has the option. Later calls reuse that graph without the option (setting it
    costs about 5 us a call, ``config.patch`` 250 us)."""
    from torch.compiler import config

    if not (first and names and hasattr(config, "unbacked_sources")):
        yield
        return
    before = config.unbacked_sources
    config.unbacked_sources = ",".join([before] * bool(before) + [f"L['{n}']" for n in names])
    try:
        yield
    finally:
        config.unbacked_sources = before


def _trusting_isa(first: bool) -> contextlib.AbstractContextManager[None]:
    """:func:`_trust_reported_isa` around a first compile (the ISA list is computed once per
    process, on the first CPU compile) where the user has not set the option; else
    nothing."""
    from torch._inductor import config

    if first and config.cpp.vec_isa_ok is None:
        return _trust_reported_isa()
    return contextlib.nullcontext()


@contextlib.contextmanager
def _trust_reported_isa() -> Iterator[None]:
    """Inductor's instruction-set probes answered by the CPU's own report (module docstring)."""
    from torch._inductor import config, cpu_vec_isa

    probe = getattr(cpu_vec_isa.VecISA, "check_build", None)
    with config.patch({"cpp.vec_isa_ok": True}):
        if probe is None:
            yield
            return
        cpu_vec_isa.VecISA.check_build = lambda self, code: True  # type: ignore[method-assign]
        try:
            yield
        finally:
            cpu_vec_isa.VecISA.check_build = probe  # type: ignore[method-assign]


#: entries of an ``nn.Module``'s ``__dict__`` that are its own bookkeeping, not user state
#: (its forward hooks are keyed apart: :func:`hook_dicts`)
_MODULE_INTERNALS = (frozenset(vars(torch.nn.Module())) - {"training"}) | {
    "_exact_constants"  # torchcbf._constants' float64 copies, which no forward reads
}
#: values a traced graph bakes in as constants and that key its cache by value
_PRIMITIVES = (bool, int, float, complex, str, type(None))
#: values keyed by their contents, compared again on every call (they change in place)
_MUTABLE = (list, dict, set, bytearray, types.FunctionType)


class _Record(NamedTuple):
    """What a :class:`Traced` call checks against the last call's key, and its graph."""

    objects: tuple[Any, ...]  # the modules' state values, by identity
    containers: list[tuple[int, Any]]  # (position, frozen contents) of mutable values
    # (position, shape, strides, dtype) of the arguments and the state tensors the graph reads
    tensors: list[tuple[int, torch.Size, tuple[int, ...], torch.dtype]]
    device: torch.device  # of the first argument
    graph: Callable[..., Any]
    used: list[int]  # positions in (*args, *state) of the tensors the graph reads
    n_args: int
    hooks: tuple[Any, ...]  # the modules' hooks (:func:`_hook_state`)


class TraceError(RuntimeError):
    """A function :class:`Traced` could not trace or compile (the cause is chained)."""


class _Ref:
    """An object in a cache key by identity, held so that its id is not reused."""

    __slots__ = ("obj",)

    def __init__(self, obj: object) -> None:
        self.obj = obj

    def __hash__(self) -> int:
        return id(self.obj)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _Ref) and other.obj is self.obj


def _freeze(value: Any) -> Any:
    """A hashable stand-in of ``value`` for a cache key: numbers and strings by type and
    value (``-0.0`` is not ``0.0``, ``True`` is not ``1``), tensors by shape, strides, dtype
    and device, containers by their contents, a function by itself, its closure's contents
    and the numbers and tensors among the globals it names, anything else by identity."""
    if isinstance(value, Tensor):
        return (value.shape, value.stride(), value.dtype, value.device)
    if isinstance(value, float):
        return (float, value.hex())
    if isinstance(value, complex):
        return (complex, value.real.hex(), value.imag.hex())
    if isinstance(value, _PRIMITIVES):
        return (type(value), value)
    if isinstance(value, (list, tuple)):
        return (type(value), tuple(_freeze(v) for v in value))
    if isinstance(value, dict):
        return (dict, tuple((k, _freeze(v)) for k, v in value.items()))
    if isinstance(value, (set, frozenset)):
        return (type(value), frozenset(_freeze(v) for v in value))
    if isinstance(value, bytearray):
        return bytes(value)
    if isinstance(value, types.FunctionType):
        cells = tuple(_shallow(c.cell_contents) for c in value.__closure__ or ())
        named = value.__globals__
        found = tuple((n, _shallow(named[n])) for n in value.__code__.co_names if n in named)
        return (_Ref(value), cells, found)
    return _Ref(value)


def _shallow(value: Any) -> Any:
    """A function's captured value in its key: numbers, strings and tensors as
    :func:`_freeze` has them, anything else by identity (not followed further)."""
    if isinstance(value, (Tensor, *_PRIMITIVES)):
        return _freeze(value)
    return _Ref(value)


def _is_record(value: object) -> bool:
    """Whether ``value`` is a plain record whose fields a trace may read as numbers: a
    ``SimpleNamespace`` or a dataclass instance."""
    return isinstance(value, types.SimpleNamespace) or (
        dataclasses.is_dataclass(value) and not isinstance(value, type)
    )


class _Fields:
    """The fields of a record without a ``__dict__`` (a dataclass with ``slots``) as the
    mapping :meth:`Traced._find_state` keeps its places in."""

    def __init__(self, record: object) -> None:
        self.record = record

    def keys(self) -> list[str]:
        return [f.name for f in dataclasses.fields(self.record)]  # type: ignore[arg-type]

    def get(self, key: str) -> Any:
        return getattr(self.record, key, None)

    def __getitem__(self, key: str) -> Any:
        return getattr(self.record, key)

    def __setitem__(self, key: str, value: Any) -> None:
        setattr(self.record, key, value)


def _record_fields(record: object) -> Any:
    """The places of a record's fields: its ``__dict__``, else :class:`_Fields`."""
    return vars(record) if hasattr(record, "__dict__") else _Fields(record)


def _class_globals(cls: type) -> list[tuple[dict[str, Any], str]]:
    """``(globals, name)`` of the plain values (numbers, strings) that the methods of a
    user's module class read as globals and never assign (``SCALE * h`` in a ``forward``;
    a counter the method increments would key every call anew); torch's and torchcbf's own
    classes read none that changes."""
    found: list[tuple[dict[str, Any], str]] = []
    for klass in cls.__mro__:
        if (getattr(klass, "__module__", None) or "").split(".")[0] in _LIBRARY_MODULES:
            continue
        for attr in vars(klass).values():
            if isinstance(attr, (staticmethod, classmethod)):
                attr = attr.__func__
            elif isinstance(attr, property):
                attr = attr.fget
            attr = inspect.unwrap(attr) if callable(attr) else attr
            if not isinstance(attr, types.FunctionType):
                continue
            named = attr.__globals__
            read, written = _global_names(attr.__code__)
            found.extend(
                (named, name)
                for name in sorted(read - written)
                if name in named and isinstance(named[name], _PRIMITIVES)
            )
    return found


def _class_values(cls: type) -> list[tuple[Any, str]]:
    """``(class dict, name)`` of the plain values (numbers, strings) that a user's module
    class and its user bases hold as class attributes (``MARGIN = 0.1`` read as
    ``self.MARGIN``; ``Disc.MARGIN = 0.2`` later is seen)."""
    return [
        (vars(klass), name)
        for klass in cls.__mro__
        if (getattr(klass, "__module__", None) or "").split(".")[0] not in _LIBRARY_MODULES
        for name, value in vars(klass).items()
        if not name.startswith("__") and isinstance(value, _PRIMITIVES)
    ]


#: top-level modules whose classes' methods read no global that changes
_LIBRARY_MODULES = frozenset({"torch", "torchcbf", "builtins", ""})


def _global_names(code: types.CodeType) -> tuple[set[str], set[str]]:
    """The global names that ``code`` and the functions nested in it (lambdas,
    comprehensions) read, and those they assign."""
    read, written = set(code.co_names), set()
    for ins in dis.get_instructions(code):
        if ins.opname in ("STORE_GLOBAL", "DELETE_GLOBAL"):
            written.add(ins.argval)
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            r, w = _global_names(const)
            read |= r
            written |= w
    return read, written


class Traced:
    """``fn(*args)`` of tensors, compiled per input signature with low call overhead.

    ``fn`` is traced once per signature (shapes, dtypes and devices of ``args``) into one
    graph of ATen operations (``make_fx``, so ``torch.func`` transforms such as ``vmap`` and
    ``jacrev`` are resolved at trace time), with every tensor of ``modules`` (parameters,
    buffers and plain tensor attributes, submodules included) lifted to an input; inductor
    compiles the graph (with a C++ wrapper on the CPU; ``options``: inductor settings). A
    call then costs a look at the modules' state (the same objects as the last call's: the
    same code) and the compiled code, without ``torch.compile``'s frame evaluation and
    guards (tens of microseconds on one state).

    The key of the cache holds what the graph bakes in: the modules' attributes that are
    plain numbers or strings (a new value traces again; ``module.temp = 0.2`` is seen), the
    contents of lists, tuples, dicts and sets among them (compared on every call, so one
    mutated in place is seen), the fields of a ``SimpleNamespace`` or dataclass among them
    (``module.cfg.gain = 2.0`` is seen; a tensor field is lifted like an attribute), the
    numbers and strings that the methods of a user's module class read as globals (not
    those they assign: a call counter does not trace again) and that the class holds as
    class attributes (``Disc.MARGIN = 0.2`` is seen), the names of the places of the state
    (a buffer registered again in another order), the identity of every other
    attribute and submodule (a replaced function or network traces again), and the shape,
    dtype and device of every lifted tensor (``.data =`` with a new shape or dtype is seen).
    New tensor values, in place or by ``.to()``, reuse the code. A tensor that ``fn``
    reaches other than through ``modules`` (a closure's) makes the trace fail.

    Where tracing or compiling fails (data-dependent control flow, an operation without a
    decomposition), :meth:`__call__` raises :class:`TraceError`; the caller decides the
    fallback. ``ignore``: names of the modules' own attributes that are bookkeeping, which
    ``fn`` reads as fixed objects or not at all (the owner's caches). The forward hooks of
    the modules and the global ones are part of the key (one registered or removed traces
    again). Not seen: attributes added after the first call (a forward that reads one with
    ``getattr(self, name, default)``), values captured deeper than a function's own closure,
    globals read by the helper functions a method calls, and the attributes of objects other
    than modules and records. The first call of each signature swaps the modules'
    tensors for tracing placeholders: do not call the modules from another thread meanwhile.
    Outputs are a tuple of tensors (of one where ``fn`` returns a tensor), computed without
    a graph (call it under ``torch.no_grad()``).
    """

    def __init__(
        self,
        fn: Callable[..., Any],
        modules: Sequence[torch.nn.Module],
        *,
        options: dict[str, Any] | None = None,
        ignore: Sequence[str] = (),
    ) -> None:
        self.fn = fn
        self.modules = list(modules)
        self.ignore = frozenset(ignore)
        self.options = dict(options or {})
        self._graphs: dict[tuple[Any, ...], tuple[Callable[..., Any], list[int]]] = {}
        self._slots: list[tuple[Any, str]] | None = None
        self._hooks: list[dict[int, Any]] = []
        self._last: _Record | None = None
        self.lookups = 0  # calls that found the modules' state changed
        self._compiled_on: set[str] = set()

    def __getstate__(self) -> dict[str, Any]:
        return {
            "fn": self.fn,
            "modules": self.modules,
            "options": self.options,
            "ignore": self.ignore,
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(
            state["fn"], state["modules"], options=state["options"], ignore=state["ignore"]
        )

    def __deepcopy__(self, memo: dict[int, Any]) -> Traced:
        fn, modules = copy.deepcopy((self.fn, self.modules), memo)
        return Traced(fn, modules, options=self.options, ignore=self.ignore)

    @property
    def compiles(self) -> int:
        """How many graphs were compiled (one per signature met)."""
        return len(self._graphs)

    def _find_state(self) -> tuple[list[tuple[Any, str]], list[dict[int, Any]]]:
        """Every place of the modules' state a trace can read, ``(mapping, key)`` pairs (a
        ``__dict__``, a parameter or buffer dict, a module's globals, :class:`_Fields`), and
        the dicts of the hooks a call runs (:func:`hook_dicts`)."""
        slots: list[tuple[Any, str]] = []
        found: list[torch.nn.Module] = []
        seen: set[int] = set()
        classes: list[type] = []
        skip = _MODULE_INTERNALS | self.ignore
        stack = list(self.modules)
        while stack:
            mod = stack.pop()
            if id(mod) in seen:
                continue
            seen.add(id(mod))
            found.append(mod)
            for store in (mod._parameters, mod._buffers, mod._modules):
                slots.extend((store, k) for k in store)
            own = mod.__dict__
            slots.extend((own, k) for k in own if k not in skip)
            # a plain record's fields (``self.cfg = SimpleNamespace(gain=1.0)``)
            for k in own:
                if k not in skip and _is_record(own[k]):
                    fields = _record_fields(own[k])
                    slots.extend((fields, name) for name in fields.keys())
            if not any(c is type(mod) for c in classes):  # each class once
                classes.append(type(mod))
                slots.extend(_class_globals(type(mod)))
                slots.extend(_class_values(type(mod)))
            stack.extend(m for m in mod._modules.values() if m is not None)
        return slots, hook_dicts(found)

    def __call__(self, *args: Tensor) -> tuple[Tensor, ...]:
        state = [] if self._slots is None else [store.get(k) for store, k in self._slots]
        values = (*args, *state)
        last = self._last
        if last is None or last.hooks != _hook_state(self._hooks) or not self._same(values, last):
            # something changed: find the state again (a new submodule has its own)
            self._slots, self._hooks = self._find_state()
            values = (*args, *[store.get(k) for store, k in self._slots])
            last = self._lookup(values, len(args))
        return last.graph(*[values[i] for i in last.used])

    @staticmethod
    def _same(values: tuple[Any, ...], last: _Record) -> bool:
        """Whether ``values`` (arguments, then the modules' state) have the last call's key:
        the same state objects, the same contents of mutable containers, and the same
        shape, strides and dtype of the arguments and of every state tensor the graph reads
        (``.data =`` keeps the object but may change all three), on the same device."""
        n_args = last.n_args
        return (
            len(values) == len(last.objects) + n_args
            and all(map(operator.is_, values[n_args:], last.objects))
            and all(
                values[i].shape == shape and values[i].stride() == st and values[i].dtype is dt
                for i, shape, st, dt in last.tensors
            )
            and values[0].device == last.device
            and all(_freeze(values[i]) == frozen for i, frozen in last.containers)
        )

    def _lookup(self, values: tuple[Any, ...], n_args: int) -> _Record:
        """The record of a call with ``values`` (arguments, then the modules' state), its
        graph compiled where its key is new."""
        self.lookups += 1
        # the names of the state's places too: tensors of equal shapes in another order
        # (a buffer registered again) would otherwise find a graph that reads them swapped
        names = tuple(k for _, k in self._slots or ())
        key = (*(_freeze(v) for v in values), *(_freeze(d) for d in self._hooks), names)
        found = self._graphs.get(key)
        if found is None:
            try:
                found = self._compile(values[:n_args], list(values[n_args:]))
            except Exception as err:  # noqa: BLE001 - any failure of make_fx or inductor
                raise TraceError(f"{type(err).__name__}: {err}") from err
            self._graphs[key] = found
        graph, used = found
        self._last = _Record(
            objects=values[n_args:],
            containers=[(i, key[i]) for i, v in enumerate(values) if isinstance(v, _MUTABLE)],
            tensors=[
                (i, values[i].shape, values[i].stride(), values[i].dtype)
                for i in (*range(n_args), *(j for j in used if j >= n_args))
            ],
            device=values[0].device,
            graph=graph,
            used=used,
            n_args=n_args,
            hooks=_hook_state(self._hooks),
        )
        return self._last

    def _compile(
        self, args: tuple[Tensor, ...], state: list[Any]
    ) -> tuple[Callable[..., Any], list[int]]:
        from torch._inductor.compile_fx import compile_fx
        from torch.fx.experimental.proxy_tensor import make_fx

        assert self._slots is not None
        n_args = len(args)
        positions = list(range(n_args)) + [
            n_args + i for i, v in enumerate(state) if isinstance(v, Tensor)
        ]
        lifted = [self._slots[i - n_args] for i in positions[n_args:]]

        def flat(*inputs: Tensor) -> tuple[Tensor, ...]:
            saved = [store[k] for store, k in lifted]
            try:
                for (store, k), value in zip(lifted, inputs[n_args:], strict=True):
                    store[k] = value
                out = self.fn(*inputs[:n_args])
                return (out,) if isinstance(out, Tensor) else tuple(out)
            finally:
                for (store, k), value in zip(lifted, saved, strict=True):
                    store[k] = value

        values = (*args, *state)
        inputs = [values[i].detach() for i in positions]
        with torch.no_grad():
            graph = make_fx(flat, tracing_mode="fake")(*inputs)
            # only the tensors the graph reads are passed to it
            placeholders = [n for n in graph.graph.nodes if n.op == "placeholder"]
            used = []
            for position, node in zip(positions, placeholders, strict=True):
                if node.users:
                    used.append(position)
                else:
                    graph.graph.erase_node(node)
            graph.recompile()
            inputs = [values[i].detach() for i in used]
            device = values[0].device.type
            # the C++ wrapper cuts the call overhead on the CPU; on an accelerator the
            # kernels' launch dominates and the Python wrapper builds without a toolkit
            patch = {"cpp_wrapper": device == "cpu", **self.options}
            with _trusting_isa(device == "cpu" and "cpu" not in self._compiled_on):
                compiled = compile_fx(graph, inputs, config_patches=patch)
        self._compiled_on.add(device)
        return compiled, used
