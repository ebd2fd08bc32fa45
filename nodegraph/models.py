"""Networks as plain data: the `TorchModel` port type, the architecture registry behind
`TorchModel.build`, and model files.

A module that defines a network registers a builder under a stable name::

    @register_architecture("dynamics.MLP")
    def build_mlp(config: dict) -> torch.nn.Module:
        return MLP(**config)

and stores a trained one as `TorchModel.from_module("dynamics.MLP", config, module)`.
`TorchModel.build()` (here: `build_model`) calls the builder with the stored config, checks
that the state keys, shapes and dtypes match the module it built, and loads the weights.
Builders registered in node modules are found after the node plugins are imported (done
on the first unknown name).

Files (`save_model` / `load_model`) are npz archives of `TorchModel.to_arrays()` plus a
`__port_type__` marker: plain arrays and JSON strings, read with `allow_pickle=False`.

This module does not import torch at module level; only `build_model` and the file readers
(`check_model_weights`) do.
"""

from __future__ import annotations

import difflib
import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from .ports import PortType, check_finite, fail

__all__ = ["TorchModel", "register_architecture", "architectures", "get_architecture", "build_model",
           "check_model_weights", "save_model", "load_model", "save_model_safetensors",
           "load_model_safetensors",
           "SAFETENSORS_FORMAT"]

SAFETENSORS_FORMAT = "nodegraph.TorchModel/1"
"""The `format` metadata entry of a TorchModel written by `save_model_safetensors`."""

Builder = Callable[[dict[str, Any]], Any]

_ARCHITECTURES: dict[str, Builder] = {}


@dataclass(eq=False)
class TorchModel(PortType):
    """A trained network as plain data: architecture name, JSON config, weights.

    The module is rebuilt by `build()` through the architecture registry of
    `nodegraph.models` (a builder `(config) -> torch.nn.Module` registered under the
    architecture name), then the weights are loaded. Stored (cache, `save`) as an npz of
    plain arrays: no pickle anywhere. The fingerprint covers architecture, config (canonical
    JSON, sorted keys), weights and normalization, independent of dict insertion order.

    Attributes:
        architecture: registered builder name (e.g. "dynamics.MLP").
        config: JSON-able builder arguments.
        state: parameter/buffer name -> array (a torch `state_dict` as numpy, dtypes kept).
        normalization: name -> array the network's user applies around it (e.g. "input_mean",
            "input_std" (D,) float32); empty when none.
    """

    architecture: str
    config: dict[str, Any]
    state: dict[str, np.ndarray]
    normalization: dict[str, np.ndarray] = field(default_factory=dict)

    def validate(self, where: str = "") -> None:
        where = where or f"{self.type_name} '{self.architecture}'"
        if not isinstance(self.architecture, str) or not self.architecture:
            fail(where, f"'architecture' must be a non-empty string, found {self.architecture!r}")
        if not isinstance(self.config, dict):
            fail(where, f"'config' must be a JSON object (dict), found {type(self.config).__name__}")
        try:
            json.dumps(self.config, allow_nan=False)
        except (TypeError, ValueError) as err:
            fail(where, f"'config' must be JSON-able, found {err}")
        for group in ("state", "normalization"):
            for key, value in getattr(self, group).items():
                if not isinstance(value, np.ndarray) or value.dtype.kind not in "biuf":
                    fail(where, f"'{group}['{key}']' must be a numeric numpy array, found "
                                f"{getattr(value, 'dtype', type(value).__name__)}")
        for key, value in self.normalization.items():  # weights may hold inf (e.g. masks)
            check_finite(where, f"normalization['{key}']", value)

    @classmethod
    def from_module(cls, architecture: str, config: Mapping[str, Any], module: Any,
                    normalization: Mapping[str, np.ndarray] | None = None) -> TorchModel:
        """Capture a torch module's `state_dict` as numpy arrays (copies, dtypes preserved).

        Args:
            architecture: the registered builder name that rebuilds `module` from `config`.
            config: JSON-able builder arguments.
            module: a `torch.nn.Module` (any device).
            normalization: optional name -> array (e.g. input mean/std).
        Raises:
            TypeError: for a tensor dtype numpy cannot hold (e.g. bfloat16), naming the key.
        """
        state = {}
        for key, tensor in module.state_dict().items():
            try:
                state[key] = tensor.detach().cpu().numpy().copy()
            except TypeError as err:
                raise TypeError(f"TorchModel '{architecture}': state '{key}' has dtype "
                                f"{tensor.dtype}, which numpy cannot hold ({err}); convert the "
                                "module to float32/float16/float64 first") from err
        model = cls(architecture=architecture, config=json.loads(json.dumps(dict(config))),
                    state=state,
                    normalization={k: np.array(v) for k, v in (normalization or {}).items()})
        model.validate()
        return model

    def build(self, device: str = "cpu") -> Any:
        """Construct the module through the architecture registry and load the weights.

        Returns:
            the `torch.nn.Module` on `device`, in eval mode.
        Raises:
            KeyError: unknown architecture (the known ones are listed).
            ValueError: state keys, shapes or dtypes that do not match the module the
                config builds.
        """
        return build_model(self, device=device)

    def save(self, path: str | Any) -> None:
        """Write the model as an npz of plain arrays (atomically, no pickle); see `load`."""
        save_model(self, path)

    @classmethod
    def load(cls, path: str | Any) -> TorchModel:
        """Read a model written by `save` (loaded with `allow_pickle=False`)."""
        return load_model(path)


def register_architecture(name: str) -> Callable[[Builder], Builder]:
    """Decorator: register `builder(config) -> torch.nn.Module` under `name`.

    Re-registering the same function (e.g. a module imported twice) is allowed; a different
    function under a known name is an error.

    Raises:
        ValueError: `name` empty, or already taken by another builder.
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"register_architecture: expected a non-empty name, found {name!r}")

    def decorator(builder: Builder) -> Builder:
        known = _ARCHITECTURES.get(name)
        if known is not None and (known.__module__, known.__qualname__) != \
                (builder.__module__, builder.__qualname__):
            raise ValueError(f"architecture '{name}' registered twice: "
                             f"{known.__module__}.{known.__qualname__} and "
                             f"{builder.__module__}.{builder.__qualname__}")
        _ARCHITECTURES[name] = builder
        return builder

    return decorator


def architectures() -> dict[str, Builder]:
    """Every registered architecture by name (node plugins imported first)."""
    from .registry import load_plugins

    load_plugins()
    return dict(sorted(_ARCHITECTURES.items()))


def get_architecture(name: str) -> Builder:
    """Return the builder registered as `name` (importing the node plugins if needed).

    Raises:
        KeyError: naming the unknown architecture, the closest and all known names.
    """
    if name not in _ARCHITECTURES:
        from .registry import load_plugins

        load_plugins()
    try:
        return _ARCHITECTURES[name]
    except KeyError:
        close = difflib.get_close_matches(name, list(_ARCHITECTURES), n=3)
        hint = f"; did you mean {', '.join(map(repr, close))}?" if close else ""
        raise KeyError(f"unknown architecture '{name}'{hint} (known: {sorted(_ARCHITECTURES)}; "
                       "register one with nodegraph.models.register_architecture)") from None


def _mismatches(model: TorchModel, expected: dict[str, Any]) -> list[str]:
    """Differences between stored weights and the state_dict of the module built from config."""
    problems = []
    missing = sorted(set(expected) - set(model.state))
    unexpected = sorted(set(model.state) - set(expected))
    if missing:
        problems.append(f"missing from the stored state: {missing}")
    if unexpected:
        problems.append(f"stored but not in the module: {unexpected}")
    for key in sorted(set(expected) & set(model.state)):
        tensor, array = expected[key], model.state[key]
        if tuple(tensor.shape) != tuple(array.shape):
            problems.append(f"'{key}': the module has shape {tuple(tensor.shape)}, stored "
                            f"{tuple(array.shape)}")
        elif str(tensor.dtype).removeprefix("torch.") != str(array.dtype):
            problems.append(f"'{key}': the module has dtype {tensor.dtype}, stored {array.dtype}")
        elif array.dtype.kind == "f" and np.isnan(array).any():  # inf may be meant (masks); NaN never
            problems.append(f"'{key}': stored {int(np.isnan(array).sum())} NaN values of {array.size}")
    return problems


def check_model_weights(model: TorchModel, where: str) -> None:
    """Check, without loading them, that `model`'s weights fit the module its config builds.

    The module is built on torch's "meta" device (shapes and dtypes, no memory), so a file can
    be checked when it is read, before any frame runs. A builder that cannot build on "meta" is
    built on the CPU instead.

    Args:
        model: the stored network.
        where: what to name in the error, e.g. the file it was read from.
    Raises:
        ValueError: "WHERE: ..." for an unknown architecture, a config its builder refuses, or
            weights whose keys, shapes or dtypes differ from the module's, or float weights
            holding NaN (each one listed).
    """
    import torch

    try:
        builder = get_architecture(model.architecture)
    except KeyError as err:
        raise ValueError(f"{where}: {err.args[0]}") from None
    try:
        try:
            with torch.device("meta"):
                module = builder(dict(model.config))
        except (NotImplementedError, RuntimeError):
            module = builder(dict(model.config))
    except (TypeError, ValueError, KeyError, RuntimeError) as err:
        raise ValueError(f"{where}: expected a config the builder of '{model.architecture}' accepts, "
                         f"found {model.config} ({type(err).__name__}: {err})") from err
    if not isinstance(module, torch.nn.Module):
        raise ValueError(f"{where}: the builder of '{model.architecture}' must return a "
                         f"torch.nn.Module, found {type(module).__name__}")
    problems = _mismatches(model, module.state_dict())
    if problems:
        raise ValueError(f"{where}: expected the weights of the '{model.architecture}' module its "
                         f"config builds ({model.config}), found: {'; '.join(problems)}")


def build_model(model: TorchModel, device: str = "cpu") -> Any:
    """Construct `model`'s module via the registry and load its weights (bit for bit).

    Args:
        model: the stored network.
        device: torch device string ("cpu", "cuda", "cuda:1", ...).
    Returns:
        `torch.nn.Module` on `device`, in eval mode.
    Raises:
        KeyError: unknown architecture.
        TypeError: the builder did not return a `torch.nn.Module`.
        ValueError: "TorchModel 'ARCH' (config {...}): ..." listing missing/unexpected keys and
            shape or dtype differences (no weight is ever cast or dropped silently).
    """
    import torch

    builder = get_architecture(model.architecture)
    module = builder(dict(model.config))
    where = f"TorchModel '{model.architecture}' (config {model.config})"
    if not isinstance(module, torch.nn.Module):
        raise TypeError(f"{where}: the builder {builder.__module__}.{builder.__qualname__} must "
                        f"return a torch.nn.Module, found {type(module).__name__}")
    problems = _mismatches(model, module.state_dict())
    if problems:
        raise ValueError(f"{where}: the stored weights do not match the module the config "
                         f"builds: {'; '.join(problems)}")
    state = {key: torch.from_numpy(np.array(array)) for key, array in model.state.items()}
    module.load_state_dict(state, strict=True)
    return module.to(device).eval()


def save_model(model: TorchModel, path: str | os.PathLike) -> None:
    """Write `model` to `path` (.npz) through a temp file in the same folder and a rename.

    A path ending in `.safetensors` is written by `save_model_safetensors` instead.
    """
    path = Path(path)
    if path.suffix.lower() == ".safetensors":
        save_model_safetensors(model, path)
        return
    from .files import atomic_path  # staged inside a writer's task (see nodegraph.staging)

    arrays = {"__port_type__": np.array(type(model).type_name), **model.to_arrays()}
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays)


def load_model(path: str | os.PathLike) -> TorchModel:
    """Read a model written by `save_model` (no pickle).

    Raises:
        ValueError: "FILE: ..." for an unreadable file, one that holds no TorchModel, or weights
            that do not fit the module their config builds (`check_model_weights`).
    """
    if Path(path).suffix.lower() == ".safetensors":
        return load_model_safetensors(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: np.array(data[key]) for key in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
        raise ValueError(f"{os.fspath(path)}: expected a TorchModel .npz, found an unreadable "
                         f"file ({type(err).__name__}: {err})") from err
    kind = str(arrays.pop("__port_type__", "(none)"))
    if kind != TorchModel.type_name:
        raise ValueError(f"{os.fspath(path)}: expected a TorchModel .npz ('__port_type__' = "
                         f"'TorchModel'), found '{kind}'")
    try:
        model = TorchModel.from_arrays(arrays)
    except (TypeError, KeyError, ValueError) as err:
        raise ValueError(f"{os.fspath(path)}: expected the arrays of a TorchModel, found keys "
                         f"{sorted(arrays)} ({err})") from err
    model.validate(os.fspath(path))
    check_model_weights(model, os.fspath(path))
    return model


def _json_array(array: np.ndarray) -> dict[str, Any]:
    """An array as exact JSON: dtype, shape and the values as Python numbers."""
    return {"dtype": array.dtype.str, "shape": list(array.shape), "data": array.reshape(-1).tolist()}


def save_model_safetensors(model: TorchModel, path: str | os.PathLike) -> None:
    """Write `model` as a `.safetensors` file (atomically: temp file in the folder, rename).

    Tensors: the weights, under their state keys. Metadata (strings): `format`
    (`SAFETENSORS_FORMAT`), `architecture`, `config` (JSON) and `normalization` (JSON: name ->
    {dtype, shape, data}, exact for every dtype) plus one `normalization.NAME` entry per array
    for readers that want a single one.
    """
    from safetensors.numpy import save_file

    from .files import atomic_path  # staged inside a writer's task (see nodegraph.staging)

    path = Path(path)
    norm = {key: _json_array(np.asarray(value)) for key, value in sorted(model.normalization.items())}
    metadata = {"format": SAFETENSORS_FORMAT, "architecture": model.architecture,
                "config": json.dumps(model.config, sort_keys=True),
                "normalization": json.dumps(norm, sort_keys=True)}
    for key, value in norm.items():
        metadata[f"normalization.{key}"] = json.dumps(value)
    tensors = {key: np.ascontiguousarray(value) for key, value in model.state.items()}
    with atomic_path(path) as tmp:  # usual permissions, temp file in the folder, then a rename
        save_file(tensors, str(tmp), metadata=metadata)


def load_model_safetensors(path: str | os.PathLike) -> TorchModel:
    """Read a model written by `save_model_safetensors` (weights and normalization bit-exact).

    Raises:
        ValueError: "FILE: ..." for an unreadable file, one without the TorchModel metadata, or
            weights that do not fit the module their config builds (`check_model_weights`).
    """
    from safetensors import safe_open

    where = os.fspath(path)
    try:
        with safe_open(where, framework="np") as fh:
            metadata = dict(fh.metadata() or {})
            state = {key: np.array(fh.get_tensor(key)) for key in fh.keys()}
    except Exception as err:  # safetensors raises its own error types for broken headers
        raise ValueError(f"{where}: expected a TorchModel .safetensors file, found an unreadable "
                         f"file ({type(err).__name__}: {err})") from err
    if metadata.get("format") != SAFETENSORS_FORMAT:
        raise ValueError(f"{where}: expected metadata 'format' = '{SAFETENSORS_FORMAT}', found "
                         f"{metadata.get('format')!r}")
    try:
        config = json.loads(metadata["config"])
        norm = {key: np.array(item["data"], dtype=np.dtype(item["dtype"])).reshape(item["shape"])
                for key, item in json.loads(metadata["normalization"]).items()}
        model = TorchModel(architecture=metadata["architecture"], config=config, state=state,
                           normalization=norm)
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{where}: expected metadata 'architecture', 'config' and "
                         f"'normalization' of a TorchModel, found keys {sorted(metadata)} ({err})") from err
    model.validate(where)
    check_model_weights(model, where)
    return model
