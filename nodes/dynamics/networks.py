"""The MLPs of the removal (F) and synthesis (H) networks, their registry entry and training.

`dynamics.MLP` builds `Linear -> ReLU -> ... -> Linear` from a config with `in_features`,
`hidden` (list of widths) and `out_features`; other config keys (feature settings) are ignored
by the builder. Training: L2 loss, Adam, mini-batches drawn from a `torch.Generator` seeded by
the caller (weights are initialised under the same seed), so a given seed reproduces the network
bit for bit on one machine. Inputs and targets are standardized with their training mean and
std; the statistics travel with the model (`TorchModel.normalization`). An input column that was
constant over the training rows (its std at `STD_FLOOR`) is read as its training value when the
network is applied (`standardize_inputs`). torch is imported only inside the functions.
"""

from __future__ import annotations

import time
from typing import Any, Callable, ContextManager, NamedTuple

import numpy as np

from nodegraph import register_architecture
from nodegraph.node import intra_op_threads

__all__ = ["build_mlp", "TrainResult", "STD_FLOOR", "standardize_stats", "standardize_inputs", "train_mlp",
           "predict", "single_thread"]

STD_FLOOR = 1e-6
"""Smallest stored std of a standardized column; a column at it was constant in training."""


@register_architecture("dynamics.MLP")
def build_mlp(config: dict[str, Any]) -> Any:
    """Build the MLP of `config` (`in_features`, `hidden`, `out_features`)."""
    import torch

    widths = [int(config["in_features"]), *[int(h) for h in config["hidden"]]]
    layers: list[Any] = []
    for a, b in zip(widths[:-1], widths[1:]):
        layers += [torch.nn.Linear(a, b), torch.nn.ReLU()]
    layers.append(torch.nn.Linear(widths[-1], int(config["out_features"])))
    return torch.nn.Sequential(*layers)


class TrainResult(NamedTuple):
    """A trained module and its history.

    Attributes:
        module: the torch module (cpu, eval mode).
        losses: mean training loss per epoch (standardized units).
        seconds: wall-clock training time (s).
    """

    module: Any
    losses: list[float]
    seconds: float


def standardize_stats(values: np.ndarray, *, floor: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std (floored) per column of (R, D) values, float32."""
    mean = values.mean(axis=0, dtype=np.float64)
    std = np.sqrt(np.maximum(values.var(axis=0, dtype=np.float64), 0.0))
    return mean.astype(np.float32), np.maximum(std, floor).astype(np.float32)


def standardize_inputs(rows: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    """(rows - mean) / std for a trained network's inputs, (..., D); 0 in the columns that were
    constant over the training rows (std at `STD_FLOOR`).

    Such a column taught the network nothing: standardized it was 0 in every training row, so
    its first-layer weights kept their random start. Divided by the floor, a new value there
    (a stretch the training frames never showed, a skull motion where they held still) became
    a huge input to those random weights: a synthesis network trained on frames of one held
    expression (64 constant stretch columns of 379) put 158 cm offsets on a smile. Read as its
    training value, such a column does not move the output.
    """
    z = (rows - mean) / std
    constant = np.asarray(std) <= np.float32(STD_FLOOR)
    if constant.any():
        z[..., constant] = 0.0
    return z


def train_mlp(inputs: np.ndarray, targets: np.ndarray, *, hidden: list[int], epochs: int,
              batch_size: int, lr: float, seed: int, device: str = "cpu",
              progress: Callable[[float, str], None] | None = None) -> TrainResult:
    """Fit an MLP to standardized (inputs, targets) with L2 loss and Adam.

    Args:
        inputs: (R, D) float32, already standardized.
        targets: (R, O) float32, already standardized.
        hidden: widths of the hidden layers.
        epochs: passes over the rows.
        batch_size: rows per step.
        lr: Adam learning rate.
        seed: weight initialisation and batch order.
        device: torch device.
        progress: optional callback (fraction, message).
    Returns:
        TrainResult with the module on cpu in eval mode.
    """
    import torch

    start = time.perf_counter()
    config = {"in_features": inputs.shape[1], "hidden": list(hidden), "out_features": targets.shape[1]}
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        module = build_mlp(config).to(device)
    gen = torch.Generator().manual_seed(seed)
    x = torch.from_numpy(np.ascontiguousarray(inputs, np.float32)).to(device)
    y = torch.from_numpy(np.ascontiguousarray(targets, np.float32)).to(device)
    opt = torch.optim.Adam(module.parameters(), lr=lr)
    rows = len(x)
    losses = []
    module.train()
    for epoch in range(epochs):
        order = torch.randperm(rows, generator=gen).to(device)
        total = 0.0
        for a in range(0, rows, batch_size):
            idx = order[a:a + batch_size]
            opt.zero_grad(set_to_none=True)
            loss = torch.mean((module(x[idx]) - y[idx]) ** 2)
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(idx)
        losses.append(total / max(rows, 1))
        if progress is not None:
            progress((epoch + 1) / epochs, f"epoch {epoch + 1}/{epochs} loss {losses[-1]:.4f}")
    module = module.cpu().eval()
    return TrainResult(module, losses, time.perf_counter() - start)


def single_thread() -> ContextManager[None]:
    """Run torch on one intra-op thread inside the block (restored after): `nodegraph.node.intra_op_threads`.

    Per-frame inference is a stream of tiny products; on a busy 2-core machine two intra-op
    threads made it 10x slower (17 s instead of 1.6 s for 220 frames of 344 samples).
    """
    return intra_op_threads(1)


def predict(module: Any, rows: np.ndarray) -> np.ndarray:
    """Evaluate `module` on (R, D) float32 rows in one call (no grad); returns (R, O) float32."""
    import torch

    with torch.no_grad():
        return module(torch.from_numpy(np.ascontiguousarray(rows, np.float32))).numpy()
