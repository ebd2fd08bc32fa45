"""Renderer: rasterization against brute force, areas against closed forms, gradients against
finite differences, CPU against CUDA."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("numba")

from nodes.render.raster import rasterize_triangles, silhouette_pairs  # noqa: E402
from nodes.geometry.mesh import triangle_adjacency  # noqa: E402
from nodes.render.renderer import (render_mesh, screen_barycentrics, sh_basis, sh_from_lights,  # noqa: E402
                                   vertex_normals)


def _icosphere(subdivisions: int, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices on a sphere (cm) and outward-wound faces (counter-clockwise seen from outside)."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions, radius=radius)
    return np.asarray(sphere.vertices, np.float64), np.asarray(sphere.faces, np.int64)


def _pinhole(width: int, height: int, focal: float, dtype=torch.float64):
    intr = torch.tensor([[focal, focal, (width - 1) / 2, (height - 1) / 2]], dtype=dtype)
    return torch.eye(4, dtype=dtype)[None], intr


def _white(num_vertices: int, dtype=torch.float64):
    return torch.ones(1, num_vertices, 3, dtype=dtype), torch.as_tensor(sh_from_lights(1.0), dtype=dtype)[None]


def test_rasterize_triangles_matches_brute_force_point_in_triangle(rng):
    pix = rng.uniform(-3, 19, (1, 12, 2))
    depth = rng.uniform(2, 9, (1, 12))
    faces = rng.choice(12, (6, 3), replace=True)
    faces = faces[np.array([len(set(f)) == 3 for f in faces])]
    tri, zbuf = rasterize_triangles(pix, depth, faces, 16, 16)
    ys, xs = np.mgrid[0:16, 0:16]
    best = np.full((16, 16), np.inf)
    want = np.full((16, 16), -1)
    for t, (a, b, c) in enumerate(faces):
        lam = screen_barycentrics(torch.as_tensor(pix[0, [a, b, c]])[None, None],
                                  torch.as_tensor(np.stack([xs, ys], -1), dtype=torch.float64)).numpy()
        inside = (lam >= 0).all(-1)
        z = 1.0 / (lam / depth[0, [a, b, c]]).sum(-1)
        better = inside & (z < best)
        best[better], want[better] = z[better], t
    np.testing.assert_array_equal(tri[0], want)
    np.testing.assert_allclose(zbuf[0][want >= 0], best[want >= 0], rtol=1e-12)


def test_rasterize_triangles_skips_triangles_behind_the_near_plane():
    tri, _ = rasterize_triangles(np.array([[[0., 0], [3, 0], [0, 3]]]), np.array([[5.0, 5.0, -1.0]]),
                                 np.array([[0, 1, 2]]), 3, 3)
    assert (tri == -1).all()


def test_rasterize_triangles_error_names_argument():
    with pytest.raises(ValueError, match=r"depth: expected shape \(1, 3\)"):
        rasterize_triangles(np.zeros((1, 3, 2)), np.zeros((1, 4)), np.array([[0, 1, 2]]), 4, 4)


def test_silhouette_walk_crosses_a_triangle_seen_edge_on():
    # pixel (0, 0) shows triangle 0 (clockwise on screen); the walk towards pixel (1, 0) leaves it across
    # the edge v0-v1 into triangle 1, whose corners are collinear on screen (seen edge-on, zero area)
    pix = np.array([[[-1.0, -1.0], [0.5, 0.3], [-1.0, 1.0], [2.0, 1.6]]])
    faces = np.array([[0, 2, 1], [1, 0, 3], [0, 1, 2]])
    adjacency = np.array([[-1, 1, -1], [-1, -1, 0], [-1, -1, -1]])
    triangle = np.array([[[0, 2]]])
    zbuffer = np.array([[[1.0, 2.0]]])
    occ, far, tri, edge = silhouette_pairs(triangle, zbuffer, pix, faces, adjacency)
    assert len(occ) == len(far) == len(tri) == len(edge) <= 1  # no division by its zero area


def test_triangle_adjacency_pairs_shared_edges():
    faces = np.array([[0, 1, 2], [2, 1, 3], [3, 1, 4]])
    adj = triangle_adjacency(faces)
    assert adj.tolist() == [[1, -1, -1], [2, -1, 0], [-1, -1, 1]]


def test_sh_from_lights_reproduces_ambient_plus_clamped_cosine():
    coeffs = sh_from_lights(0.3, (0.0, 0.0, 1.0), 1.0)
    normals = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
    irradiance = sh_basis(normals) @ torch.as_tensor(coeffs, dtype=torch.float64)
    # order-2 SH of max(cos, 0): 1/4 + cos/2 + 5/32 (3 cos^2 - 1) -> 1.0625, 0.09375, 0.0625
    np.testing.assert_allclose(irradiance[:, 0].numpy(), [0.3 + 1.0625, 0.3 + 0.09375, 0.3 + 0.0625],
                               atol=1e-5)


def test_vertex_normals_of_a_sphere_point_outwards():
    verts, faces = _icosphere(3, 3.0)
    n = vertex_normals(torch.as_tensor(verts)[None], torch.as_tensor(faces))[0].numpy()
    np.testing.assert_allclose(n, verts / 3.0, atol=2e-2)


def _normals_by_gather(vertices, faces):
    """Plain autograd reference: gather corners, cross, index_add to vertices, normalize."""
    v0, v1, v2 = (vertices[:, faces[:, k]] for k in range(3))
    face_n = torch.cross(v1 - v0, v2 - v0, dim=-1)
    sums = torch.zeros_like(vertices).index_add(1, faces.T.reshape(-1), face_n.repeat(1, 3, 1))
    return sums / sums.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def test_vertex_normals_values_and_gradients_match_a_gather_reference(rng):
    verts, faces = _icosphere(1, 2.0)
    faces_t = torch.as_tensor(faces)
    x = torch.as_tensor(verts[None] * rng.uniform(0.8, 1.2, (2, len(verts), 3)))  # batch of 2, bumpy
    weights = torch.as_tensor(rng.normal(size=(2, len(verts), 3)))
    ours = x.clone().requires_grad_()
    ref = x.clone().requires_grad_()
    (vertex_normals(ours, faces_t) * weights).sum().backward()
    (_normals_by_gather(ref, faces_t) * weights).sum().backward()
    np.testing.assert_allclose(vertex_normals(x, faces_t).numpy(), _normals_by_gather(x, faces_t).numpy(),
                               atol=1e-12)
    np.testing.assert_allclose(ours.grad.numpy(), ref.grad.numpy(), atol=1e-10)
    assert torch.autograd.gradcheck(lambda v: vertex_normals(v, faces_t), (x[:1].clone().requires_grad_(),))
    # a changed triangle list with the same sizes must not reuse the cached matrices
    flipped = faces_t[:, [0, 2, 1]].contiguous()
    np.testing.assert_allclose(vertex_normals(x, flipped).numpy(), -vertex_normals(x, faces_t).numpy(),
                               atol=1e-12)


def test_render_single_triangle_area_matches_closed_form(rng):
    width = height = 64
    world_to_camera, intr = _pinhole(width, height, 100.0)
    for _ in range(4):
        corners = rng.uniform(6, 57, (3, 2))
        z = rng.uniform(8, 12, 3)  # a tilted triangle: the image triangle is the projection
        verts = np.concatenate([(corners - (width - 1) / 2) / 100.0 * z[:, None], z[:, None]], 1)
        albedo, sh = _white(3)
        out = render_mesh(torch.as_tensor(verts)[None], np.array([[0, 1, 2]]), world_to_camera, intr,
                          height, width, albedo=albedo, sh=sh)
        e1, e2 = corners[1] - corners[0], corners[2] - corners[0]
        area = abs(e1[0] * e2[1] - e1[1] * e2[0]) / 2
        assert out.alpha.sum().item() == pytest.approx(area, rel=0.015, abs=1.0)
        # coverage and colour agree (white on black)
        np.testing.assert_allclose(out.image[..., 0].numpy(), out.alpha.numpy(), atol=1e-9)


def test_render_sphere_silhouette_area_matches_closed_form():
    radius, distance, focal = 5.0, 40.0, 300.0
    verts, faces = _icosphere(4, radius)
    verts = verts + np.array([0.0, 0.0, distance])
    world_to_camera, intr = _pinhole(128, 128, focal)
    albedo, sh = _white(len(verts))
    out = render_mesh(torch.as_tensor(verts)[None], faces, world_to_camera, intr, 128, 128, albedo=albedo, sh=sh)
    # silhouette of a sphere on the optical axis: a circle of radius f r / sqrt(d^2 - r^2)
    expected = np.pi * focal ** 2 * radius ** 2 / (distance ** 2 - radius ** 2)
    # the tessellated sphere (vertices on the sphere) is inscribed: about 0.3 % smaller
    assert out.alpha.sum().item() == pytest.approx(expected, rel=0.01)
    hard = render_mesh(torch.as_tensor(verts)[None], faces, world_to_camera, intr, 128, 128, albedo=albedo,
                       sh=sh, antialias=False)
    assert set(np.unique(hard.alpha.numpy())) <= {0.0, 1.0}
    assert 0 < (out.alpha != hard.alpha).sum() < 0.1 * expected


def test_render_depth_is_perspective_correct():
    # a plane z = 10 + 0.5 x, seen through a pinhole: depth at pixel (u, v) in closed form
    width = height = 32
    focal = 40.0
    world_to_camera, intr = _pinhole(width, height, focal)
    verts = np.array([[-8.0, -8, 6], [8, -8, 14], [8, 8, 14], [-8, 8, 6]])
    out = render_mesh(torch.as_tensor(verts)[None], np.array([[0, 1, 2], [0, 2, 3]]), world_to_camera, intr,
                      height, width, albedo=torch.ones(1, 4, 3, dtype=torch.float64),
                      sh=torch.as_tensor(sh_from_lights(1.0), dtype=torch.float64)[None])
    u = (np.arange(width) - (width - 1) / 2) / focal
    want = 10.0 / (1 - 0.5 * u)[None, :].repeat(height, 0)
    mask = out.triangle[0].numpy() >= 0
    assert mask.mean() > 0.5
    np.testing.assert_allclose(out.depth[0].numpy()[mask], want[mask], rtol=1e-10)
    np.testing.assert_allclose(out.barycentrics[0].sum(-1).numpy()[mask], 1.0, rtol=1e-12)


def _scene(dtype=torch.float64):
    rng = np.random.default_rng(0)
    verts, faces = _icosphere(2, 5.0)
    verts = verts * (1 + 0.1 * rng.standard_normal((len(verts), 1))) + np.array([1.0, 0.5, 40.0])
    world_to_camera, intr = _pinhole(48, 48, 150.0, dtype)
    albedo = torch.tensor(rng.uniform(0.2, 1, (1, len(verts), 3)), dtype=dtype)
    sh = torch.as_tensor(sh_from_lights(0.4, (0.3, -0.5, -1.0), 0.8), dtype=dtype)[None]
    weights = torch.tensor(rng.standard_normal((1, 48, 48, 3)), dtype=dtype)
    return torch.as_tensor(verts, dtype=dtype)[None], faces, world_to_camera, intr, albedo, sh, weights


def test_render_gradients_match_finite_differences():
    verts, faces, world_to_camera, intr, albedo, sh, weights = _scene()
    background = torch.tensor([0.2, 0.3, 0.1], dtype=torch.float64)
    adjacency = triangle_adjacency(faces)

    def loss(v, a, s):
        out = render_mesh(v, faces, world_to_camera, intr, 48, 48, albedo=a, sh=s, background=background,
                          adjacency=adjacency)
        return (out.image * weights).sum()

    leaves = [t.clone().requires_grad_() for t in (verts, albedo, sh)]
    loss(*leaves).backward()
    rng = np.random.default_rng(1)
    h = 1e-6
    for k, leaf in enumerate(leaves):
        for _ in range(2):
            direction = torch.as_tensor(rng.standard_normal(leaf.shape))
            plus = [t.detach() + (h * direction if i == k else 0) for i, t in enumerate(leaves)]
            minus = [t.detach() - (h * direction if i == k else 0) for i, t in enumerate(leaves)]
            numeric = (loss(*plus) - loss(*minus)).item() / (2 * h)
            analytic = (leaf.grad * direction).sum().item()
            assert analytic == pytest.approx(numeric, rel=1e-4, abs=1e-6), k


def test_render_silhouette_gradient_moves_the_edge():
    # moving a white square right by dx adds dx * height of coverage on the right and removes
    # it on the left: d(sum of right half - sum of left half) / dx = 2 * height in pixels
    width = height = 32
    world_to_camera, intr = _pinhole(width, height, 32.0)
    verts = torch.tensor([[-3.0, -3.2, 10], [3.1, -3.2, 10], [3.1, 3.3, 10], [-3.0, 3.3, 10]],
                         dtype=torch.float64, requires_grad=True)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    albedo, sh = _white(4)
    out = render_mesh(verts[None], faces, world_to_camera, intr, height, width, albedo=albedo, sh=sh)
    signed = torch.cat([-out.alpha[0, :, :16], out.alpha[0, :, 16:]], 1).sum()
    signed.backward()
    dx_px = verts.grad[:, 0].sum().item() * 10.0 / 32.0  # per pixel of shift
    span_px = 6.5 * 32.0 / 10.0
    assert dx_px == pytest.approx(2 * span_px, rel=0.03)


def test_render_batched_matches_one_at_a_time():
    verts, faces, world_to_camera, intr, albedo, sh, _ = _scene()
    shifted = verts + torch.tensor([0.5, -0.3, 2.0], dtype=torch.float64)
    both = render_mesh(torch.cat([verts, shifted]), faces, world_to_camera.expand(2, 4, 4),
                       intr.expand(2, 4), 48, 48, albedo=albedo, sh=sh)
    one = render_mesh(shifted, faces, world_to_camera, intr, 48, 48, albedo=albedo, sh=sh)
    np.testing.assert_allclose(both.image[1].numpy(), one.image[0].numpy(), atol=1e-12)
    np.testing.assert_array_equal(both.triangle[1].numpy(), one.triangle[0].numpy())


def test_render_supersample_averages_blocks():
    verts, faces, world_to_camera, intr, albedo, sh, _ = _scene()
    fine = render_mesh(verts, faces, world_to_camera, intr, 48, 48, albedo=albedo, sh=sh, supersample=2)
    assert fine.image.shape == (1, 48, 48, 3)
    plain = render_mesh(verts, faces, world_to_camera, intr, 48, 48, albedo=albedo, sh=sh)
    assert fine.alpha.sum().item() == pytest.approx(plain.alpha.sum().item(), rel=0.02)


def test_render_mesh_error_names_argument():
    verts, faces, world_to_camera, intr, albedo, sh, _ = _scene()
    with pytest.raises(ValueError, match=r"albedo: expected shape \(1 or 1, 162, 3\)"):
        render_mesh(verts, faces, world_to_camera, intr, 48, 48, albedo=albedo[:, :10], sh=sh)
    with pytest.raises(ValueError, match=r"sh: expected shape"):
        render_mesh(verts, faces, world_to_camera, intr, 48, 48, albedo=albedo, sh=sh[:, :4])


@pytest.mark.cuda
def test_render_cuda_matches_cpu():
    verts, faces, world_to_camera, intr, albedo, sh, weights = _scene(torch.float32)
    outs, grads = [], []
    for device in ("cpu", "cuda"):
        v = verts.detach().to(device).requires_grad_()  # a leaf on each device
        out = render_mesh(v, faces, world_to_camera.to(device), intr.to(device), 48, 48,
                          albedo=albedo.to(device), sh=sh.to(device))
        (out.image * weights.to(device)).sum().backward()
        outs.append(out.image.detach().cpu())
        grads.append(v.grad.cpu())
    np.testing.assert_allclose(outs[1].numpy(), outs[0].numpy(), atol=1e-4)
    np.testing.assert_allclose(grads[1].numpy(), grads[0].numpy(), atol=1e-3, rtol=1e-3)
