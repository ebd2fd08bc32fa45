"""ARKit names and the Live Link Face CSV conventions (nodes.io.arkit), and io.LoadLiveLinkCSV:
the ICT-to-ARKit mapping checked against the mesh itself (which side a shape moves), timecodes,
angles against scipy, and reading takes written as the app writes them."""

from __future__ import annotations

import re

import numpy as np
import pytest

from nodegraph import NodeError, run_node
from nodes.io.arkit import (ANGLE_UNIT_RAD, ARKIT_NAMES, LIVE_LINK_HEADER, LIVE_LINK_SHAPES, arkit_name,
                            format_timecode, from_arkit_weights, head_angles, head_rotation, parse_timecode,
                            shape_basis, to_arkit_weights)
from nodes.io.face_model import load_face_model
from nodes.io.livelink import LoadLiveLinkCSV, infer_fps, read_live_link_csv


@pytest.fixture(scope="module")
def model():
    return load_face_model()


def test_arkit_names_are_the_52_of_the_live_link_header():
    assert len(ARKIT_NAMES) == 52 == len(set(ARKIT_NAMES))
    assert LIVE_LINK_HEADER[:4] == ("Timecode", "BlendShapeCount", "EyeBlinkLeft", "EyeLookDownLeft")
    assert LIVE_LINK_HEADER[-9:-6] == ("HeadYaw", "HeadPitch", "HeadRoll") and len(LIVE_LINK_HEADER) == 63
    assert LIVE_LINK_SHAPES[14:18] == ("JawForward", "JawRight", "JawLeft", "JawOpen")


def test_every_ict_shape_maps_to_an_arkit_shape_and_only_tongue_out_is_missing(model):
    mapped = {arkit_name(n) for n in model.expression_names}
    assert mapped <= set(ARKIT_NAMES)
    assert set(ARKIT_NAMES) - mapped == {"tongueOut"}
    assert arkit_name("eyeBlink_L") == "eyeBlinkLeft" and arkit_name("mouthSmile_R") == "mouthSmileRight"
    assert arkit_name("browInnerUp_R") == "browInnerUp" and arkit_name("jawOpen") == "jawOpen"


def test_left_shapes_move_the_subjects_left_side(model):
    """ARKit's Left is the subject's own left: +x of the ICT head (it faces +z, y up), found from the mesh."""
    right_eye_x = model.neutral[model.landmarks[36:42]].mean(0)[0]  # 68-point 36-41: the subject's right eye
    left_eye_x = model.neutral[model.landmarks[42:48]].mean(0)[0]
    assert right_eye_x < 0 < left_eye_x
    deltas = np.linalg.norm(model.expression_deltas, axis=2)
    for k, name in enumerate(model.expression_names):
        if not name.endswith(("_L", "_R")):
            continue
        centre = np.average(model.neutral[:, 0], weights=deltas[k])  # where the shape moves the skin
        assert (centre > 0) == name.endswith("_L"), (name, centre)
        if arkit_name(name).endswith(("Left", "Right")):
            assert arkit_name(name).endswith("Left") == name.endswith("_L")


def test_shape_basis_reproduces_the_model_exactly(model, rng):
    names, a, b = shape_basis(model.expression_names)
    assert names[:52] == list(ARKIT_NAMES) and names[52:] == ["browInnerUpAsymmetry", "cheekPuffAsymmetry"]
    k = len(model.expression_names)
    w = rng.uniform(0, 1, (5, k))
    d = model.expression_deltas.reshape(k, -1).astype(np.float64)
    np.testing.assert_allclose((w @ a.T) @ (b @ d), w @ d, atol=1e-9)
    names2, a2, b2 = shape_basis(model.expression_names, asymmetry=False)
    assert names2 == list(ARKIT_NAMES)
    sym = w.copy()
    for left, right in (("browInnerUp_L", "browInnerUp_R"), ("cheekPuff_L", "cheekPuff_R")):
        sym[:, model.expression_names.index(right)] = sym[:, model.expression_names.index(left)]
    np.testing.assert_allclose((sym @ a2.T) @ (b2 @ d), sym @ d, atol=1e-9)


def test_arkit_weights_round_trip_and_split_halves(model, rng):
    k = len(model.expression_names)
    w = rng.uniform(0, 1, (4, k))
    arkit = to_arkit_weights(w, model.expression_names)
    names = model.expression_names
    np.testing.assert_allclose(arkit[:, ARKIT_NAMES.index("browInnerUp")],
                               (w[:, names.index("browInnerUp_L")] + w[:, names.index("browInnerUp_R")]) / 2)
    assert np.all(arkit[:, ARKIT_NAMES.index("tongueOut")] == 0)
    back, unmatched = from_arkit_weights(arkit, names)
    assert unmatched == []
    same = [i for i, n in enumerate(names) if arkit_name(n) not in ("browInnerUp", "cheekPuff")]
    np.testing.assert_allclose(back[:, same], w[:, same], atol=1e-6)
    assert np.allclose(back[:, names.index("cheekPuff_L")], back[:, names.index("cheekPuff_R")])


def test_head_angles_invert_head_rotation_and_match_scipy(rng):
    from scipy.spatial.transform import Rotation

    angles = rng.uniform(-1.2, 1.2, (20, 3))
    rot = head_rotation(angles)
    yaw, pitch, roll = angles.T
    one = Rotation.from_rotvec(np.stack([0 * yaw, yaw, 0 * yaw], 1)) * Rotation.from_rotvec(
        np.stack([pitch, 0 * pitch, 0 * pitch], 1)) * Rotation.from_rotvec(np.stack([0 * roll, 0 * roll, roll], 1))
    np.testing.assert_allclose(rot, one.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(head_angles(rot), angles, atol=1e-9)
    # positive yaw turns the face (+z) towards the subject's left (+x)
    assert head_rotation(np.array([[0.3, 0, 0]]))[0, 0, 2] > 0


def test_timecodes_format_and_parse():
    assert format_timecode(0, 30.0) == "00:00:00:00.000"
    assert format_timecode(45, 30.0) == "00:00:01:15.000"
    assert format_timecode(30 * 3600, 30.0) == "01:00:00:00.000"
    assert format_timecode(3, 60.0, "10:59:59:58") == "11:00:00:01.000"
    assert format_timecode(1, 59.94) == "00:00:00:01.001"
    for i in range(200):  # never an out-of-range field at a fractional rate
        h, m, s, ff = parse_timecode(format_timecode(i, 29.97))
        assert 0 <= ff < 30 and 0 <= s < 60
    assert parse_timecode("01:02:03:04.500") == (1, 2, 3, 4.5)
    with pytest.raises(ValueError, match="timecode"):
        parse_timecode("12:00")


def _app_take(path, frames: int, fps_rows: int = 60, timecode_rate: int = 30) -> np.ndarray:
    """A CSV as the app writes a 60 fps take under a 30 fps timecode: 'BlendshapeCount', .500 rows,
    columns in the app's order; returns the (F, 52) weights written."""
    rng = np.random.default_rng(3)
    weights = np.round(rng.uniform(0, 1, (frames, 52)), 6)
    header = list(LIVE_LINK_HEADER)
    header[1] = "BlendshapeCount"
    lines = [",".join(header)]
    for i in range(frames):
        t = i / fps_rows
        whole = int(np.floor(t * timecode_rate + 1e-9))
        sub = round((t * timecode_rate - whole) * 1000)
        sec, ff = divmod(whole, timecode_rate)
        tc = f"17:42:{sec:02d}:{ff:02d}.{sub:03d}"
        angles = [0.1, -0.05, 0.02] + [0.0] * 6
        lines.append(",".join([tc, "61"] + [f"{v:.6f}" for v in weights[i]] + [f"{v:.6f}" for v in angles]))
    path.write_text("\n".join(lines) + "\n")
    return weights


def test_load_live_link_csv_reads_an_app_take_at_60_fps(tmp_path, model):
    path = tmp_path / "take.csv"
    weights = _app_take(path, 90)
    perf = run_node(LoadLiveLinkCSV, {"path": str(path)}, model=model)["performance"]
    perf.validate()
    assert perf.num_frames == 90 and perf.fps == pytest.approx(60.0)
    names = model.expression_names
    np.testing.assert_allclose(perf.weights[:, names.index("jawOpen")], weights[:, ARKIT_NAMES.index("jawOpen")],
                               atol=1e-6)
    np.testing.assert_allclose(perf.weights[:, names.index("browInnerUp_R")],
                               weights[:, ARKIT_NAMES.index("browInnerUp")], atol=1e-6)
    np.testing.assert_allclose(head_angles(perf.rotation[:1]) / ANGLE_UNIT_RAD, [[0.1, -0.05, 0.02]], atol=1e-6)
    np.testing.assert_allclose(perf.translation, np.tile([0, 0, -60.0], (90, 1)))
    arkit_only = run_node(LoadLiveLinkCSV, {"path": str(path)})["performance"]
    assert arkit_only.expression_names == list(ARKIT_NAMES)
    part = run_node(LoadLiveLinkCSV, {"path": str(path)}, model=model, frames=range(30, 40))["performance"]
    assert part.num_frames == 10 and part.fps == pytest.approx(60.0)  # the rate comes from the whole file
    np.testing.assert_allclose(part.weights, perf.weights[30:40])


def test_load_live_link_csv_finds_columns_by_name_in_any_case_and_order(tmp_path):
    path = tmp_path / "few.csv"
    path.write_text("jawopen,TIMECODE,eyeblinkleft\n0.5,00:00:00:00.000,0.25\n0.75,00:00:00:01.000,1\n")
    take = read_live_link_csv(path)
    np.testing.assert_allclose(take.arkit[:, ARKIT_NAMES.index("jawOpen")], [0.5, 0.75])
    np.testing.assert_allclose(take.arkit[:, ARKIT_NAMES.index("eyeBlinkLeft")], [0.25, 1.0])
    assert take.found == ["EyeBlinkLeft", "JawOpen"]
    with pytest.raises(ValueError, match="never pass a second"):
        infer_fps(take)
    perf = run_node(LoadLiveLinkCSV, {"path": str(path), "fps": 24.0})["performance"]
    assert perf.fps == 24.0


@pytest.mark.parametrize("text, match", [
    ("a,b,c\n1,2,3\n", "expected Live Link Face columns"),
    ("Timecode,JawOpen\n00:00:00:00.000,oops\n", "row 2, column 'JawOpen': expected a number, found 'oops'"),
    ("Timecode,JawOpen\nnoon,0.1\n", "row 2, column 'Timecode'"),
    ("", "empty file"),
])
def test_load_live_link_csv_refuses_bad_files_naming_the_place(tmp_path, text, match):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(NodeError, match=match):
        run_node(LoadLiveLinkCSV, {"path": str(path), "fps": 30.0})


@pytest.mark.parametrize("cell, shown", [("1e300", "found 1e+300"), ("-250", "found -250")])
def test_a_curve_value_far_outside_its_range_is_refused_naming_row_and_column(tmp_path, cell, shown):
    path = tmp_path / "take.csv"
    rows = [",".join(["Timecode", *LIVE_LINK_SHAPES])]
    rows += [",".join([f"10:00:00:{f:02d}.000", *("0.1" for _ in LIVE_LINK_SHAPES)]) for f in range(3)]
    rows[2] = rows[2].replace(",0.1", f",{cell}", 1)
    path.write_text("\n".join(rows) + "\n")
    with pytest.raises(ValueError, match=rf"row 3, column '{LIVE_LINK_SHAPES[0]}': expected a value within "
                                         rf"\+-100, {re.escape(shown)}"):
        read_live_link_csv(path)
