"""Secondary dynamics: the paper's Fig. 5 protocol, resynthesis residual, training time, throughput.

Run: nice python bench/dynamics.py [--max-vertices 1500] [--epochs 20] [--rows 100000]
     nice python bench/dynamics.py --throughput   # removal speed on the 9,409-vertex face only
     nice python bench/dynamics.py --captures     # dynamics_train_captures.json on a day of capture
     nice python bench/dynamics.py --transfer     # synthesis H on identities it has not seen

Transfer of H (`--transfer`, 400-point face region): H trained on 2 or 6 identities (still, walk,
run, jump, 6/8/10/11 Hz platform; neutral, smile, jaw open, speech; 96 and 128 fps), then
resynthesis on the seen identity 1 and the unseen identities 9 and 12, and on identity 9 with
other tissue (stiffness x0.8 and x1.25, damping x0.6): residual RMS against the true dynamic
capture, as a percentage of doing nothing (adding no dynamics).

A day of capture (`--captures`): one identity (seed 21) on the 9,409-vertex face region in a
shuffled vertex order, six held expressions under walk, run, jump and the 8 Hz platform, 200
frames a take, the 96 fps takes with `rigid`, the 120 fps ones without (mode pursuit in the
graph); `graphs/dynamics_train_captures.json` with its defaults, then `dynamics_remove.json` on
a take of an unseen expression (frown) at an unseen frequency (10 Hz, 110 fps): RMS distance to
the true quasistatic face before and after, and the graph's time.

Removal throughput (`--throughput`, printed first in a full run): the bundled network on a
600-frame capture of the whole 9,409-vertex face region at 120 fps: `dynamics.RemoveDynamics`
on one 288-frame chunk (the graph's 256 frames + 16 frames of halo each side) with the
propagation matrix cold (first chunk of a process) and warm (every later chunk), per output
frame, and `graphs/dynamics_remove.json` end to end (NPZ in, NPZ out, the thread scheduler,
no cache), with the torch threads given.

Fig. 5 protocol (Zoss et al. 2020, section 5.3): the vibrating platform at 6, 7, 8, 9, 10 and
11 Hz, held expressions; removal network F trained on the k slowest frequencies (k = 1..5) and
tested on the fastest one (11 Hz, neutral expression, never seen in training). The test capture
is another identity (seed) at another frame rate (110 fps; training 96 and 128 fps). Printed per
setting: RMS distance to the true quasistatic sequence at the samples and over the whole face
(mm), the reduction against doing nothing (%), training time (s) and apply throughput of
`dynamics.RemoveDynamics` (frames/s, propagation included, one chunk).

Resynthesis: H trained on still/walk/run/jump/oscillation (9 Hz held out) with held expressions
and speech; tested on the 9 Hz platform and on a walk of another seed: residual RMS against the
true dynamic capture, as % of the true dynamic offset RMS.

CPU only (torch on the CPU; no GPU on this machine): times are for the 2-core machine shared
with other jobs, so treat them as upper bounds.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from nodegraph import run_node
from nodes.dynamics.evaluate import rms_distance
from nodes.dynamics.features import dynamic_offsets
from nodes.dynamics.removal import RemoveDynamics, TrainRemoval, predict_removal
from nodes.dynamics.synthesis import SynthesizeDynamics, TrainSynthesis
from nodes.io.face_model import load_face_model
from nodes.synth.dynamics import simulate_dynamics

FREQUENCIES = [6, 7, 8, 9, 10, 11]
HELD = ["neutral", "smile", "jaw_open", "pucker"]


def throughput(threads: int) -> None:
    """Print the removal speed on the 9,409-vertex face (see the module docstring)."""
    import tempfile
    from pathlib import Path

    import torch

    from nodegraph import runner
    from nodes.dynamics.files import LoadModel

    torch.set_num_threads(threads)
    face = load_face_model(region="face")
    test = simulate_dynamics(face, motions=["run"], expressions=["neutral"], segment_frames=600, fps=120.0,
                             seed=11)
    model = run_node(LoadModel, {})["model"]
    chunk = test.capture.slice_frames(0, 288)
    skull = test.skull.slice_frames(0, 288)
    times = []
    for _ in range(3):
        start = time.perf_counter()
        run_node(RemoveDynamics, {}, capture=chunk, skull=skull, model=model)
        times.append(time.perf_counter() - start)
    print(f"removal on {face.neutral.shape[0]} vertices, {threads} torch threads: one 288-frame chunk "
          f"{times[0]:.2f} s cold (propagation matrix built), {min(times[1:]):.2f} s warm "
          f"({256 / min(times[1:]):.0f} output frames/s)")
    with tempfile.TemporaryDirectory() as folder:
        capture, out = Path(folder) / "capture.npz", Path(folder) / "out.npz"
        np.savez(capture, vertices=test.capture.vertices, faces=test.capture.faces, fps=120.0,
                 rigid=test.skull.matrices)
        start = time.perf_counter()
        result = runner.run(Path(__file__).resolve().parents[1] / "graphs" / "dynamics_remove.json",
                            cache=False, parameters={"capture": str(capture), "skull": str(capture),
                                                     "model": "", "output": str(out)})
        seconds = time.perf_counter() - start
        assert result.exit_code == 0, result.summary()
        with np.load(out) as saved:
            after = rms_distance(saved["vertices"], test.quasistatic.vertices)
    before = rms_distance(test.capture.vertices, test.quasistatic.vertices)
    print(f"dynamics_remove.json, {test.capture.num_frames} frames: {seconds:.1f} s end to end "
          f"({test.capture.num_frames / seconds:.0f} frames/s); RMS {10 * before:.3f} -> {10 * after:.3f} mm")


def captures(args: argparse.Namespace) -> None:
    """Print the day-of-capture figures (see the module docstring)."""
    import json
    import tempfile
    from pathlib import Path

    from nodegraph import runner

    graphs = Path(__file__).resolve().parents[1] / "graphs"
    face = load_face_model(region="face")
    order = np.random.default_rng(21).permutation(len(face.neutral))
    faces = np.argsort(order)[face.faces].astype(np.int32)
    motions = ["walk", "run", "jump", "oscillate@8"]
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        (root / "takes").mkdir()
        for fps, expressions, rigid in ((96.0, ["neutral", "smile", "jaw_open"], True),
                                        (120.0, ["pucker", "brow_raise", "sneer"], False)):
            data = simulate_dynamics(face, motions=motions, expressions=expressions, segment_frames=200,
                                     fps=fps, seed=21)
            for k, (expression, motion) in enumerate((e, m) for e in expressions for m in motions):
                cut = slice(200 * k, 200 * (k + 1))
                arrays = {"vertices": data.capture.vertices[cut][:, order], "faces": faces, "fps": fps}
                if rigid:
                    arrays["rigid"] = data.skull.matrices[cut]
                np.savez(root / "takes" / f"take_{expression}_{motion.replace('@', '')}.npz", **arrays)
        np.savez(root / "neutral.npz", vertices=data.neutral.vertices[:, order], faces=faces)
        start = time.perf_counter()
        result = runner.run(graphs / "dynamics_train_captures.json", cache=root / "cache",
                            parameters={"captures": str(root / "takes" / "take_*.npz"),
                                        "neutral": str(root / "neutral.npz"), "model": str(root / "f.safetensors"),
                                        "synthesis_model": str(root / "h.safetensors"),
                                        "report": str(root / "report.json")})
        train_s = time.perf_counter() - start
        assert result.exit_code == 0, result.summary()
        both = json.loads((root / "report.json").read_text())
        report, synthesis = both["removal"], both["synthesis"]
        print(f"dynamics_train_captures.json: 24 takes ({report['frames']} training frames, 12 without rigid), "
              f"{train_s:.0f} s (F {report['seconds']:.0f} s, H {synthesis['seconds']:.0f} s of training); F loss "
              f"{report['loss_per_epoch'][0]:.4f} -> {report['final_loss']:.4f}, H loss "
              f"{synthesis['loss_per_epoch'][0]:.4f} -> {synthesis['final_loss']:.4f}; held-out take "
              f"{report['held_out']['take']}: {report['held_out']['rms_before_mm']} -> "
              f"{report['held_out']['rms_after_mm']} mm to its moving average")
        test = simulate_dynamics(face, motions=["oscillate@10"], expressions=["frown"], segment_frames=300,
                                 fps=110.0, seed=21)
        np.savez(root / "test.npz", vertices=test.capture.vertices[:, order], faces=faces, fps=110.0,
                 rigid=test.skull.matrices)
        result = runner.run(graphs / "dynamics_remove.json", cache=False,
                            parameters={"capture": str(root / "test.npz"), "skull": str(root / "test.npz"),
                                        "model": str(root / "f.safetensors"), "output": str(root / "q.npz")})
        assert result.exit_code == 0, result.summary()
        with np.load(root / "q.npz") as saved:
            removed = saved["vertices"]
    truth = test.quasistatic.vertices[:, order]
    before, after = rms_distance(test.capture.vertices[:, order], truth), rms_distance(removed, truth)
    print(f"  unseen frown at 10 Hz, 110 fps: RMS to the true quasistatic face {10 * before:.3f} -> "
          f"{10 * after:.3f} mm ({100 * (1 - after / before):.1f}% removed)")


def transfer() -> None:
    """Print how H transfers to identities and tissue it has not seen (see the module docstring)."""
    face = load_face_model(region="face", max_vertices=400)
    motions = ["still", "walk", "run", "jump", "oscillate@6", "oscillate@8", "oscillate@10", "oscillate@11"]
    tests = [("seen identity 1, 9 Hz, smile", 1, {}), ("unseen identity 9, 9 Hz, smile", 9, {}),
             ("unseen identity 12, 9 Hz, smile", 12, {}),
             ("identity 9, stiffness x0.8", 9, {"stiffness_scale": 0.8}),
             ("identity 9, stiffness x1.25", 9, {"stiffness_scale": 1.25}),
             ("identity 9, damping x0.6", 9, {"damping_scale": 0.6})]
    held = {name: simulate_dynamics(face, motions=["oscillate@9"], expressions=["smile"], segment_frames=220,
                                    fps=100.0, seed=seed, **kw) for name, seed, kw in tests}
    for ids in ([1, 2], [1, 2, 3, 4, 5, 6]):
        parts = [simulate_dynamics(face, motions=motions, expressions=["neutral", "smile", "jaw_open", "speech"],
                                   segment_frames=120, fps=96.0 if i % 2 else 128.0, seed=seed)
                 for i, seed in enumerate(ids)]
        h = run_node(TrainSynthesis, {"num_samples": 100, "epochs": 15, "batch_size": 100, "seed": 0},
                     frames=range(parts[0].capture.num_frames), captures=[p.capture for p in parts],
                     quasistatic=[p.quasistatic for p in parts], skulls=[p.skull for p in parts],
                     neutral=[p.neutral for p in parts], segments=[p.segments for p in parts])["model"]
        print(f"H trained on identities {ids}:")
        for name, test in held.items():
            syn = run_node(SynthesizeDynamics, {}, quasistatic=test.quasistatic, skull=test.skull,
                           neutral=test.neutral, model=h)["capture"]
            nothing = rms_distance(test.capture.vertices, test.quasistatic.vertices)
            residual = rms_distance(syn.vertices, test.capture.vertices)
            print(f"  {name}: no dynamics {10 * nothing:.3f} mm, H {10 * residual:.3f} mm "
                  f"({100 * residual / nothing:.0f} % of nothing)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--max-vertices", type=int, default=1500, help="face region subsample (0 = all 9,409)")
    parser.add_argument("--samples", type=int, default=344)
    parser.add_argument("--epochs", type=int, default=20)
    parser.add_argument("--rows", type=int, default=100000)
    parser.add_argument("--segment-frames", type=int, default=128)
    parser.add_argument("--synthesis-epochs", type=int, default=30)
    parser.add_argument("--throughput", action="store_true", help="only the removal speed on the whole face")
    parser.add_argument("--threads", type=int, default=2, help="torch threads for the throughput")
    parser.add_argument("--captures", action="store_true", help="only the day-of-capture training")
    parser.add_argument("--transfer", action="store_true", help="only H on unseen identities")
    args = parser.parse_args()
    if args.captures:
        captures(args)
        return
    if args.transfer:
        transfer()
        return
    throughput(args.threads)
    if args.throughput:
        return
    print()
    face = load_face_model(region="face", max_vertices=args.max_vertices)
    v = face.neutral.shape[0]
    print(f"face region: {v} vertices; {args.samples} samples; F: {args.rows} rows x {args.epochs} "
          f"epochs, batch 10,000, Adam 1e-3; CPU only (no GPU)")
    test = simulate_dynamics(face, motions=["oscillate@11"], expressions=["neutral"], segment_frames=220,
                             fps=110.0, seed=9)
    base = rms_distance(test.capture.vertices, test.quasistatic.vertices)
    print(f"test: 11 Hz, neutral, seed 9, 110 fps, {test.capture.num_frames} frames; doing nothing: "
          f"{10 * base:.3f} mm RMS over the face")
    print()
    print("trained on     | rows   | train s | samples mm | face mm | reduction | apply frames/s")
    print("---------------|--------|---------|------------|---------|-----------|---------------")
    for k in range(1, 6):
        programs = [f"oscillate@{f}" for f in FREQUENCIES[:k]]
        parts = [simulate_dynamics(face, motions=programs, expressions=HELD, segment_frames=args.segment_frames,
                                   fps=fps, seed=seed) for fps, seed in ((96.0, 1), (128.0, 2))]
        start = time.perf_counter()
        out = run_node(TrainRemoval, {"num_samples": args.samples, "epochs": args.epochs, "max_rows": args.rows},
                       frames=range(parts[0].capture.num_frames),
                       captures=[p.capture for p in parts], skulls=[p.skull for p in parts],
                       quasistatic=[p.quasistatic for p in parts], segments=[p.segments for p in parts])
        train_s = time.perf_counter() - start
        model = out["model"]
        ids = model.normalization["sample_ids"]
        pred = predict_removal(model, test.capture.vertices, test.skull.matrices, 110.0)
        true = dynamic_offsets(test.capture.vertices[:, ids], test.quasistatic.vertices[:, ids], test.skull.matrices)
        sample_err = float(np.sqrt(((pred - true) ** 2).sum(-1).mean()))
        start = time.perf_counter()
        removed = run_node(RemoveDynamics, {}, capture=test.capture, skull=test.skull, model=model)
        apply_s = time.perf_counter() - start
        face_err = rms_distance(removed["quasistatic"].vertices, test.quasistatic.vertices)
        label = ",".join(str(f) for f in FREQUENCIES[:k]) + " Hz"
        print(f"{label:<14} | {out['report'].value['rows']:>6} | {train_s:7.1f} | {10 * sample_err:10.3f} | "
              f"{10 * face_err:7.3f} | {100 * (1 - face_err / base):8.1f}% | {test.capture.num_frames / apply_s:13.1f}")

    print()
    corpus = simulate_dynamics(face, motions=["still", "walk", "run", "jump", "oscillate@6", "oscillate@8",
                                              "oscillate@10", "oscillate@11"],
                               expressions=["neutral", "smile", "jaw_open", "speech"],
                               segment_frames=args.segment_frames, fps=120.0, seed=1)
    start = time.perf_counter()
    h = run_node(TrainSynthesis, {"num_samples": args.samples, "epochs": args.synthesis_epochs},
                 frames=range(corpus.capture.num_frames), captures=[corpus.capture],
                 quasistatic=[corpus.quasistatic], skulls=[corpus.skull], neutral=[corpus.neutral],
                 segments=[corpus.segments])
    train_s = time.perf_counter() - start
    print(f"synthesis H: {h['report'].value['rows']} frames x {args.synthesis_epochs} epochs, batch 50: "
          f"{train_s:.1f} s")
    for name, kwargs in (("9 Hz platform, smile, 100 fps", dict(motions=["oscillate@9"], expressions=["smile"],
                                                                 fps=100.0, seed=1)),
                         ("walk, speech, 110 fps", dict(motions=["walk"], expressions=["speech"], fps=110.0,
                                                        seed=1))):
        held = simulate_dynamics(face, segment_frames=220, **kwargs)
        start = time.perf_counter()
        syn = run_node(SynthesizeDynamics, {}, quasistatic=held.quasistatic, skull=held.skull,
                       neutral=held.neutral, model=h["model"])
        apply_s = time.perf_counter() - start
        dyn = rms_distance(held.capture.vertices, held.quasistatic.vertices)
        res = rms_distance(syn["capture"].vertices, held.capture.vertices)
        print(f"  resynthesis on {name}: dynamic RMS {10 * dyn:.3f} mm, residual {10 * res:.3f} mm "
              f"({100 * res / dyn:.1f} %), {held.capture.num_frames / apply_s:.1f} frames/s")


if __name__ == "__main__":
    main()
