"""Trained dynamics networks on disk: `.safetensors` files (weights as tensors; architecture,
config, input normalization and sample vertex ids in the metadata), or `.npz`."""

from __future__ import annotations

from pathlib import Path

from pydantic import field_validator

from nodegraph import SEQUENCE, Files, In, InputError, Node, NodeParams, Out, Param, TorchModel
from nodegraph.files import check_output_suffix, files_value
from nodegraph.models import load_model, save_model

__all__ = ["BUNDLED_REMOVAL", "SaveModel", "LoadModel"]

_SUFFIXES = (".safetensors", ".npz")


def _check_suffix(path: str) -> None:
    if Path(path).suffix.lower() not in _SUFFIXES:
        raise InputError("path", f"expected a {' or '.join(_SUFFIXES)} file, found '{path}'")


class SaveModel(Node):
    """Write a trained network to a .safetensors (or .npz) file, atomically."""

    type_name = "dynamics.SaveModel"
    version = 1
    kind = SEQUENCE
    writes_files = True

    class Params(NodeParams):
        path: str = Param("out/dynamics_removal.safetensors", output_file=True,
                          description="output .safetensors (or .npz) file")

        @field_validator("path")
        @classmethod
        def _suffix(cls, value: str) -> str:  # refused at validation, not after the training
            return check_output_suffix(value, _SUFFIXES)

    model = In(TorchModel, doc="the network (dynamics.TrainRemoval / dynamics.TrainSynthesis)")
    files = Out(Files, doc="the written file and its sha256")

    def run(self, model: TorchModel) -> dict:
        _check_suffix(self.params.path)
        save_model(model, self.params.path)  # temp file in the same folder, then a rename
        return {"files": files_value([self.params.path])}


BUNDLED_REMOVAL = Path(__file__).resolve().parent.parent / "data" / "dynamics" / "removal_ict_face.safetensors"
"""The removal network F shipped with the package: trained by `graphs/dynamics_train.json` (its
defaults with 80 epochs, seed 0) on the ICT head's 'face' region (9409 vertices); see its README."""


class LoadModel(Node):
    """Read a trained network written by dynamics.SaveModel (or the bundled removal network)."""

    type_name = "dynamics.LoadModel"
    version = 1
    kind = SEQUENCE

    class Params(NodeParams):
        path: str = Param("", input_file=True, description=".safetensors (or .npz) model file; '' = the bundled "
                          "removal network for captures of the ICT head's 'face' region "
                          "(io.LoadFaceModel region 'face'), trained by graphs/dynamics_train.json")

        @field_validator("path")
        @classmethod
        def _suffix(cls, value: str) -> str:
            return check_output_suffix(value, _SUFFIXES, allow_empty=True)

    model = Out(TorchModel, doc="the network")

    def input_files(self, frames: range | None = None) -> list[Path]:
        return [Path(self.params.path) if self.params.path else BUNDLED_REMOVAL]

    def check_plan(self, producers: dict) -> None:
        """Before anything runs: the file is read, so a missing, unreadable or spoiled network
        (wrong tensor shapes, float64 or NaN weights) is one refusal (exit 2) naming it, not a
        failure after the capture was read and the rest of the graph ran."""
        self.run()

    def peek_model(self) -> TorchModel | None:
        """The network, read while planning (for consumers' `check_plan`); None when unreadable
        (the run then reports why)."""
        try:
            return self.run()["model"]
        except (InputError, OSError, ValueError):
            return None

    def run(self) -> dict:
        path = self.params.path or str(BUNDLED_REMOVAL)
        _check_suffix(path)
        if not Path(path).is_file():
            raise InputError("path", f"expected an existing model file, found no file '{path}'")
        try:
            return {"model": load_model(path)}
        except ValueError as err:
            raise InputError("path", str(err)) from err
