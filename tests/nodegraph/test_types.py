"""Port types: chunk slicing and concatenation, storage round trip, fingerprints, checks."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph.types import (FaceModel, ImageSequence, Landmarks2D, MeshSequence, ParamSequence,
                             RigidSequence, Table, port_type_by_name)


def _mesh(rng, frames=6, verts=5):
    return MeshSequence(rng.normal(size=(frames, verts, 3)).astype(np.float32),
                        np.array([[0, 1, 2], [2, 3, 4]], np.int32),
                        groups={"rigid": np.array([0, 2], np.int64)}, fps=24.0)


def test_mesh_slice_concat_round_trip(rng):
    mesh = _mesh(rng)
    parts = [mesh.slice_frames(0, 2), mesh.slice_frames(2, 5), mesh.slice_frames(5, 6)]
    again = MeshSequence.concat_frames(parts)
    assert np.array_equal(again.vertices, mesh.vertices)
    assert np.array_equal(again.faces, mesh.faces)
    assert again.fps == 24.0 and set(again.groups) == {"rigid"}


def test_to_arrays_round_trip_keeps_fingerprint(rng):
    mesh = _mesh(rng)
    back = MeshSequence.from_arrays(mesh.to_arrays())
    assert back.fingerprint() == mesh.fingerprint()
    assert np.array_equal(back.groups["rigid"], mesh.groups["rigid"]) and back.fps == mesh.fps
    params = ParamSequence(rng.random((4, 2)).astype(np.float32), ["a", "b"])
    assert ParamSequence.from_arrays(params.to_arrays()).names == ["a", "b"]
    table = Table(["x", "y"], [[1, "a"], [2.5, "b"]])
    assert Table.from_arrays(table.to_arrays()).rows == table.rows


def test_fingerprint_changes_with_one_value(rng):
    mesh = _mesh(rng)
    other = MeshSequence(mesh.vertices.copy(), mesh.faces, groups=mesh.groups, fps=mesh.fps)
    assert other.fingerprint() == mesh.fingerprint()
    other.vertices[3, 2, 1] += 1e-6
    assert other.fingerprint() != mesh.fingerprint()


def test_to_arrays_has_no_object_arrays(rng):
    for value in [_mesh(rng), Table(["a"], [[1]]), ParamSequence(np.zeros((2, 1), np.float32), ["a"])]:
        assert all(a.dtype != object for a in value.to_arrays().values())


@pytest.mark.parametrize("make, message", [
    (lambda: MeshSequence(np.zeros((2, 3, 2), np.float32)), "size 3 on axis 2"),
    (lambda: MeshSequence(np.full((1, 3, 3), np.nan, np.float32)), "non-finite"),
    (lambda: MeshSequence(np.zeros((1, 3, 3), np.float32), np.array([[0, 1, 7]])), "outside"),
    (lambda: MeshSequence(np.zeros((1, 3, 3), np.float32), groups={"g": np.array([5])}), "groups\\['g'\\]"),
    (lambda: RigidSequence(np.ones((2, 4, 4))), "orthonormal"),
    (lambda: Landmarks2D(np.zeros((2, 5, 2), np.float32), np.zeros((2, 4), np.float32)), "confidence"),
    (lambda: ImageSequence(np.zeros((1, 4, 4, 3), np.float32), ["R", "G"]), "channel"),
    (lambda: ParamSequence(np.zeros((3, 2), np.float32), ["a"]), "names"),
])
def test_validate_names_the_field(make, message):
    with pytest.raises(ValueError, match=message):
        make().validate()


def test_concat_rejects_different_topology(rng):
    a = _mesh(rng)
    b = MeshSequence(a.vertices[:, :4], np.zeros((0, 3), np.int32))
    with pytest.raises(ValueError, match="chunk 1"):
        MeshSequence.concat_frames([a, b])


def test_face_model_evaluate_numpy_matches_formula(rng):
    k, v, i = 3, 4, 2
    model = FaceModel(rng.normal(size=(v, 3)).astype(np.float32), np.zeros((0, 3), np.int32),
                      rng.normal(size=(k, v, 3)).astype(np.float32), ["a", "b", "c"],
                      rng.normal(size=(i, v, 3)).astype(np.float32))
    w = rng.random((5, k)).astype(np.float32)
    ident = rng.normal(size=i).astype(np.float32)
    expected = model.neutral + np.einsum("fk,kvc->fvc", w, model.expression_deltas) \
        + np.einsum("i,ivc->vc", ident, model.identity_deltas)
    np.testing.assert_allclose(model.evaluate(w, ident), expected, rtol=1e-5, atol=1e-5)


def test_port_type_lookup():
    assert port_type_by_name("MeshSequence") is MeshSequence
    with pytest.raises(KeyError, match="unknown port type"):
        port_type_by_name("Nope")


# -- ImageSequence colour space ---------------------------------------------------------------

def test_srgb_curve_matches_the_standard_and_inverts():
    from nodegraph.types import linear_to_srgb, srgb_to_linear

    c = np.linspace(-0.1, 1.2, 2001)
    ref = np.array([v / 12.92 if v <= 0.04045 else ((v + 0.055) / 1.055) ** 2.4 for v in c])
    np.testing.assert_allclose(srgb_to_linear(c), ref, rtol=1e-6, atol=1e-9)
    assert srgb_to_linear(np.array([0.04045]))[0] == np.float32(0.04045 / 12.92)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(c)), c, rtol=1e-6, atol=1e-7)
    assert srgb_to_linear(np.array([0.0, 1.0])).tolist() == [0.0, 1.0]


def test_image_colour_conversion_leaves_alpha_and_returns_new_values(rng):
    pixels = rng.random((2, 3, 4, 4)).astype(np.float32)
    images = ImageSequence(pixels.copy(), ["R", "G", "B", "A"])
    assert images.colour_space == "srgb" and images.to_srgb() is images
    lin = images.to_linear()
    assert lin.colour_space == "linear" and images.colour_space == "srgb"
    np.testing.assert_array_equal(images.pixels, pixels)  # unchanged
    np.testing.assert_array_equal(lin.pixels[..., 3], pixels[..., 3])
    assert (lin.pixels[..., :3] <= pixels[..., :3] + 1e-7).all()
    np.testing.assert_allclose(lin.to_srgb().pixels, pixels, atol=2e-6)
    layered = ImageSequence(pixels.copy(), ["diffuse.R", "diffuse.G", "Z", "diffuse.A"])
    assert layered.colour_channels() == [0, 1]


def test_image_colour_space_is_validated_stored_and_refused_across_chunks(rng):
    images = ImageSequence(rng.random((4, 2, 2, 3)).astype(np.float32), colour_space="linear")
    back = ImageSequence.from_arrays(images.to_arrays())
    assert back.colour_space == "linear" and back.fingerprint() == images.fingerprint()
    assert images.fingerprint() != images.to_srgb().fingerprint()
    with pytest.raises(ValueError, match=r"'colour_space' must be one of \['linear', 'srgb'\], "
                                         r"found 'rec709'"):
        ImageSequence(images.pixels, colour_space="rec709").validate()
    parts = [images.slice_frames(0, 2), images.slice_frames(2, 4)]
    np.testing.assert_array_equal(ImageSequence.concat_frames(parts).pixels, images.pixels)
    with pytest.raises(ValueError, match=r"chunk 1 has colour_space 'srgb', chunk 0 has 'linear'"):
        ImageSequence.concat_frames([parts[0], parts[1].to_srgb()])
