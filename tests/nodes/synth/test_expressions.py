"""Tests of nodes/synth/expressions.py: rest budget, blinks, speech, symmetry, range."""

from __future__ import annotations

import numpy as np
import pytest

from nodes.io.face_model import load_face_model
from nodes.synth.expressions import (REST_THRESHOLD, ExpressionEvent, envelope, expression_curves,
                                     place_events)

FPS = 30.0


@pytest.fixture(scope="module")
def names() -> list[str]:
    return load_face_model(region="narrow_face", max_vertices=50).expression_names


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of each run of True."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))


@pytest.mark.parametrize("rest_fraction", [0.0, 0.5, 0.8, 0.97])
def test_expression_curves_rest_fraction_per_weight(names, rest_fraction):
    w = expression_curves(names, 1800, seed=5, fps=FPS, rest_fraction=rest_fraction)
    assert w.shape == (1800, 53) and w.dtype == np.float32
    assert w.min() >= 0.0 and w.max() <= 1.0
    at_rest = (w < REST_THRESHOLD).mean(axis=0)
    assert at_rest.min() >= rest_fraction
    assert (w > 0.3).any(axis=0).sum() >= (5 if rest_fraction < 0.9 else 2)  # not all at rest


def test_expression_curves_blinks_both_eyes_short_every_few_seconds(names):
    w = expression_curves(names, 1800, seed=2, fps=FPS, rest_fraction=0.5)
    left, right = w[:, names.index("eyeBlink_L")], w[:, names.index("eyeBlink_R")]
    np.testing.assert_array_equal(left > 0.5, right > 0.5)
    blinks = _runs(left > REST_THRESHOLD)
    assert 60 / 6.5 <= len(blinks) <= 60 / 2 + 1  # every 2-6 s over 60 s
    assert max(b - a for a, b in blinks) <= int(np.ceil(0.15 * FPS)) + 1  # 100-150 ms
    assert sum(left[a:b].max() > 0.5 for a, b in blinks) >= 0.8 * len(blinks)


def test_expression_curves_speech_jaw_at_syllable_rate(names):
    w = expression_curves(names, 1800, seed=1, fps=FPS, rest_fraction=0.5)
    jaw = w[:, names.index("jawOpen")].astype(np.float64)
    power = np.abs(np.fft.rfft(jaw - jaw.mean())) ** 2
    freq = np.fft.rfftfreq(len(jaw), 1 / FPS)
    above_1hz = freq > 1.0
    peak = freq[above_1hz][np.argmax(power[above_1hz])]
    assert 3.0 <= peak <= 6.0
    assert (w[:, names.index("mouthClose")] > 0.2).any()
    assert (w[:, [names.index("mouthFunnel"), names.index("mouthPucker")]] > 0.2).any()


def test_expression_curves_pairs_mostly_symmetric(names):
    w = expression_curves(names, 3600, seed=4, fps=FPS, rest_fraction=0.5)
    for base in ("browInnerUp", "mouthSmile", "eyeSquint", "browDown"):
        left, right = w[:, names.index(base + "_L")], w[:, names.index(base + "_R")]
        if left.max() > 0.1:
            assert np.corrcoef(left, right)[0, 1] > 0.7, base


def test_expression_curves_busy_stretches_move_many_shapes(names):
    w = expression_curves(names, 1800, seed=3, fps=FPS, rest_fraction=0.3)
    assert (w > 0.1).sum(axis=1).max() >= 10
    quiet = expression_curves(names, 1800, seed=3, fps=FPS, rest_fraction=0.3, busy=False,
                              speech=False)
    assert (quiet > 0.1).sum(axis=1).max() < (w > 0.1).sum(axis=1).max()


def test_expression_curves_same_seed_same_curves(names):
    a = expression_curves(names, 300, seed=7)
    np.testing.assert_array_equal(a, expression_curves(names, 300, seed=7))
    assert not np.array_equal(a, expression_curves(names, 300, seed=8))


def test_expression_curves_unknown_names_stay_zero():
    w = expression_curves(["foo", "eyeBlink_L", "bar"], 600, seed=0)
    assert np.all(w[:, [0, 2]] == 0) and w[:, 1].max() > 0.5


def test_expression_curves_errors(names):
    with pytest.raises(ValueError, match=r"rest_fraction: expected in \[0, 1\], found 1.5"):
        expression_curves(names, 10, seed=0, rest_fraction=1.5)
    with pytest.raises(ValueError, match="fps: expected > 0"):
        expression_curves(names, 10, seed=0, fps=0)


def test_envelope_attack_hold_release():
    t = np.array([0.0, 1.0, 1.05, 1.1, 1.5, 2.1, 2.2, 2.3, 3.0])
    e = envelope(t, 1.0, 0.1, 1.0, 0.2)
    np.testing.assert_allclose(e, [0, 0, 0.5, 1, 1, 1, 0.5, 0, 0], atol=1e-12)


def test_place_events_rejects_over_budget():
    ones = np.ones((1, 10), np.float32)
    events = [ExpressionEvent(np.array([0]), s, s + 10, ones) for s in (0, 20, 40)]
    w = place_events(events, 1, 50, rest_fraction=0.6, rng=np.random.default_rng(0))
    assert (w[:, 0] > 0).sum() == 20  # budget 0.4 * 50 = 20 frames: two events of 10
