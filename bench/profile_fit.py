"""Where fit.RigidPose and fit.Expression spend their time: a table per part of the solve.

Synthetic plates as bench/fit.py's (the plates' own identity, read from a file, and one
fit.EstimateAppearance), then RigidPose and Expression with their parts timed: every call of
the parts below is wrapped (wall and process CPU seconds, calls, and the frames those calls
covered), so the numbers are exclusive of nothing: `fit_stages` contains all the others.

With --identity: bench/fit.py's "identity + appearance (once, per shot)" chain instead (fit.EstimateIdentity
with the default appearance, then twice fit.EstimateAppearance and fit.EstimateIdentity with the plates),
one table per node; --save then writes the identities and appearances (JSON) to compare two versions.

Usage: nice python bench/profile_fit.py [--frames 8] [--seed 0] [--cprofile 25] [--identity] [--save out.npz]
Prints, per node: seconds per frame, then one row per part (total seconds, calls, per call
ms, and per frame: how many times each frame went through it, e.g. renders per frame; the
calls cover all the frames of a batch at once). Times are of this machine as loaded now: report `uptime` beside them.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any, Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root: tests.support

from nodegraph import Camera, ImageSequence, run_node  # noqa: E402
from nodes.fit import EstimateAppearance, EstimateIdentity, Expression, RigidPose  # noqa: E402
from nodes.io.face_model import load_face_model  # noqa: E402
from nodes.landmarks import DetectFaces, FaceLandmarks  # noqa: E402
from tests.support.synthetic import random_face_parameters, render_truth_plates  # noqa: E402

TOTALS: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0, 0, 0])  # wall s, CPU s, calls, frames


def _frames_of(args: tuple, kwargs: dict, first: int) -> int:
    """How many frames (batch rows) one call covered: of the first batched argument from `first` on."""
    import torch

    for a in list(args)[first:] + list(kwargs.values()):
        if isinstance(a, torch.Tensor) and a.ndim >= 1:
            return int(a.shape[0])
        if hasattr(a, "seen"):
            return int(a.seen.shape[0])
        if hasattr(a, "rot"):
            return int(a.rot.shape[0])
    return 0


def _wrap(owner: Any, attr: str, name: str, iterations: bool = False, arg: int = 0) -> None:
    fn = getattr(owner, attr)

    def timed(*args: Any, **kwargs: Any) -> Any:
        w, c = time.perf_counter(), time.process_time()
        out = fn(*args, **kwargs)
        row = TOTALS[name]
        row[0] += time.perf_counter() - w
        row[1] += time.process_time() - c
        row[2] += 1
        row[3] += _frames_of(args, kwargs, arg)
        if iterations:
            it = TOTALS[name + ": iterations"]
            it[2] += out.iterations
        return out

    setattr(owner, attr, timed)


def instrument() -> None:
    from nodes.fit import photometric, solve, views

    _wrap(solve, "fit_stages", "fit_stages (all)")
    _wrap(solve, "_render_anchors", "render + read + anchor (one read)")
    _wrap(solve, "render_crops", "render_crops (render + crop)")
    _wrap(views, "render_mesh", "  render_mesh (rasterize + shade)")
    _wrap(solve, "network_points", "network read (face mesh)")
    _wrap(solve, "anchors_from_render", "anchors_from_render")
    _wrap(solve, "photometric_samples", "photometric_samples")
    _wrap(photometric, "gaussian_blur", "  blur (render and plate, per round)")
    _wrap(photometric, "at_anchors", "  model and shapes at the samples", arg=1)
    _wrap(solve, "_anchored", "basis at the anchors (_anchored)")
    _wrap(solve, "solve_stage", "solve_stage (one stage, all LM)")
    _wrap(solve, "levenberg_marquardt", "levenberg_marquardt", iterations=True)
    _wrap(solve, "_stage_jacobian", "landmark Jacobian (_stage_jacobian)")
    _wrap(photometric.PhotoTerm, "jacobian", "photometric Jacobian (PhotoTerm.jacobian)")
    _wrap(photometric.PhotoTerm, "about", "photometric term setup (PhotoTerm.about)")
    _wrap(photometric.PhotoTerm, "residuals", "photometric residuals")
    from nodes.fit import appearance, identity

    _wrap(identity, "solve_identity", "solve_identity (all)")
    _wrap(identity, "_identity_step", "_identity_step (one round, all LM)")
    _wrap(identity, "levenberg_marquardt", "levenberg_marquardt (identity)", iterations=True)
    _wrap(identity, "_render_anchors", "render + read + anchor (identity)")
    _wrap(identity, "_stage_jacobian", "landmark Jacobian (identity)")
    _wrap(appearance, "render_mesh", "render_mesh (appearance, plate size)")
    _wrap(appearance, "_pool", "albedo pooling (_pool)")


def table(title: str, frames: int, seconds: float, cpu: float) -> None:
    print(f"{title}: {seconds / frames:.3f} s / frame wall, {cpu / frames:.3f} s / frame process CPU ({frames} frames)")
    print(f"  {'part':44s} {'wall s':>8s} {'CPU s':>8s} {'calls':>6s} {'ms/call':>8s} {'per frame':>9s}")
    for name, (w, c, n, covered) in TOTALS.items():
        if name.endswith(": iterations"):
            continue
        extra = ""
        if name.startswith("levenberg_marquardt"):
            its = TOTALS[name + ": iterations"][2]
            extra = f"  ({its} LM iterations, {its / max(n, 1):.1f} per solve, {1e3 * w / max(its, 1):.1f} ms each)"
        print(f"  {name:44s} {w:8.3f} {c:8.3f} {n:6d} {1e3 * w / max(n, 1):8.1f} {covered / frames:9.2f}{extra}")
    TOTALS.clear()


def identity_chain(args: argparse.Namespace, model: Any, cam: Camera, seq: ImageSequence, det: dict) -> None:
    """bench/fit.py's "identity + appearance (once, per shot)": one table per node call; with
    --save, the identities and appearances (to compare two versions of the code)."""
    out = run_node(FaceLandmarks, images=seq, boxes=det["boxes"])
    marks, marks468 = out["landmarks68"], out["landmarks468"]
    f = args.frames
    views = dict(landmarks=[marks468], boxes=[det["boxes"]], cameras=[cam])
    app_in = dict(images=seq, landmarks=marks, boxes=det["boxes"], camera=cam)
    instrument()
    prof = cProfile.Profile() if args.cprofile else None
    saved: dict[str, Any] = {}
    total = time.perf_counter()

    def run(title: str, call: Callable[[], Any]) -> Any:
        w, c = time.perf_counter(), time.process_time()
        if prof:
            prof.enable()
        result = call()
        if prof:
            prof.disable()
        table(title, 1, time.perf_counter() - w, time.process_time() - c)
        if prof:
            pstats.Stats(prof).sort_stats("tottime").print_stats(args.cprofile)
            prof.clear()
        return result

    ident = run("fit.EstimateIdentity (first)", lambda: run_node(EstimateIdentity, {"frames_used": 4},
                                                                 frames=range(f), model=model, **views))
    saved["identity0"] = np.asarray(ident["identity"].value["identity"])
    for n in range(2):
        app = run(f"fit.EstimateAppearance ({n + 1})", lambda: run_node(EstimateAppearance, model=ident["fitted_model"],
                                                                       **app_in))
        saved[f"appearance{n + 1}"] = json.dumps(app["appearance"].value, sort_keys=True)
        ident = run(f"fit.EstimateIdentity ({n + 2})", lambda: run_node(
            EstimateIdentity, {"frames_used": 4}, frames=range(f), model=model, images=[seq],
            appearance=app["appearance"], **views))
        saved[f"identity{n + 1}"] = np.asarray(ident["identity"].value["identity"])
    print(f"identity + appearance (once, per shot): {time.perf_counter() - total:.2f} s")
    if args.save:
        np.savez(args.save, **saved)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cprofile", type=int, default=0, help="also print cProfile's top N functions by own time")
    ap.add_argument("--identity", action="store_true", help="profile bench/fit.py's identity + appearance chain "
                    "(EstimateIdentity, then twice EstimateAppearance and EstimateIdentity with the plates) instead of "
                    "RigidPose and Expression")
    ap.add_argument("--save", default="", help="NPZ of the outputs (rigid pose, expression fitted, energies), to "
                    "compare two versions of the code")
    args = ap.parse_args()
    model = load_face_model()
    cam = Camera.from_fov(args.size, args.size, 30.0)
    truth = random_face_parameters(model, args.frames, seed=args.seed, distance_cm=65.0)
    plates = render_truth_plates(model, [cam], truth, noise=0.005)[0]
    seq = ImageSequence(plates, colour_space="linear")
    det = run_node(DetectFaces, images=seq)
    marks = run_node(FaceLandmarks, images=seq, boxes=det["boxes"])["landmarks68"]
    if args.identity:
        identity_chain(args, model, cam, seq, det)
        return
    tmp = tempfile.mkdtemp()
    np.savez(f"{tmp}/identity.npz", identity=truth["identity"])
    f = args.frames
    ident = run_node(EstimateIdentity, {"mode": "file", "path": f"{tmp}/identity.npz"}, frames=range(f), model=model,
                     landmarks=[marks], boxes=[det["boxes"]], cameras=[cam])
    fitted = ident["fitted_model"]
    app = run_node(EstimateAppearance, images=seq, landmarks=marks, boxes=det["boxes"], camera=cam, model=fitted)
    common = dict(landmarks=[marks], boxes=[det["boxes"]], cameras=[cam], appearance=app["appearance"], images=[seq])
    instrument()
    prof = cProfile.Profile() if args.cprofile else None
    results: dict[str, Any] = {}

    def run(title: str, call: Callable[[], Any]) -> None:
        w, c = time.perf_counter(), time.process_time()
        if prof:
            prof.enable()
        results[title] = call()
        if prof:
            prof.disable()
        table(title, f, time.perf_counter() - w, time.process_time() - c)
        if prof:
            pstats.Stats(prof).sort_stats("tottime").print_stats(args.cprofile)
            prof.clear()

    run("fit.RigidPose", lambda: run_node(RigidPose, frames=range(f), model=fitted, **common))
    run("fit.Expression", lambda: run_node(Expression, frames=range(f), model=fitted,
                                           pose=results["fit.RigidPose"]["pose"], **common))
    if args.save:
        rigid, expr = results["fit.RigidPose"], results["fit.Expression"]
        np.savez(args.save, pose=rigid["pose"].values, rigid_energy=rigid["energy"].values,
                 fitted=expr["fitted"].values, energy=expr["energy"].values, truth_rotation=truth["rotation"],
                 truth_translation=truth["translation"], truth_weights=truth["weights"])


if __name__ == "__main__":
    main()
