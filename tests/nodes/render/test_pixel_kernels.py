"""The renderer's compiled CPU path (numba forward and hand-written backward,
`nodes.render.pixel_kernels`) against its torch-ops path (autograd), float64 gradcheck, and the
pruned silhouette walk against the unpruned one."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("numba")

from nodes.geometry.mesh import triangle_adjacency  # noqa: E402
from nodes.render import pixel_kernels, raster, renderer  # noqa: E402
from nodes.render.renderer import render_mesh, shade_pixels, sh_from_lights, vertex_normals  # noqa: E402


def _bumpy_sphere(rng: np.random.Generator, batch: int = 1, dtype=torch.float64):
    """A bumpy icosphere (642 vertices, radius ~5 cm) 40 cm in front of a 48^2 pinhole camera."""
    import trimesh

    sphere = trimesh.creation.icosphere(3, radius=5.0)
    verts = np.asarray(sphere.vertices) * (1 + 0.05 * rng.standard_normal((batch, len(sphere.vertices), 1)))
    verts = verts + np.array([0.7, -0.4, 40.0]) + rng.normal(0, 0.5, (batch, 1, 3))
    faces = np.asarray(sphere.faces, np.int64)
    e = torch.eye(4, dtype=dtype)[None].expand(batch, 4, 4)
    k = torch.tensor([[150.0, 150.0, 23.5, 23.5]], dtype=dtype).expand(batch, 4)
    return torch.as_tensor(verts, dtype=dtype), faces, e, k


def _render_both(verts, faces, e, k, albedo, sh, **kwargs):
    """render_mesh with the compiled kernels and with torch ops: outputs and gradients of a
    loss on the image, depth and barycentrics w.r.t. vertices, albedo and sh."""
    results = []
    for compiled in (True, False):
        leaves = [t.clone().requires_grad_() for t in (verts, albedo, sh)]
        out = render_mesh(leaves[0], faces, e, k, 48, 48, albedo=leaves[1], sh=leaves[2], compiled=compiled,
                          **kwargs)
        g = torch.Generator().manual_seed(3)
        w = torch.randn(out.image.shape, generator=g, dtype=verts.dtype)
        loss = (out.image * w).sum() + 0.1 * out.depth.sum() + (out.barycentrics * w).sum() + out.alpha.sum()
        loss.backward()
        results.append((out.image.detach(), out.alpha.detach(), out.depth.detach(), out.barycentrics.detach(),
                        out.triangle) + tuple(t.grad for t in leaves))
    return results


@pytest.mark.parametrize("dtype, rtol", [(torch.float64, 1e-10), (torch.float32, 2e-4)])
def test_compiled_render_matches_the_torch_path_values_and_gradients(rng, dtype, rtol):
    # float64: both paths do the same arithmetic in a different order (rounding ~1e-16 of values
    # of order 1-100, summed over at most a few hundred pixels per vertex); float32: the kernels keep
    # scalar temporaries in float64, torch rounds each op to float32 (~6e-8 relative per op, over
    # ~40 ops and sums of up to ~10^3 terms)
    verts, faces, e, k = _bumpy_sphere(rng, 2, dtype)
    albedo = torch.as_tensor(rng.uniform(0.2, 1, (2, verts.shape[1], 3)), dtype=dtype)  # per image
    sh = torch.stack([torch.as_tensor(sh_from_lights(0.4, (0.3, -0.5, -1.0), 0.8)),
                      torch.as_tensor(sh_from_lights(0.6, (-0.2, 0.4, -1.0), 0.5))]).to(dtype)
    compiled, plain = _render_both(verts, faces, e, k, albedo, sh, background=(0.2, 0.3, 0.1), supersample=2,
                                   adjacency=triangle_adjacency(faces))
    assert (compiled[4] >= 0).float().mean() > 0.2
    np.testing.assert_array_equal(compiled[4].numpy(), plain[4].numpy())
    for name, a, b in zip(["image", "alpha", "depth", "barycentrics", "triangle", "d vertices", "d albedo",
                           "d sh"], compiled, plain):
        scale = b.abs().max().item()
        assert scale > 0, name
        np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=0, atol=rtol * scale, err_msg=name)


def test_compiled_render_with_one_albedo_and_sh_for_the_batch(rng):
    verts, faces, e, k = _bumpy_sphere(rng, 2)
    albedo = torch.as_tensor(rng.uniform(0.2, 1, (1, verts.shape[1], 3)))
    sh = torch.as_tensor(sh_from_lights(0.4, (0.3, -0.5, -1.0), 0.8), dtype=torch.float64)[None]
    compiled, plain = _render_both(verts, faces, e, k, albedo, sh)
    for a, b in zip(compiled, plain):
        np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=0, atol=1e-10 * b.abs().max().item())


def test_compiled_shading_passes_gradcheck(rng):
    # a few pixels of a two-image batch, gradients w.r.t. all five differentiable inputs
    verts, faces, e, k = _bumpy_sphere(rng, 2)
    pix = renderer.project_points_torch(verts, e, k)
    depth = verts[..., 2].clone()
    tri, _ = raster.rasterize_triangles(pix.numpy(), depth.numpy(), faces, 48, 48)
    covered = np.flatnonzero(tri.reshape(-1) >= 0)
    pixels = torch.as_tensor(np.sort(rng.choice(covered, 12, replace=False)))
    corners = torch.as_tensor(faces[tri.reshape(-1)[pixels.numpy()]])
    normals = vertex_normals(verts, torch.as_tensor(faces))
    albedo = torch.as_tensor(rng.uniform(0.2, 1, (2, verts.shape[1], 3)))
    sh = torch.as_tensor(rng.normal(0, 1, (2, 9, 3)))
    leaves = tuple(t.clone().requires_grad_() for t in (pix, depth, normals, albedo, sh))

    def shade(*args):
        return shade_pixels(*args, pixels, corners, 48, 48, compiled=True)

    assert torch.autograd.gradcheck(shade, leaves)


def test_compiled_vertex_normals_match_and_pass_gradcheck(rng):
    verts, faces, _, _ = _bumpy_sphere(rng, 2)
    faces_t = torch.as_tensor(faces)
    weights = torch.as_tensor(rng.normal(size=verts.shape))
    grads = []
    for compiled in (True, False):
        x = verts.clone().requires_grad_()
        normals = vertex_normals(x, faces_t, compiled=compiled)
        (normals * weights).sum().backward()
        grads.append((normals.detach(), x.grad))
    np.testing.assert_allclose(grads[0][0].numpy(), grads[1][0].numpy(), atol=1e-12)
    np.testing.assert_allclose(grads[0][1].numpy(), grads[1][1].numpy(), atol=1e-10)
    import trimesh

    sphere = trimesh.creation.icosphere(1, radius=2.0)
    small = torch.as_tensor(np.asarray(sphere.vertices)[None] * rng.uniform(0.8, 1.2, (1, 42, 3))).requires_grad_()
    small_faces = torch.as_tensor(np.asarray(sphere.faces, np.int64))
    assert torch.autograd.gradcheck(lambda v: vertex_normals(v, small_faces, compiled=True), (small,))


def test_compiled_path_refuses_cuda_tensors_only_when_asked():
    if torch.cuda.is_available():
        with pytest.raises(ValueError, match="compiled: the numba kernels run on the CPU only"):
            vertex_normals(torch.zeros(1, 3, 3, device="cuda"), torch.tensor([[0, 1, 2]]), compiled=True)
    with pytest.raises(ValueError, match="compiled: the numba kernels run on the CPU only"):
        renderer._compiled(torch.device("meta"), torch.float32, True)


def test_pruned_silhouette_walk_finds_the_same_pairs(rng):
    # the walk is skipped from triangles farther than WALK_STEPS - 1 steps from any silhouette edge
    # (PRUNE_DISTANCE) or for pairs no silhouette edge passes within EDGE_MARGIN of (PRUNE_MASK);
    # on renders of bumpy spheres at two sizes the pairs must not change
    verts, faces, e, k = _bumpy_sphere(rng, 3)
    adjacency = triangle_adjacency(faces)
    cases = []
    for size in (48, 160):
        kk = k.clone()
        kk[:, :2] *= size / 48
        kk[:, 2:] = (size - 1) / 2
        pix = renderer.project_points_torch(verts, e, kk).numpy()
        tri, zbuf = raster.rasterize_triangles(pix, verts[..., 2].numpy(), faces, size, size)
        cases.append((tri, zbuf, pix))
    found = 0
    for tri, zbuf, pix in cases:
        outs = []
        for prune in (raster.PRUNE_NONE, raster.PRUNE_DISTANCE, raster.PRUNE_MASK):
            outs.append(raster._find_pairs(tri.astype(np.int64), zbuf, np.ascontiguousarray(pix, np.float64), faces,
                                           adjacency, raster.WALK_STEPS, prune))
        for other in outs[1:]:
            for a, b in zip(outs[0], other):
                np.testing.assert_array_equal(a, b)
        found += len(outs[0][0])
    assert found > 100


def test_masked_silhouette_walk_on_the_head_finds_the_same_pairs():
    # the pair masks against the unpruned walk on the ICT head: turned 0 to 170 degrees, 64^2 to
    # 512^2, one image and a batch of two (the masks per image inside the kernel); and an image
    # whose mesh has a silhouette edge too short for the masks' margin falls back (same pairs)
    from scipy.spatial.transform import Rotation

    from nodes.io.face_model import load_face_model
    from nodes.render.appearance import visible_faces

    model = load_face_model()
    faces = np.ascontiguousarray(visible_faces(model.faces, model.neutral.shape[0]), np.int64)
    adjacency = triangle_adjacency(faces)
    e = np.array([[1.0, 0, 0, 0], [0, -1, 0, 1.0], [0, 0, -1, 55.0], [0, 0, 0, 1]], np.float32)
    found = 0
    for size in (64, 512):
        k = np.array([520.0 * size / 256, 520.0 * size / 256, (size - 1) / 2, (size - 1) / 2], np.float32)
        views = []
        for yaw, pitch in ((0, 0), (35, -10), (-60, 15), (170, 20)):
            rot = Rotation.from_euler("yx", [yaw, pitch], degrees=True).as_matrix()
            v = (model.neutral @ rot.T).astype(np.float32)
            pix, depth = pixel_kernels.project_forward(v[None], e[None], k[None], None)
            views.append((pix, depth))
        pix = np.concatenate([p for p, _ in views]).astype(np.float64)
        depth = np.concatenate([d for _, d in views])
        tri, zbuf = raster.rasterize_triangles(pix, depth, faces, size, size, triangle_dtype=np.int64)
        for b in range(len(views)):
            args = (tri[b:b + 1], zbuf[b:b + 1], pix[b:b + 1], faces, adjacency, raster.WALK_STEPS)
            ref = raster._find_pairs(*args, raster.PRUNE_NONE)
            for a, c in zip(ref, raster._find_pairs(*args, raster.PRUNE_MASK)):
                np.testing.assert_array_equal(a, c)
            found += len(ref[0])
        args = (tri[:2], zbuf[:2], pix[:2], faces, adjacency, raster.WALK_STEPS)
        for a, c in zip(raster._find_pairs(*args, raster.PRUNE_NONE), raster._find_pairs(*args, raster.PRUNE_MASK)):
            np.testing.assert_array_equal(a, c)
    assert found > 1000
    # a silhouette edge 1e-12 px long: the masks cannot bound the walk's rounding there
    facing = np.zeros(len(faces), np.bool_)
    masks = np.zeros((64, 64), np.bool_), np.zeros((64, 64), np.bool_)
    short = pix[:1].copy()
    t = int(np.flatnonzero(adjacency.min(1) < 0)[0])  # a triangle on the mesh's open border
    edge = int(np.flatnonzero(adjacency[t] < 0)[0])
    k1, k2 = faces[t, (edge + 1) % 3], faces[t, (edge + 2) % 3]
    short[0, k2] = short[0, k1] + 1e-12
    mode = raster._walk_kernel(short, 0, faces, adjacency, raster.WALK_STEPS, raster.PRUNE_MASK,
                               np.zeros(1, np.int64), np.zeros(0, np.int64), facing, np.zeros(0, np.int64), *masks)
    assert mode == raster.PRUNE_NONE


def test_compiled_projection_and_background_match_the_torch_path(rng):
    # the compiled projection (distortion included) and compositing against torch ops: values and
    # gradients w.r.t. the camera, the intrinsics, the distortion and a per-image background image
    verts, faces, e, k = _bumpy_sphere(rng, 2)
    e = e.clone()
    from scipy.spatial.transform import Rotation

    e[:, :3, :3] = torch.as_tensor(Rotation.from_rotvec(np.radians([[2.0, -1.0, 10.0], [-1.5, 2.0, -20.0]])).as_matrix())
    e[1, 0, 3] = 0.3
    dist = torch.tensor([[-0.08, 0.02], [0.05, -0.01]], dtype=torch.float64)
    background = torch.as_tensor(rng.uniform(0, 1, (2, 48, 48, 3)))
    results = []
    for compiled in (True, False):
        leaves = [t.clone().requires_grad_() for t in (verts, e, k, dist, background)]
        out = render_mesh(leaves[0], faces, leaves[1], leaves[2], 48, 48, albedo=torch.full((1, verts.shape[1], 3), 0.7,
                          dtype=torch.float64), sh=torch.as_tensor(sh_from_lights(0.4, (0.3, -0.5, -1.0), 0.8),
                                                                   dtype=torch.float64)[None],
                          background=leaves[4], distortion=leaves[3], compiled=compiled)
        w = torch.randn(out.image.shape, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
        ((out.image * w).sum() + out.depth.sum() + out.alpha.sum()).backward()
        results.append((out.image.detach(), out.depth.detach(), out.triangle) + tuple(t.grad for t in leaves))
    np.testing.assert_array_equal(results[0][2].numpy(), results[1][2].numpy())
    for name, a, b in zip(["image", "depth", "triangle", "d vertices", "d camera", "d intrinsics", "d distortion",
                           "d background"], *results):
        scale = b.abs().max().item()
        assert scale > 0, name
        np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=0, atol=1e-10 * scale, err_msg=name)


def test_compiled_projection_passes_gradcheck(rng):
    verts, _, e, k = _bumpy_sphere(rng, 2)
    small = verts[:, :20].clone()
    e = e.clone()
    e[:, :3, 3] = torch.tensor([0.2, -0.1, 1.0], dtype=torch.float64)
    leaves = tuple(t.clone().requires_grad_() for t in (small, e, k, torch.tensor([[-0.08, 0.02], [0.05, -0.01]],
                                                                                  dtype=torch.float64)))
    assert torch.autograd.gradcheck(lambda *a: renderer._CompiledProjection.apply(*a), leaves)
    assert torch.autograd.gradcheck(lambda *a: renderer._CompiledProjection.apply(*a, None), leaves[:3])


def test_two_threads_give_the_same_bits_as_one(rng, monkeypatch):
    # the kernels' fixed halves run side by side with 2+ torch threads and one after the other
    # with 1: images, buffers and gradients must be identical, float32 and float64, batch 1 and 2
    from nodes.render import halves

    monkeypatch.setattr(halves, "MIN_PARALLEL_WORK", 0)
    before = torch.get_num_threads()
    for batch, dtype, supersample in ((1, torch.float32, 2), (2, torch.float64, 2), (1, torch.float32, 1)):
        verts, faces, e, k = _bumpy_sphere(rng, batch, dtype)
        albedo = torch.as_tensor(rng.uniform(0.2, 1, (1, verts.shape[1], 3)), dtype=dtype)
        sh = torch.as_tensor(sh_from_lights(0.4, (0.3, -0.5, -1.0), 0.8), dtype=dtype)[None]
        runs = []
        try:
            for threads in (1, 2):  # 1: the raster in one pass; 2: two bands of rows side by side
                torch.set_num_threads(threads)
                runs.append(_render_both(verts, faces, e, k, albedo, sh, supersample=supersample,
                                         adjacency=triangle_adjacency(faces))[0])
        finally:
            torch.set_num_threads(before)
        for a, b in zip(*runs):
            assert torch.equal(a, b)


def _raster_reference(pix: np.ndarray, depth: np.ndarray, faces: np.ndarray, height: int, width: int,
                      near: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """The z-buffer without any early rejection, in numpy (the kernel's per-pixel arithmetic)."""
    tri = np.full((height, width), -1, np.int32)
    zbuf = np.full((height, width), np.inf)
    for t, (i0, i1, i2) in enumerate(faces):
        (x0, y0), (x1, y1), (x2, y2) = pix[i0], pix[i1], pix[i2]
        z0, z1, z2 = depth[i0], depth[i1], depth[i2]
        xa, xb, ya, yb = min(x0, x1, x2), max(x0, x1, x2), min(y0, y1, y2), max(y0, y1, y2)
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if not (z0 > near and z1 > near and z2 > near and area != 0.0 and np.isfinite(area)):
            continue
        xs = np.arange(max(int(np.ceil(xa)), 0), min(int(np.floor(xb)), width - 1) + 1, dtype=np.float64)
        ys = np.arange(max(int(np.ceil(ya)), 0), min(int(np.floor(yb)), height - 1) + 1, dtype=np.float64)
        if not (len(xs) and len(ys)):
            continue
        px, py = np.meshgrid(xs, ys)
        inv = 1.0 / area
        w0 = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) * inv
        w1 = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) * inv
        w2 = 1.0 - w0 - w1
        with np.errstate(divide="ignore"):
            z = 1.0 / (w0 * (1.0 / z0) + w1 * (1.0 / z1) + w2 * (1.0 / z2))
        iy, ix = py.astype(int), px.astype(int)
        win = (w0 >= 0) & (w1 >= 0) & (w2 >= 0) & (z < zbuf[iy, ix])
        zbuf[iy[win], ix[win]] = z[win]
        tri[iy[win], ix[win]] = t
    return tri, zbuf


def test_rasterizer_matches_a_plain_z_buffer(rng):
    # the kernel skips a pixel already showing something nearer than the triangle's nearest corner;
    # the buffers must be those of the plain z-buffer, also where triangles tie in depth (a flat
    # grid parallel to the image, drawn twice: the first drawn keeps the pixel) and overlap
    verts, faces, e, k = _bumpy_sphere(rng, 1)
    pix = renderer.project_points_torch(verts, e, k)[0].numpy()
    depth = verts[0, :, 2].numpy()
    n = 9
    gx, gy = np.meshgrid(np.linspace(2.3, 45.1, n), np.linspace(1.7, 44.9, n))
    grid_pix = np.stack([gx.ravel(), gy.ravel()], -1)
    cells = np.array([[r * n + c, r * n + c + 1, (r + 1) * n + c] for r in range(n - 1) for c in range(n - 1)] +
                     [[r * n + c + 1, (r + 1) * n + c + 1, (r + 1) * n + c] for r in range(n - 1) for c in range(n - 1)])
    all_pix = np.concatenate([pix, grid_pix])
    all_depth = np.concatenate([depth, np.full(n * n, 38.0)])
    all_faces = np.concatenate([faces, cells + len(pix), cells + len(pix)])
    tri, zbuf = raster.rasterize_triangles(all_pix[None], all_depth[None], all_faces, 48, 48)
    ref_tri, ref_z = _raster_reference(all_pix, all_depth, all_faces, 48, 48)
    np.testing.assert_array_equal(tri[0], ref_tri)
    np.testing.assert_array_equal(zbuf[0], ref_z)
    assert (tri[0] >= len(faces)).sum() > 200 and (tri[0][tri[0] >= 0] < len(faces)).sum() > 200


@pytest.mark.parametrize("loss_on", ["image", "alpha", "geometry"])
def test_compiled_render_gradients_of_one_output_at_a_time(rng, loss_on):
    # a loss on the colour, the coverage or the geometry alone (the compiled image node then gets
    # no gradient for the others) must match the torch path
    verts, faces, e, k = _bumpy_sphere(rng, 2)
    albedo = torch.as_tensor(rng.uniform(0.2, 1, (1, verts.shape[1], 3)))
    sh = torch.as_tensor(sh_from_lights(0.4, (0.3, -0.5, -1.0), 0.8), dtype=torch.float64)[None]
    grads = []
    for compiled in (True, False):
        leaves = [t.clone().requires_grad_() for t in (verts, albedo, sh)]
        bg = torch.full((1, 48, 48, 3), 0.3, dtype=torch.float64, requires_grad=True)
        out = render_mesh(leaves[0], faces, e, k, 48, 48, albedo=leaves[1], sh=leaves[2], background=bg,
                          adjacency=triangle_adjacency(faces), compiled=compiled)
        g = torch.Generator().manual_seed(5)
        if loss_on == "image":
            loss = (out.image * torch.randn(out.image.shape, generator=g, dtype=torch.float64)).sum()
        elif loss_on == "alpha":
            loss = (out.alpha * torch.randn(out.alpha.shape, generator=g, dtype=torch.float64)).sum()
        else:
            loss = out.depth.sum() + out.barycentrics[..., 0].sum()
        loss.backward()
        grads.append([t.grad for t in leaves] + [bg.grad])
    for name, a, b in zip(["vertices", "albedo", "sh", "background"], *grads):
        if b is None or not b.abs().max() > 0:  # no path from this loss (the torch path may give zeros)
            assert a is None or not a.abs().max() > 0, name
            continue
        np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=0, atol=1e-10 * b.abs().max().item(), err_msg=name)


def test_covered_pixels_match_numpy(rng):
    verts, faces, e, k = _bumpy_sphere(rng, 2)
    pix = verts[..., :2] / verts[..., 2:] * 150.0 + 23.5
    tri, _ = raster.rasterize_triangles(pix.numpy(), verts[..., 2].numpy(), faces, 48, 48,
                                        triangle_dtype=np.int64)
    assert tri.dtype == np.int64 and (tri >= 0).any() and (tri < 0).any()
    pixels, corners = raster.covered_pixels(tri, faces)
    expected = np.flatnonzero(tri.reshape(-1) >= 0)
    np.testing.assert_array_equal(pixels, expected)
    np.testing.assert_array_equal(corners, faces[tri.reshape(-1)[expected]])
