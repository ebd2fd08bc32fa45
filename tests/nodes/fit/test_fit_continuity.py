"""The fit's answer is a continuous function of its input (issue 30: it followed the thread count).

Why: a run with another number of threads rounds the float32 renders and network readings
differently (OMP_NUM_THREADS 1 against 2 on a 6-frame synthetic shot: plate landmarks 6e-5 px
apart, renders 4e-6). A fit whose answer jumps under such a change gives a studio different
animation on a laptop and on a farm node. Two jumps, each fixed and tested here:

- the photometric term read the plate bilinearly, whose derivative jumps at every pixel
  boundary: Levenberg-Marquardt's Gauss-Newton model was wrong past the next boundary and the
  solve stalled (damping 1e6, 51 iterations) where the last bits decided. It reads it
  bicubically (`sample_bicubic`, C1), and the identity's rounds converge (damping 1e-7);
- a render landmark was anchored on the triangle under its *rounded pixel*, clamped into it:
  a point crossing a pixel boundary switched triangle and its surface point jumped. It is
  anchored on the triangle that contains it (`_containing_triangles`), so the surface point
  changes only where neighbouring triangles share it.

Together, on the 6-frame shot's photometric identity (6 rounds), a 1e-7 relative change of the
lighting moved the identity by 1.1e-5 after the last round, against 5.3e-2 before (bicubic
alone 1.6e-2, containing triangle alone 2.4e-2).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nodes.fit.photometric import sample_bicubic  # noqa: E402
from nodes.fit.views import FitViews, _containing_triangles, anchors_from_render, landmark_anchors  # noqa: E402

f64 = torch.float64


def test_sample_bicubic_is_exact_at_centres_and_its_gradient_is_the_derivative():
    g = torch.Generator().manual_seed(0)
    images = torch.rand(2, 9, 11, 3, generator=g, dtype=f64)
    ys, xs = torch.meshgrid(torch.arange(9.0, dtype=f64), torch.arange(11.0, dtype=f64), indexing="ij")
    centres = torch.stack([xs, ys], -1).reshape(1, -1, 2).expand(2, -1, 2)
    torch.testing.assert_close(sample_bicubic(images, centres), images.reshape(2, -1, 3), atol=1e-12, rtol=0)
    xy = torch.rand(2, 40, 2, generator=g, dtype=f64) * torch.tensor([9.0, 7.0], dtype=f64) + 0.5  # inside
    value, grad = sample_bicubic(images, xy, gradient=True)
    for axis in range(2):
        tangent = torch.zeros_like(xy)
        tangent[..., axis] = 1.0
        _, ref = torch.func.jvp(lambda p: sample_bicubic(images, p), (xy,), (tangent,))
        torch.testing.assert_close(grad[..., axis], ref, atol=1e-10, rtol=0)


def test_sample_bicubic_derivative_is_continuous_across_pixel_boundaries():
    """The derivative on both sides of x = 4 (and y = 5) agrees to O(eps); a bilinear read's jumps
    by the difference of the neighbouring slopes, order 1 on this random image."""
    g = torch.Generator().manual_seed(1)
    images = torch.rand(1, 8, 8, 1, generator=g, dtype=f64)
    eps = 1e-9
    xy = torch.tensor([[[4.0 - eps, 3.3], [4.0 + eps, 3.3], [2.7, 5.0 - eps], [2.7, 5.0 + eps]]], dtype=f64)
    _, grad = sample_bicubic(images, xy, gradient=True)
    assert abs(float(grad[0, 0, 0, 0] - grad[0, 1, 0, 0])) < 1e-6
    assert abs(float(grad[0, 2, 0, 1] - grad[0, 3, 0, 1])) < 1e-6
    assert float(grad.abs().max()) > 0.05  # a real slope, not a flat image


def _grid_render(size: int = 40, cells: int = 9, spacing: float = 3.7, origin: float = 3.3):
    """A flat grid mesh (two triangles per cell) seen head-on: its projected vertices (1, V, 2)
    and the visible triangle under each pixel centre (1, S, S), as `render_crops` gives them."""
    n = cells + 1
    ys, xs = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    pix = np.stack([xs, ys], -1).reshape(-1, 2) * spacing + origin
    pix[:, 0] += 0.31 * pix[:, 1] / spacing  # sheared: the edges are not pixel-aligned
    idx = (ys * n + xs)[:-1, :-1].reshape(-1)
    faces = np.concatenate([np.stack([idx, idx + 1, idx + n + 1], 1), np.stack([idx, idx + n + 1, idx + n], 1)])
    cy, cx = np.meshgrid(np.arange(size, dtype=np.float64), np.arange(size, dtype=np.float64), indexing="ij")
    centres = np.stack([cx, cy], -1).reshape(-1, 2)
    triangle = np.full(size * size, -1, np.int64)
    for t, (a, b, c) in enumerate(faces):  # test setup: a brute-force rasterizer of 162 triangles
        p0, v0, v1 = pix[a], pix[b] - pix[a], pix[c] - pix[a]
        v2 = centres - p0
        den = v0[0] * v1[1] - v1[0] * v0[1]
        l1 = (v2[:, 0] * v1[1] - v1[0] * v2[:, 1]) / den
        l2 = (v0[0] * v2[:, 1] - v2[:, 0] * v0[1]) / den
        triangle[(l1 >= 0) & (l2 >= 0) & (l1 + l2 <= 1)] = t
    return (torch.as_tensor(pix, dtype=f64)[None], torch.as_tensor(triangle.reshape(1, size, size)),
            torch.as_tensor(faces))


def test_a_render_point_is_anchored_on_the_triangle_that_contains_it():
    """Points scattered inside a sheared grid mesh, many within 1e-7 px of a pixel boundary: each is
    anchored on a triangle that contains it (the anchor's projection is the point itself, offset
    < 1e-9 px), and moving a point across a pixel boundary by 2e-7 px moves its anchor by as much.
    With the rounded pixel's triangle, clamped into it, a point on the far side of an edge from its
    pixel centre was anchored up to a pixel away (offset > 0.01 px at several of these points)."""
    pix, triangle, faces = _grid_render()
    g = torch.Generator().manual_seed(3)
    inner = torch.rand(1, 200, 2, generator=g, dtype=f64) * 24.0 + 8.0
    near = inner.clone()
    near[0, :100, 0] = near[0, :100, 0].floor() + 0.5 - 1e-7  # just left of a pixel boundary
    near[0, 100:, 1] = near[0, 100:, 1].floor() + 0.5 - 1e-7  # just above one
    across = near.clone()
    across[0, :100, 0] += 2e-7
    across[0, 100:, 1] += 2e-7
    found, _ = _containing_triangles(triangle, pix, near, faces)
    assert bool(found.all())
    model = SimpleNamespace(faces=faces.numpy())
    views = FitViews(target=torch.zeros(1, 1, 68, 2), boxes=torch.tensor([[[0.0, 0.0, 40.0, 40.0]]], dtype=f64),
                     seen=torch.ones(1, 1, dtype=torch.bool), world_to_camera=torch.eye(4)[None],
                     intrinsics=torch.tensor([[1.0, 1.0, 0.0, 0.0]]), distortion=None,
                     image_size=torch.tensor([[40, 40]]))
    fallback = landmark_anchors(SimpleNamespace(landmarks=np.zeros(68, np.int64), neutral=torch.zeros(1, 3)),
                                1, 1, 200)
    presence = torch.ones(1, dtype=f64)
    anchored = []
    for points in (near, across):
        a = anchors_from_render(model, views, triangle, pix, points, presence, fallback)
        assert bool(a.rendered.all())
        at = (a.bary[..., None] * pix[0][a.vertices]).sum(-2)  # (1, 1, L, 2) the anchors' projections
        assert float(a.offset.abs().max()) < 1e-9
        anchored.append(at)
    torch.testing.assert_close(anchored[0][0, 0], near[0], atol=1e-9, rtol=0)
    assert float((anchored[1] - anchored[0]).abs().max()) < 1e-6
    # the old rule's failure is real here: the rounded pixel's triangle misses some of these points
    ij = near[0].round().long()
    pixel_tri = triangle[0, ij[:, 1], ij[:, 0]]
    _, contains = _containing_triangles(triangle, pix, near, faces)
    assert int((pixel_tri != contains[0]).sum()) >= 5
