"""`visible_faces`: the triangles drawn once the ICT head's eye shells and eyelash strips are culled
(the one culling the fit, the temporal solves and the synthetic plates share)."""

from __future__ import annotations

import numpy as np

from nodes.io.face_model import load_face_model
from nodes.render.appearance import (ICT_HIDDEN_VERTEX_RANGES, culled_faces, hidden_faces, model_appearance,
                                     visible_faces)


def test_visible_faces_drops_the_faces_touching_a_hidden_range_in_order():
    faces = np.array([[0, 1, 2], [1, 2, 3], [2, 4, 5], [0, 2, 5], [5, 4, 3]], np.int32)
    kept = visible_faces(faces, 6, ((3, 4),))
    assert kept.dtype == np.int64
    assert kept.tolist() == [[0, 1, 2], [0, 2, 5]]
    assert visible_faces(faces, 6, ()).tolist() == faces.tolist()


def test_visible_faces_keeps_every_face_of_a_mesh_the_ranges_do_not_index():
    faces = np.array([[0, 1, 2], [1, 2, 3], [2, 3, 4]])
    assert visible_faces(faces, 5, ((3, 6),)).tolist() == faces.tolist()  # 5 vertices: the range ends at 6
    assert visible_faces(faces, 7, ((3, 6),)).tolist() == [[0, 1, 2]]
    region = load_face_model(region="face")
    assert region.neutral.shape[0] <= ICT_HIDDEN_VERTEX_RANGES[-1][1]
    np.testing.assert_array_equal(visible_faces(region.faces, region.neutral.shape[0]), region.faces)
    assert culled_faces(faces, 5, ((3, 6),)).tolist() == [] and culled_faces(faces, 7, ((3, 6),)).tolist() == [1, 2]
    assert culled_faces(region.faces, region.neutral.shape[0]).tolist() == []


def test_visible_faces_of_the_ict_head_against_a_per_face_reference():
    model = load_face_model()
    kept = visible_faces(model.faces, model.neutral.shape[0])
    reference = [face for face in model.faces.tolist()
                 if not any(first <= v <= last for v in face for first, last in ICT_HIDDEN_VERTEX_RANGES)]
    assert kept.tolist() == reference
    assert len(kept) + len(hidden_faces(model.faces)) == len(model.faces)
    np.testing.assert_array_equal(model_appearance(model, None)[3], hidden_faces(model.faces))
    assert 0 < len(kept) < len(model.faces)
