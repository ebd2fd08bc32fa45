"""The `Node` base: typed ports, a pydantic `Params` model, a version, an execution kind.

A node is written as a class::

    class ScaleMesh(Node):
        '''Scale every vertex about the origin.'''
        type_name = "example.ScaleMesh"
        version = 1
        kind = FRAMEWISE

        class Params(NodeParams):
            factor: float = Param(1.0, gt=0, description="Scale factor (unitless).")

        mesh = In(MeshSequence, doc="Mesh to scale.")
        scaled = Out(MeshSequence)

        def run(self, mesh: MeshSequence) -> dict:
            return {"scaled": dataclasses.replace(mesh, vertices=mesh.vertices * self.params.factor)}

`run` receives only its input values (None for an unconnected optional input) and reads
`self.params`; `self.frames` is the absolute frame range of the values it received
(for windowed nodes: the chunk plus its halo) and `self.full_frames` the range of the whole
run. It returns a dict keyed by output port. Caching, chunking and devices belong to the
runner. Bad input data is reported by raising `InputError(port, message)`.

The parameter model (`NodeParams`, `Param`, strict numbers) lives in `nodegraph.params`; this
module declares ports and node types and runs a node on values (`execute`, `run_node`).
"""

from __future__ import annotations

import hashlib
import inspect
import json
import traceback
import weakref
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, ClassVar, Iterable, Iterator, Mapping

from pydantic import ValidationError

from .errors import InputError, NodeError
from .params import NodeParams, field_flag, format_validation_error
from .ports import PortType

__all__ = ["Kind", "FRAMEWISE", "SEQUENCE", "windowed", "In", "Out", "Node", "run_node", "execute", "wrap_error",
           "task_seed"]

@dataclass(frozen=True)
class Kind:
    """How a node may be split over frames.

    Attributes:
        name: "framewise" (any chunk alone), "windowed" (a chunk plus `halo` frames each
            side) or "sequence" (all frames at once).
        halo: frames of context each side, for "windowed".
    """

    name: str
    halo: int = 0

    def __str__(self) -> str:
        return f"windowed(halo={self.halo})" if self.name == "windowed" else self.name


FRAMEWISE = Kind("framewise")
SEQUENCE = Kind("sequence")


def windowed(halo: int) -> Kind:
    """Return the windowed kind with `halo` frames of context on each side of a chunk."""
    if halo < 0:
        raise ValueError(f"windowed: halo must be >= 0, found {halo}")
    return Kind("windowed", int(halo))


class In:
    """Declares an input port.

    Args:
        type: the port type class.
        optional: the input may be left unconnected (the node then receives None, or [] for
            a `many` port).
        per_frame: for per-frame types, False means the port takes the whole value unchunked
            (e.g. a one-frame rest mesh); None follows the type.
        many: a list port: it takes any number of connections (several edges to the one
            port in JSON) and the node receives a list of values in the order of the edges.
        doc: one line for `nodegraph nodes`.
    """

    def __init__(self, type: type[PortType], *, optional: bool = False,
                 per_frame: bool | None = None, many: bool = False, doc: str = ""):
        self.type = type
        self.optional = optional
        self.per_frame = type.per_frame if per_frame is None else (per_frame and type.per_frame)
        self.many = many
        self.doc = doc
        self.name = ""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name


class Out(In):
    """Declares an output port (same arguments as `In`, without `optional` and `many`)."""

    def __init__(self, type: type[PortType], *, per_frame: bool | None = None, doc: str = ""):
        super().__init__(type, per_frame=per_frame, doc=doc)


class Node:
    """Base class of every node type (see the module docstring)."""

    type_name: ClassVar[str] = ""
    version: ClassVar[int] = 1
    kind: ClassVar[Kind] = FRAMEWISE
    cacheable: ClassVar[bool] = True
    uses_run_log: ClassVar[bool] = False
    writes_files: ClassVar[bool] = False
    resources: ClassVar[dict[str, float]] = {}
    preload: ClassVar[tuple[str, ...]] = ()
    torch_threads: ClassVar[int | None] = None
    """Torch intra-op threads of this node's `run` on the CPU (None: the process's). A float
    reduction split over threads rounds differently for each thread count; 1 makes the answer the
    same on every machine's thread count for a node that amplifies rounding (an iterative fit).
    Parallelism then comes from running chunks of frames side by side."""
    port_renames: ClassVar[dict[int, dict[str, str]]] = {}
    Params: ClassVar[type[NodeParams]] = NodeParams
    inputs: ClassVar[dict[str, In]] = {}
    outputs: ClassVar[dict[str, Out]] = {}
    cache_root: str | None = None  # the run's cache folder, set by the runner (None: no cache)
    skips_unread_outputs: ClassVar[bool] = False
    """True: `run` may leave out of its dict the outputs no edge of the graph reads (it asks
    `self.wants(port)`), e.g. a stabilized mesh beside the motion that is all a graph uses. The
    runner then keys the task's cache entry by the outputs it computed too, so a graph that
    reads another output recomputes instead of finding the entry without it."""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        ins: dict[str, In] = {}
        outs: dict[str, Out] = {}
        for klass in reversed(cls.__mro__):
            for name, value in vars(klass).items():
                if isinstance(value, Out):
                    outs[name] = value
                elif isinstance(value, In):
                    ins[name] = value
        reserved = sorted((set(ins) | set(outs)) & _RESERVED)
        if reserved:
            raise TypeError(f"node class {cls.__module__}.{cls.__qualname__}: port name(s) {reserved} shadow "
                            f"attributes of Node; rename the port(s)")
        for name, port in outs.items():
            if port.many:
                raise TypeError(f"node class {cls.__qualname__}: output '{name}' cannot be many=True")
        cls.inputs, cls.outputs = ins, outs
        if cls.__dict__.get("type_name"):
            from . import registry

            registry.register(cls)

    def __init__(self, params: NodeParams | Mapping[str, Any] | None = None, *,
                 node_id: str = "", **kwargs: Any):
        self.node_id = node_id or self.type_name or type(self).__name__
        if isinstance(params, NodeParams):
            if kwargs:
                params = params.model_copy(update=kwargs)
        else:
            values = {**dict(params or {}), **kwargs}
            try:
                params = self.Params(**values)
            except ValidationError as err:
                problems = "; ".join(f"'{k}': {m}" for k, m in format_validation_error(err))
                raise NodeError(self.node_id, self.type_name, f"invalid parameters: {problems}",
                                bad_input=True) from err
        self.params = params
        self.frames: range = range(0)
        self.full_frames: range = range(0)
        self.seed: int = 0
        self._device = "cpu"
        self._progress: Callable[[float, str], None] | None = None
        self.wanted_outputs: frozenset[str] = frozenset(self.outputs)
        """The outputs this run must return (all but those no edge reads, for a node that
        `skips_unread_outputs`); set by `execute`."""
        self.run_log: list[dict[str, Any]] = []
        """With `uses_run_log`: one record per task upstream of this one in the current run
        (name, node, frames, status: executed / cached / restored / ..., seconds), for run
        reports. Such a node's output depends on the run, not only on its inputs: it should
        not be `cacheable`."""

    @property
    def device(self) -> str:
        """The torch device to compute on: "cpu" or "cuda" (chosen by the runner's `--device`:
        "auto" means CUDA when torch sees a GPU). Only nodes that use torch should read it."""
        if self._device == "auto":
            import torch

            self._device = "cuda" if torch.cuda.is_available() else "cpu"
        return self._device

    def import_first(self) -> tuple[str, ...]:
        """Modules `run` will import that must be imported before the run's tasks start, on the
        runner's own thread (sync and threads schedulers). For C extensions whose library
        initialisers wait for the GIL inside the dynamic loader (usd-core's `pxr`): imported
        from a task thread while another task thread holds the GIL and asks the loader (numpy's
        temporary elision calls `dladdr`), the two wait on each other forever
        (`video_to_animation.json` hung once so, its USD and glTF writers side by side)."""
        return ()

    def wants(self, port: str) -> bool:
        """Whether this run must return output `port` (see `skips_unread_outputs`)."""
        return port in self.wanted_outputs

    # -- hooks a node type may override -----------------------------------------------
    def run(self, **inputs: Any) -> Mapping[str, PortType]:
        """Compute the outputs from the inputs (see the module docstring)."""
        raise NotImplementedError(f"{type(self).__name__}.run")

    def run_delegate(self, delegate: "Node", **inputs: Any) -> Mapping[str, PortType]:
        """Run `delegate`, a node of another type that this node adapts (`landmarks.LoadFrames`
        over `io.LoadImageSequence` and `io.LoadVideo`), inside this node's task: it sees this
        task's frames, seed, device and progress, and what it raises is reported as this node's.
        Call it from `run`."""
        delegate.frames, delegate.full_frames, delegate.seed = self.frames, self.full_frames, self.seed
        delegate._device, delegate._progress = self._device, self._progress
        return delegate.run(**inputs)

    @classmethod
    def migrate(cls, from_version: int, params: dict[str, Any]) -> dict[str, Any]:
        """Return `params` written for `from_version` rewritten for `cls.version`.

        The default accepts old versions whose parameters are still valid unchanged.
        Override to rename or convert parameters; raise ValueError when impossible.
        """
        return dict(params)

    @classmethod
    def migrate_port(cls, from_version: int, port: str) -> str:
        """The current name of a port that graph files written for `from_version` call `port`.

        Default: follows `port_renames` ({version: {old name: new name}}: the renames made
        when leaving that version), version by version.
        """
        for version in range(from_version, cls.version):
            port = cls.port_renames.get(version, {}).get(port, port)
        return port

    def frame_count(self) -> int | None:
        """For source nodes (no per-frame inputs): how many frames they can produce, or None."""
        return None

    def input_files(self, frames: range | None = None) -> list[Path]:
        """Files this node reads (their contents enter the cache key).

        Args:
            frames: absolute frames of the chunk being keyed; a framewise source reading one
                file per frame returns only the files of these frames, so that editing one
                frame's file recomputes only its chunk. None: all files.

        Default: the values of parameters declared with `input_file=True` that exist.
        """
        files = []
        for name in self.Params.model_fields:
            if field_flag(self.Params, name, "input_file", False):
                value = getattr(self.params, name)
                if value and Path(str(value)).is_file():
                    files.append(Path(str(value)))
        return files

    # -- helpers for run() -------------------------------------------------------------
    def progress(self, fraction: float, message: str = "") -> None:
        """Report progress within a long `run` (0..1); shown by the runner."""
        if self._progress is not None:
            self._progress(float(fraction), message)

    # -- introspection -------------------------------------------------------------------
    @classmethod
    def code_sources(cls) -> dict[str, str]:
        """{relative path: sha256} of the node's module and every project module it imports,
        transitively (found statically, see `nodegraph.codehash`)."""
        from .codehash import module_sources

        sources = module_sources(cls.__module__)
        if not sources:  # no file (e.g. defined interactively): the class's own source
            try:
                text = inspect.getsource(cls)
            except (OSError, TypeError):
                text = f"{cls.__module__}.{cls.__qualname__}"
            sources = {f"<{cls.__module__}.{cls.__qualname__}>": hashlib.sha256(text.encode()).hexdigest()}
        return sources

    @classmethod
    def code_hash(cls) -> str:
        """sha256 over `code_sources()` (part of the cache key); computed once per process."""
        cached = cls.__dict__.get("_code_hash")
        if cached:
            return cached
        from .codehash import source_digest

        digest = source_digest(cls.code_sources())
        cls._code_hash = digest
        return digest

    def key_params(self) -> dict[str, Any]:
        """Parameters that enter the cache key, as JSON-able values (input paths removed)."""
        data = self.params.model_dump(mode="json")
        out = {}
        for name, value in data.items():
            if not field_flag(self.Params, name, "affects_output", True):
                continue
            if field_flag(self.Params, name, "input_file", False):
                continue
            out[name] = value
        return out

    def __repr__(self) -> str:
        return f"{type(self).__name__}(node_id={self.node_id!r}, params={self.params!r})"


_RESERVED = frozenset(name for name in dir(Node) if not name.startswith("__")) | {
    "node_id", "params", "frames", "full_frames", "seed", "device"}


def task_seed(key: str) -> int:
    """A 63-bit seed derived from a task's cache key: the same in every process and machine."""
    return int(hashlib.sha256(f"seed:{key}".encode()).hexdigest()[:16], 16) >> 1


def _where(node: Node, chunk: range) -> tuple[int, int] | None:
    return (chunk.start, chunk.stop) if node.kind != SEQUENCE else None


_VALIDATED: "weakref.WeakSet[PortType]" = weakref.WeakSet()
"""Node outputs that passed `validate` in this process (by identity, dropped when the value
dies): a value a task produced and checked is not checked again as the input of each of its
readers (a whole-head capture: one pass over 210 MB per reader). Values built elsewhere, and
joined or sliced chunks (new objects), are checked as inputs as before."""


def _check_value(node: Node, port: In, value: Any, expected_frames: int | None, direction: str,
                 chunk: range) -> None:
    if not isinstance(value, port.type):
        raise NodeError(node.node_id, node.type_name,
                        f"{direction} expected {port.type.type_name}, found {type(value).__name__}",
                        port=port.name, frames=_where(node, chunk), bad_input=direction == "input")
    try:
        known = direction == "input" and value in _VALIDATED
    except TypeError:  # a port type that is not hashable (a dataclass with eq): always checked
        known = False
    if not known:
        try:
            value.validate(f"{port.type.type_name}")
        except ValueError as err:
            raise NodeError(node.node_id, node.type_name, f"{direction} {err}", port=port.name,
                            frames=_where(node, chunk), bad_input=direction == "input") from err
        if direction == "output":
            try:
                _VALIDATED.add(value)
            except TypeError:
                pass
    if port.per_frame and expected_frames is not None and value.num_frames != expected_frames:
        raise NodeError(node.node_id, node.type_name,
                        f"{direction} expected {expected_frames} frames, found {value.num_frames}",
                        port=port.name, frames=_where(node, chunk), bad_input=direction == "input")


def wrap_error(node: Node, err: Exception, frames: tuple[int, int] | None = None,
               bad_input: bool = False) -> NodeError:
    """Turn any exception raised by a node's code into a NodeError naming the node.

    `InputError` keeps its port and counts as bad input; other exceptions count as bad input
    only when `bad_input` is set (e.g. while planning, before anything runs).
    """
    if isinstance(err, NodeError):
        return err
    if isinstance(err, InputError):
        return NodeError(node.node_id, node.type_name, err.message, port=err.port, frames=frames,
                         bad_input=True)
    return NodeError(node.node_id, node.type_name, f"{type(err).__name__}: {err}", frames=frames,
                     bad_input=bad_input)


@contextmanager
def intra_op_threads(threads: int | None) -> Iterator[None]:
    """Run torch's CPU ops on `threads` intra-op threads inside the block (None: unchanged).

    With torch's OpenMP backend the count belongs to the calling thread (OpenMP's and MKL's
    per-thread settings), so a dask worker thread setting it does not change its neighbours';
    it is restored on exit.
    """
    if threads is None:
        yield
        return
    import torch

    before = torch.get_num_threads()
    if before != threads:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        if before != threads:
            torch.set_num_threads(before)


def execute(node: Node, inputs: Mapping[str, Any], frames: range, full_frames: range,
            progress: Callable[[float, str], None] | None = None, *, seed: int | None = None,
            device: str = "cpu", wanted: Iterable[str] | None = None) -> dict[str, PortType]:
    """Run `node` on values covering `frames`, checking inputs and outputs.

    Args:
        node: the node instance.
        inputs: port name -> value (per-frame values cover exactly `frames`).
        frames: absolute frame range of the per-frame inputs and outputs.
        full_frames: the range of the whole run.
        progress: optional callback (fraction, message).
        seed: the node's `self.seed` (the runner derives it from the task's key); None: from
            the node's type and key parameters.
        device: "cpu", "cuda" or "auto", the node's `self.device`.
        wanted: the outputs the run must return (None: all); the others may be left out only
            by a node that `skips_unread_outputs`.
    Returns:
        port name -> value.
    Raises:
        NodeError: naming node, port and frames; `bad_input` tells input problems (exit 2)
            from crashes (exit 1). The original exception is the `__cause__`.
    """
    count = len(frames)
    for name, port in node.inputs.items():
        value = inputs.get(name)
        if port.many:
            value = [] if value is None else value
            if not isinstance(value, (list, tuple)):
                raise NodeError(node.node_id, node.type_name, f"input expected a list of {port.type.type_name}, "
                                f"found {type(value).__name__}", port=name, frames=_where(node, frames),
                                bad_input=True)
            if not value and not port.optional:
                raise NodeError(node.node_id, node.type_name, "required input is missing (no connection)",
                                port=name, frames=_where(node, frames), bad_input=True)
            for item in value:
                _check_value(node, port, item, count, "input", frames)
            continue
        if value is None:
            if not port.optional:
                raise NodeError(node.node_id, node.type_name, "required input is missing",
                                port=name, frames=_where(node, frames), bad_input=True)
            continue
        _check_value(node, port, value, count, "input", frames)
    unknown = set(inputs) - set(node.inputs)
    if unknown:
        raise NodeError(node.node_id, node.type_name, f"unknown input(s) {sorted(unknown)}; "
                        f"inputs are {sorted(node.inputs)}", bad_input=True)
    node.frames, node.full_frames, node._progress = frames, full_frames, progress
    node.seed = task_seed(json.dumps([node.type_name, node.key_params(), frames.start, frames.stop],
                                     sort_keys=True)) if seed is None else int(seed)
    node._device = device
    if wanted is not None:
        unknown = set(wanted) - set(node.outputs)
        if unknown:
            raise NodeError(node.node_id, node.type_name, f"wanted unknown output(s) {sorted(unknown)}; "
                            f"outputs are {sorted(node.outputs)}")
        node.wanted_outputs = frozenset(wanted) if node.skips_unread_outputs else frozenset(node.outputs)
    try:
        with intra_op_threads(node.torch_threads):
            result = node.run(**{name: (list(inputs.get(name) or []) if port.many else inputs.get(name))
                                 for name, port in node.inputs.items()})
    except Exception as err:
        raise wrap_error(node, err, _where(node, frames)) from err
    finally:
        node._progress = None
    if not isinstance(result, Mapping):
        raise NodeError(node.node_id, node.type_name,
                        f"run() must return a dict of outputs, found {type(result).__name__}")
    missing = node.wanted_outputs - set(result)
    extra = set(result) - set(node.outputs)
    if missing or extra:
        raise NodeError(node.node_id, node.type_name,
                        f"run() returned ports {sorted(result)}, declared {sorted(node.outputs)}"
                        + (f" (wanted {sorted(node.wanted_outputs)})" if node.wanted_outputs != set(node.outputs) else ""))
    for name, port in node.outputs.items():
        if name in result:
            _check_value(node, port, result[name], count, "output", frames)
    return dict(result)


def run_node(node_type: type[Node] | Node, params: NodeParams | Mapping[str, Any] | None = None, /,
             *, frames: range | None = None, **inputs: Any) -> dict[str, PortType]:
    """Run one node in-process (no dask, no cache): the helper for unit tests and scripts.

    Args:
        node_type: a Node subclass (or an instance, then `params` must be None).
        params: parameters (dict or the node's Params model).
        frames: absolute frames the per-frame inputs cover; default: 0..F-1 from the first
            per-frame input, else the node's `frame_count()`.
        inputs: input values by port name.
    Returns:
        output port name -> value.

    Example:
        >>> out = run_node(ScaleMesh, {"factor": 2.0}, mesh=mesh)  # doctest: +SKIP
    """
    node = node_type if isinstance(node_type, Node) else node_type(params)
    if frames is None:
        count = None
        for name, port in node.inputs.items():
            value = inputs.get(name)
            if port.many and isinstance(value, (list, tuple)) and value:
                value = value[0]  # a list port: its values cover the same frames
            if port.per_frame and isinstance(value, PortType) and value.per_frame:
                count = value.num_frames
                break
        if count is None:
            try:
                count = node.frame_count() or 0
            except Exception as err:
                raise wrap_error(node, err, bad_input=True) from err
        frames = range(count)
    return execute(node, inputs, frames, frames)


def format_exception(err: BaseException) -> str:
    """The traceback text of `err` (with its causes)."""
    return "".join(traceback.format_exception(type(err), err, err.__traceback__))
