"""graphs/fit_video.json on one real photo must not jump to another minimum when a few pixels change
by one 8-bit level (issue 30: another machine's rounding, a re-encoded file).

skimage's astronaut (the 256^2 crop of test_fit_video_graph.py) is fitted as it is and with 0.1%
of its pixels moved by +-1 level (the network's plate points move by ~4e-3 px, forty times what
another CPU's rounding moves them). Measured on three such copies before the photometric term
left painted frames and down-weighted views the model does not explain (nodes.fit.tuning.
photometric_frame_weights, nodes.fit.photometric.RESIDUAL_SCALE_REFERENCE): rotation 2.5 / 3.0 /
0.26 deg apart, translation 1.2 / 3.1 / 0.07 cm, weights 0.50 / 1.00 / 0.44, identity 2.2 / 3.1 /
1.6; after: 0.17 / 0.16 / 0.25 deg, 0.02 / 0.06 / 0.09 cm, weights 0.024 / 0.036 / 0.022,
identity 0.016 / 0.006 / 0.014. The bounds sit three to four times above the second set and far
below the first."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nodegraph import Graph, runner

pytest.importorskip("torch")
pytest.importorskip("tflite")
data = pytest.importorskip("skimage.data")

GRAPH = Path(__file__).resolve().parents[2] / "graphs" / "fit_video.json"


def _fit(folder: Path, plate: np.ndarray) -> dict[str, np.ndarray]:
    from nodes.io.image import write_image

    folder.mkdir()
    write_image(folder / "plate.0000.png", plate.astype(np.float32) / 255.0, ["R", "G", "B"], "uint8")
    params = {"images": str(folder / "plate.%04d.png"), "output": str(folder / "fit.npz"),
              "report": str(folder / "report")}
    result = runner.run(Graph.load(GRAPH), parameters=params, scheduler="sync", cache=False)
    assert result.exit_code == 0, result.summary()
    with np.load(folder / "fit.npz") as fit:
        return {k: fit[k].astype(np.float64) for k in ("rotation", "translation", "weights", "identity")}


@pytest.mark.slow
def test_one_level_on_a_few_pixels_moves_the_photo_fit_little(tmp_path):
    face = data.astronaut()[:256, 64:320].astype(np.int16)
    ref = _fit(tmp_path / "v0", face)
    rng = np.random.default_rng(0)
    for k in (1, 2):
        moved = face.copy()
        pick = rng.random(face.shape[:2]) < 0.001
        moved[pick] = np.clip(moved[pick] + rng.choice([-1, 1], size=moved[pick].shape), 0, 255)
        got = _fit(tmp_path / f"v{k}", moved)
        diff = np.linalg.norm((got["rotation"] - ref["rotation"]).ravel())
        rotation_deg = np.degrees(2 * np.arcsin(min(1.0, diff / 8 ** 0.5)))
        print(f"copy {k}: rotation {rotation_deg:.3f} deg, translation "
              f"{np.abs(got['translation'] - ref['translation']).max():.3f} cm, weights "
              f"{np.abs(got['weights'] - ref['weights']).max():.3f}, identity "
              f"{np.abs(got['identity'] - ref['identity']).max():.3f}")
        assert rotation_deg < 0.75, (k, rotation_deg)
        assert np.abs(got["translation"] - ref["translation"]).max() < 0.4, k
        assert np.abs(got["weights"] - ref["weights"]).max() < 0.15, k
        assert np.abs(got["identity"] - ref["identity"]).max() < 0.1, k
