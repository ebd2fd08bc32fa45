"""Synthetic expression-weight curves: sparse, enveloped, mostly at rest (ARKit shape names).

A performance is built from events, each an envelope (smoothstep attack, hold, release) over
a few channels that move together:
- blinks: eyeBlink_L and eyeBlink_R together, 100-150 ms, every 2-6 s;
- speech bursts (1-3 s): jawOpen pulses at a syllable rate of 3-6 Hz, with mouthClose
  between some syllables and mouthFunnel / mouthPucker on some, mouthLowerDown_L/R with the jaw;
- expressions: one family (brow raise, smile, frown, squint, sneer, gaze, ...) at a time,
  left/right pairs symmetric most of the time (85 %), else one side weaker;
- busy stretches (1-2 s): many families at once under one envelope.

Rest is guaranteed, not hoped for: events are proposed in random order and one is accepted
only if each of its channels stays within its budget of active frames,
`(1 - rest_fraction) * num_frames`. A weight can exceed 0.05 only inside the support of an
accepted event, so every weight is < 0.05 on at least `rest_fraction` of the frames.
Weights are clipped to [0, 1]. Channels whose names the model lacks are skipped.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

__all__ = [
    "REST_THRESHOLD", "smoothstep", "envelope", "ExpressionEvent", "expression_curves",
    "blink_events", "speech_events", "expression_events", "busy_events", "place_events",
    "held_expressions",
]

REST_THRESHOLD = 0.05
"""A weight below this is "at rest"."""

_FAMILIES: tuple[tuple[str, ...], ...] = (
    ("browInnerUp_L", "browInnerUp_R"), ("browOuterUp_L", "browOuterUp_R"),
    ("browDown_L", "browDown_R"), ("mouthSmile_L", "mouthSmile_R"),
    ("mouthFrown_L", "mouthFrown_R"), ("cheekSquint_L", "cheekSquint_R"),
    ("eyeSquint_L", "eyeSquint_R"), ("eyeWide_L", "eyeWide_R"), ("noseSneer_L", "noseSneer_R"),
    ("mouthDimple_L", "mouthDimple_R"), ("mouthStretch_L", "mouthStretch_R"),
    ("cheekPuff_L", "cheekPuff_R"), ("mouthPress_L", "mouthPress_R"),
    ("mouthUpperUp_L", "mouthUpperUp_R"), ("mouthLowerDown_L", "mouthLowerDown_R"),
    ("eyeLookUp_L", "eyeLookUp_R"), ("eyeLookDown_L", "eyeLookDown_R"),
    ("eyeLookOut_L", "eyeLookIn_R"), ("eyeLookIn_L", "eyeLookOut_R"),
    ("mouthLeft",), ("mouthRight",), ("jawLeft",), ("jawRight",), ("jawForward",),
    ("mouthRollLower",), ("mouthRollUpper",), ("mouthShrugLower",), ("mouthShrugUpper",),
    ("mouthFunnel",), ("mouthPucker",),
)


class ExpressionEvent(NamedTuple):
    """Channels that move together over frames [start, stop).

    Attributes:
        channels: (C,) int channel indices.
        start, stop: support in frames (absolute, clipped to the sequence).
        curves: (C, stop - start) float32 weights added to the channels.
    """

    channels: np.ndarray
    start: int
    stop: int
    curves: np.ndarray


def smoothstep(x: np.ndarray) -> np.ndarray:
    """Return 3x^2 - 2x^3 of x clipped to [0, 1] (C1 ramp from 0 to 1)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def envelope(t: np.ndarray, start: float, attack: float, hold: float, release: float) -> np.ndarray:
    """Attack / hold / release envelope (smoothstep ramps), 0 outside, 1 during the hold.

    Args:
        t: (...) times in seconds.
        start: onset (s); attack, hold, release: durations (s), attack and release > 0.
    Returns:
        (...) float64 in [0, 1]; zero for t <= start and t >= start + attack + hold + release.
    """
    rise = smoothstep((t - start) / attack)
    fall = smoothstep((start + attack + hold + release - t) / release)
    return np.minimum(rise, fall)


def _index(names: Sequence[str]) -> dict[str, int]:
    return {str(n): i for i, n in enumerate(names)}


def _event(index: dict[str, int], names: Sequence[str], weights: Sequence[np.ndarray],
           start: int, num_frames: int) -> ExpressionEvent | None:
    """Keep the channels the model has; None when none is left or the support is empty."""
    pairs = [(index[n], w) for n, w in zip(names, weights) if n in index]
    stop = min(start + len(weights[0]), num_frames)
    if not pairs or stop <= start:
        return None
    chans = np.array([p[0] for p in pairs], np.int64)
    curves = np.stack([p[1][: stop - start] for p in pairs]).astype(np.float32)
    return ExpressionEvent(chans, start, stop, curves)


def _times(start_s: float, duration_s: float, fps: float) -> tuple[int, np.ndarray]:
    """First frame at or after `start_s` and the frame times (s) covering the duration."""
    first = int(np.ceil(start_s * fps))
    last = int(np.floor((start_s + duration_s) * fps))
    return first, np.arange(first, max(last, first) + 1) / fps


def _pair_gains(rng: np.random.Generator, count: int) -> np.ndarray:
    """Gains of the channels of a family: symmetric (85 %: +-5 %) or one side weaker."""
    if count == 1:
        return np.ones(1)
    if rng.random() < 0.85:
        return 1.0 + 0.05 * rng.standard_normal(count)
    gains = np.ones(count)
    gains[rng.integers(count)] = rng.uniform(0.0, 0.5)
    return gains


def blink_events(rng: np.random.Generator, index: dict[str, int], num_frames: int,
                 fps: float) -> list[ExpressionEvent]:
    """Blinks every 2-6 s, 100-150 ms long (fast close, slower open), both eyes together."""
    events, t, duration_s = [], rng.uniform(0.5, 3.0), num_frames / fps
    while t < duration_s:
        length = rng.uniform(0.10, 0.15)
        first, times = _times(t, length, fps)
        curve = rng.uniform(0.9, 1.0) * envelope(times, t, 0.4 * length, 0.0, 0.6 * length)
        event = _event(index, ("eyeBlink_L", "eyeBlink_R"), [curve, curve], first, num_frames)
        if event is not None:
            events.append(event)
        t += length + rng.uniform(2.0, 6.0)
    return events


def speech_events(rng: np.random.Generator, index: dict[str, int], num_frames: int,
                  fps: float) -> list[ExpressionEvent]:
    """Speech bursts of 1-3 s every 2-8 s: jaw pulses at 3-6 syllables/s with lip shapes."""
    events, t, duration_s = [], rng.uniform(0.0, 3.0), num_frames / fps
    while t < duration_s:
        length = rng.uniform(1.0, 3.0)
        rate = rng.uniform(3.0, 6.0)
        first, times = _times(t, length, fps)
        burst = envelope(times, t, 0.1, length - 0.2, 0.1)
        period = 1.0 / rate
        syllable = np.floor((times - t) / period).astype(np.int64)
        phase = (times - t) / period - syllable  # [0, 1) within a syllable
        count = int(syllable.max()) + 1
        amp_jaw = rng.uniform(0.15, 0.6, count)[syllable]
        lips = rng.random(count)
        pulse = np.sin(np.pi * phase) ** 2  # open mid-syllable
        closure = np.cos(np.pi * phase) ** 2  # closed at syllable edges
        jaw = burst * amp_jaw * pulse
        close = burst * np.where(lips < 0.3, rng.uniform(0.3, 0.7), 0.0)[syllable] * closure
        funnel = burst * np.where((lips >= 0.3) & (lips < 0.45), rng.uniform(0.3, 0.7), 0.0)[syllable] * pulse
        pucker = burst * np.where((lips >= 0.45) & (lips < 0.6), rng.uniform(0.3, 0.7), 0.0)[syllable] * pulse
        lower = 0.5 * jaw
        event = _event(index, ("jawOpen", "mouthClose", "mouthFunnel", "mouthPucker",
                               "mouthLowerDown_L", "mouthLowerDown_R"),
                       [jaw, close, funnel, pucker, lower, lower], first, num_frames)
        if event is not None:
            events.append(event)
        t += length + rng.uniform(2.0, 8.0)
    return events


def _family_event(rng: np.random.Generator, index: dict[str, int], family: Sequence[str],
                  first: int, shape: np.ndarray, num_frames: int) -> ExpressionEvent | None:
    gains = _pair_gains(rng, len(family)) * rng.uniform(0.3, 1.0)
    return _event(index, family, [g * shape for g in gains], first, num_frames)


def expression_events(rng: np.random.Generator, index: dict[str, int], num_frames: int,
                      fps: float, rate_hz: float) -> list[ExpressionEvent]:
    """One family at a time (Poisson onsets at `rate_hz`): attack 0.1-0.4 s, hold 0.2-1.5 s,
    release 0.2-0.6 s, peak 0.3-1."""
    events, duration_s = [], num_frames / fps
    if rate_hz <= 0:
        return events
    t = rng.exponential(1.0 / rate_hz)
    while t < duration_s:
        attack, hold, release = rng.uniform(0.1, 0.4), rng.uniform(0.2, 1.5), rng.uniform(0.2, 0.6)
        first, times = _times(t, attack + hold + release, fps)
        shape = envelope(times, t, attack, hold, release)
        family = _FAMILIES[rng.integers(len(_FAMILIES))]
        event = _family_event(rng, index, family, first, shape, num_frames)
        if event is not None:
            events.append(event)
        t += rng.exponential(1.0 / rate_hz)
    return events


def busy_events(rng: np.random.Generator, index: dict[str, int], num_frames: int,
                fps: float) -> list[ExpressionEvent]:
    """Every 8-20 s, 1-2 s where 6-12 families move at once (slowly modulated, one envelope)."""
    events, t, duration_s = [], rng.uniform(2.0, 10.0), num_frames / fps
    while t < duration_s:
        length = rng.uniform(1.0, 2.0)
        first, times = _times(t, length, fps)
        base = envelope(times, t, 0.3, length - 0.6, 0.3)
        picks = rng.choice(len(_FAMILIES), size=rng.integers(6, 13), replace=False)
        for pick in picks:
            freq, phase = rng.uniform(0.3, 1.5), rng.uniform(0, 2 * np.pi)
            shape = base * (0.75 + 0.25 * np.sin(2 * np.pi * freq * (times - t) + phase))
            event = _family_event(rng, index, _FAMILIES[pick], first, shape, num_frames)
            if event is not None:
                events.append(event)
        t += length + rng.uniform(8.0, 20.0)
    return events


def place_events(events: Sequence[ExpressionEvent], num_channels: int, num_frames: int, *,
                 rest_fraction: float, rng: np.random.Generator) -> np.ndarray:
    """Sum events into weights, accepting each only if every channel keeps its rest budget.

    Args:
        events: candidate events.
        num_channels: K.
        num_frames: F.
        rest_fraction: in [0, 1]; each channel's accepted supports cover at most
            floor((1 - rest_fraction) * F) frames.
        rng: orders the candidates (random order spreads the budget over the sequence).
    Returns:
        (F, K) float32 weights in [0, 1].
    """
    budget = int(np.floor((1.0 - rest_fraction) * num_frames + 1e-9))
    active = np.zeros((num_channels, num_frames), bool)
    used = np.zeros(num_channels, np.int64)
    weights = np.zeros((num_frames, num_channels), np.float64)
    for i in rng.permutation(len(events)):
        chans, start, stop, curves = events[i]
        support = curves > 0
        new = (support & ~active[chans, start:stop]).sum(axis=1)
        if np.any(used[chans] + new > budget):
            continue
        active[chans, start:stop] |= support
        used[chans] += new
        weights[start:stop, chans] += curves.T
    return np.clip(weights, 0.0, 1.0).astype(np.float32)


def expression_curves(names: Sequence[str], num_frames: int, *, seed: int | np.random.SeedSequence,
                      fps: float = 30.0, rest_fraction: float = 0.7,
                      expression_rate_hz: float = 0.4, blinks: bool = True, speech: bool = True,
                      busy: bool = True) -> np.ndarray:
    """Generate expression weights for a whole performance (see the module docstring).

    Args:
        names: K channel names (ARKit names; unknown names stay 0).
        num_frames: F >= 0.
        seed: int or SeedSequence; the same seed gives the same curves.
        fps: frames per second (> 0); durations are in seconds, so curves scale with it.
        rest_fraction: in [0, 1]; every weight is < 0.05 on at least this fraction of frames.
        expression_rate_hz: mean onsets per second of single-family expressions.
        blinks, speech, busy: include blinks, speech bursts, busy stretches.
    Returns:
        (F, K) float32 in [0, 1].
    Raises:
        ValueError: fps <= 0, rest_fraction outside [0, 1], or num_frames < 0.

    Example:
        >>> w = expression_curves(["eyeBlink_L", "eyeBlink_R"], 300, seed=0)
        >>> w.shape, bool((w[:, 0] > 0.5).any())
        ((300, 2), True)
    """
    if fps <= 0:
        raise ValueError(f"fps: expected > 0, found {fps}")
    if not 0.0 <= rest_fraction <= 1.0:
        raise ValueError(f"rest_fraction: expected in [0, 1], found {rest_fraction}")
    if num_frames < 0:
        raise ValueError(f"num_frames: expected >= 0, found {num_frames}")
    streams = np.random.SeedSequence(seed) if not isinstance(seed, np.random.SeedSequence) else seed
    rngs = [np.random.default_rng(s) for s in streams.spawn(5)]
    index = _index(names)
    events: list[ExpressionEvent] = []
    if blinks:
        events += blink_events(rngs[0], index, num_frames, fps)
    if speech:
        events += speech_events(rngs[1], index, num_frames, fps)
    events += expression_events(rngs[2], index, num_frames, fps, expression_rate_hz)
    if busy:
        events += busy_events(rngs[3], index, num_frames, fps)
    return place_events(events, len(names), num_frames, rest_fraction=rest_fraction, rng=rngs[4])


def held_expressions(names: Sequence[str], num_frames: int, *, rng: np.random.Generator,
                     fps: float = 30.0, held_fraction: float = 0.0,
                     start_strength: float = 0.0) -> np.ndarray:
    """Strong held expressions (a hard case for stabilization), to add to `expression_curves`.

    - `held_fraction` > 0: the timeline is cut into segments of 1-3 s; each segment, with
      probability `held_fraction`, holds 2-4 random families at 0.6-1.0 (smoothstep attack
      and release of 0.2 s inside the segment), so about that fraction of the frames shows a
      strong expression.
    - `start_strength` > 0: the shot starts in a strong expression: 3 random families at
      `start_strength` held for the first second, released over the next 0.5 s.

    Args:
        names: K channel names (unknown family names are skipped).
        num_frames: F.
        rng: the generator (a stream of its own, so other curves do not change).
        fps: frames per second.
        held_fraction: in [0, 1].
        start_strength: in [0, 1].
    Returns:
        (F, K) float32 weights >= 0 (to be added, then clipped to [0, 1]).
    """
    if not 0.0 <= held_fraction <= 1.0 or not 0.0 <= start_strength <= 1.0:
        raise ValueError(f"held_fraction, start_strength: expected in [0, 1], found "
                         f"{held_fraction}, {start_strength}")
    index = _index(names)
    out = np.zeros((num_frames, len(names)), np.float64)
    t = np.arange(num_frames) / fps

    def add(families: Sequence[int], gains: np.ndarray, shape: np.ndarray) -> None:
        for fam, gain in zip(families, gains):
            for name in _FAMILIES[fam]:
                if name in index:
                    out[:, index[name]] += gain * shape

    if held_fraction > 0:
        start, duration = 0.0, num_frames / fps
        while start < duration:
            length = rng.uniform(1.0, 3.0)
            if rng.random() < held_fraction:
                picks = rng.choice(len(_FAMILIES), size=rng.integers(2, 5), replace=False)
                add(picks, rng.uniform(0.6, 1.0, len(picks)),
                    envelope(t, start, 0.2, max(length - 0.4, 0.0), 0.2))
            start += length
    if start_strength > 0:
        picks = rng.choice(len(_FAMILIES), size=3, replace=False)
        shape = np.where(t < 1.0, 1.0, smoothstep((1.5 - t) / 0.5))
        add(picks, np.full(3, start_strength), shape)
    return out.astype(np.float32)
