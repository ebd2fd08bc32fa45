"""TorchModel and the architecture registry: bit-exact round trips through the cache's npz form."""

from __future__ import annotations

import io
import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nodegraph.models import architectures, load_model, register_architecture, save_model  # noqa: E402
from nodegraph.types import TorchModel  # noqa: E402


class TinyMLP(torch.nn.Module):
    def __init__(self, d_in: int, hidden: int, d_out: int, dtype: str = "float32"):
        super().__init__()
        dt = getattr(torch, dtype)
        self.layers = torch.nn.Sequential(torch.nn.Linear(d_in, hidden, dtype=dt), torch.nn.Tanh(),
                                          torch.nn.Linear(hidden, d_out, dtype=dt))
        self.register_buffer("scale", torch.ones(d_out, dtype=dt))

    def forward(self, x):
        return self.layers(x) * self.scale


@register_architecture("test.TinyMLP")
def build_tiny_mlp(config: dict) -> torch.nn.Module:
    return TinyMLP(**config)


def _trained(config: dict, seed: int = 0) -> TinyMLP:
    gen = torch.Generator().manual_seed(seed)
    module = TinyMLP(**config)
    with torch.no_grad():
        for tensor in module.state_dict().values():
            tensor.copy_(torch.randn(tensor.shape, generator=gen, dtype=tensor.dtype))
    return module


def _npz_round_trip(model: TorchModel) -> TorchModel:
    buffer = io.BytesIO()
    np.savez(buffer, **model.to_arrays())
    buffer.seek(0)
    with np.load(buffer, allow_pickle=False) as data:
        return TorchModel.from_arrays({k: data[k] for k in data.files})


@pytest.mark.parametrize("dtype", ["float32", "float64", "float16"])
def test_mlp_round_trips_bit_for_bit_through_npz(dtype):
    config = {"d_in": 5, "hidden": 16, "d_out": 3, "dtype": dtype}
    module = _trained(config)
    norm = {"input_mean": np.arange(5, dtype=np.float32), "input_std": np.ones(5, np.float32)}
    model = TorchModel.from_module("test.TinyMLP", config, module, normalization=norm)
    assert model.state["layers.0.weight"].dtype == np.dtype(dtype)
    back = _npz_round_trip(model)
    assert back.fingerprint() == model.fingerprint()
    assert back.architecture == "test.TinyMLP" and back.config == config
    np.testing.assert_array_equal(back.normalization["input_mean"], norm["input_mean"])
    rebuilt = back.build()
    assert not rebuilt.training
    x = torch.randn(7, 5, generator=torch.Generator().manual_seed(1), dtype=getattr(torch, dtype))
    if dtype == "float16":
        x = x.float().half()
    with torch.no_grad():
        expected = module.eval()(x)
        assert torch.equal(rebuilt(x), expected)
    for key, tensor in module.state_dict().items():
        assert torch.equal(rebuilt.state_dict()[key], tensor)


def test_save_and_load_file(tmp_path):
    config = {"d_in": 2, "hidden": 4, "d_out": 1}
    model = TorchModel.from_module("test.TinyMLP", config, _trained(config))
    path = tmp_path / "sub" / "model.npz"
    model.save(path)
    assert TorchModel.load(path).fingerprint() == model.fingerprint()
    assert load_model(path).build().state_dict().keys() == _trained(config).state_dict().keys()
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(ValueError, match=r"other\.npz: expected a TorchModel \.npz.*found '\(none\)'"):
        load_model(tmp_path / "other.npz")
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(ValueError, match=r"junk\.npz: expected a TorchModel \.npz, found an "
                                         r"unreadable file"):
        load_model(tmp_path / "junk.npz")


def test_fingerprint_covers_architecture_config_and_ignores_insertion_order():
    config = {"d_in": 3, "hidden": 4, "d_out": 2}
    module = _trained(config)
    model = TorchModel.from_module("test.TinyMLP", config, module)
    reordered = TorchModel(architecture="test.TinyMLP",
                           config={"d_out": 2, "hidden": 4, "d_in": 3},
                           state=dict(reversed(list(model.state.items()))))
    assert reordered.fingerprint() == model.fingerprint()
    assert TorchModel("test.Other", model.config, model.state).fingerprint() != model.fingerprint()
    assert TorchModel(model.architecture, {**config, "dtype": "float32"},
                      model.state).fingerprint() != model.fingerprint()
    norm = TorchModel(model.architecture, model.config, model.state,
                      normalization={"input_mean": np.zeros(3, np.float32)})
    assert norm.fingerprint() != model.fingerprint()
    changed = {k: v.copy() for k, v in model.state.items()}
    changed["scale"][0] = np.nextafter(changed["scale"][0], np.float32(2))
    assert TorchModel(model.architecture, model.config, changed).fingerprint() != model.fingerprint()


def test_build_errors_name_the_architecture_and_the_mismatch():
    config = {"d_in": 3, "hidden": 4, "d_out": 2}
    model = TorchModel.from_module("test.TinyMLP", config, _trained(config))
    with pytest.raises(KeyError, match=r"unknown architecture 'test.TinyMPL'; did you mean "
                                       r"'test.TinyMLP'.*known: \[.*'test.TinyMLP'"):
        TorchModel("test.TinyMPL", config, model.state).build()
    with pytest.raises(ValueError, match=r"TorchModel 'test.TinyMLP' \(config .*'hidden': 5.*\): "
                                         r"the stored weights do not match.*'layers.0.weight': the "
                                         r"module has shape \(5, 3\), stored \(4, 3\)"):
        TorchModel("test.TinyMLP", {**config, "hidden": 5}, model.state).build()
    partial = {k: v for k, v in model.state.items() if k != "scale"}
    partial["extra"] = np.zeros(1, np.float32)
    with pytest.raises(ValueError, match=r"missing from the stored state: \['scale'\]; stored but "
                                         r"not in the module: \['extra'\]"):
        TorchModel("test.TinyMLP", config, partial).build()
    with pytest.raises(ValueError, match=r"'scale': the module has dtype torch.float32, stored "
                                         r"float64"):
        TorchModel("test.TinyMLP", config,
                   {**model.state, "scale": model.state["scale"].astype(np.float64)}).build()


def test_register_architecture_refuses_a_second_builder():
    with pytest.raises(ValueError, match=r"architecture 'test.TinyMLP' registered twice"):
        @register_architecture("test.TinyMLP")
        def other(config):  # noqa: ARG001
            return None
    assert "test.TinyMLP" in architectures()


def test_bfloat16_is_refused_with_the_key():
    module = torch.nn.Linear(2, 2, dtype=torch.bfloat16)
    with pytest.raises(TypeError, match=r"state 'weight' has dtype torch.bfloat16"):
        TorchModel.from_module("x", {}, module)


def test_models_module_does_not_import_torch():
    code = "import sys, nodegraph.models, nodegraph.types; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
