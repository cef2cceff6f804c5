"""Capture sets with fitted planes: ``plane`` targets, pixel masks and ``geometry`` (read, written, checked)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from elevmap.sources.captures import read_capture_set, write_capture_set
from noise_model.analysis.capture_data import CaptureData, capture_geometry
from noise_model.analysis.planes import Plane, plane_pose, target_plane

CAMERA = {"model": "D435", "width": 32, "height": 24, "fx": 20.0, "fy": 20.0, "ppx": 15.5, "ppy": 11.5,
          "depth_scale": 0.001, "baseline_m": 0.05}
FLOOR = {"kind": "plane", "normal": [-0.177, -0.927, -0.330], "offset_m": 0.630}


def _floor_capture(rng, **keys):
    mask = np.zeros((24, 32), dtype=bool)
    mask[12:, 4:] = True
    depth = rng.integers(0, 4000, (5, 24, 32), dtype=np.uint16)
    return {"id": "floor_s1", "target": dict(FLOOR), "geometry": "fitted", **keys}, depth, mask


def test_plane_target_mask_and_geometry_round_trip(tmp_path, rng):
    entry, depth, mask = _floor_capture(rng, operator="me")
    wall = ({"id": "wall", "target": {"kind": "wall", "distance_m": 1.0}}, rng.integers(0, 4000, (2, 24, 32),
                                                                                       dtype=np.uint16))
    write_capture_set(tmp_path / "s", CAMERA, [(entry, depth, mask), wall])
    doc = json.loads((tmp_path / "s" / "captures.json").read_text())
    floor_doc = doc["captures"][0]
    assert floor_doc["target"] == FLOOR and floor_doc["mask"] == "floor_s1_mask.png"
    assert floor_doc["geometry"] == "fitted" and floor_doc["operator"] == "me"
    assert "mask" not in doc["captures"][1] and "geometry" not in doc["captures"][1]

    cs = read_capture_set(tmp_path / "s")
    cap = cs.capture("floor_s1")
    np.testing.assert_array_equal(cs.load_depth("floor_s1"), depth)
    np.testing.assert_array_equal(cs.load_mask("floor_s1"), mask)
    assert cap.geometry == "fitted" and cap.is_fitted and cap.kind == "plane"
    assert cs.capture("wall").geometry == "measured" and cs.load_mask("wall") is None
    # the plane as the library holds it: normal away from the camera, the file's normal negated
    n = np.array(FLOOR["normal"]) / np.linalg.norm(FLOOR["normal"])
    np.testing.assert_allclose(cap.plane.normal, -n, atol=1e-12)
    assert cap.plane.offset_m == pytest.approx(0.630)
    # it meets the optical axis at offset / n_z
    assert cap.distance_m == pytest.approx(0.630 / (0.330 / np.linalg.norm(FLOOR["normal"])))
    # written again from what was read: the same file
    write_capture_set(tmp_path / "t", cs.camera, [(c.to_dict(), cs.load_depth(c.id), cs.load_mask(c.id))
                                                  for c in cs.captures])
    again = json.loads((tmp_path / "t" / "captures.json").read_text())
    assert again == doc


def test_capture_data_carries_mask_geometry_and_plane(tmp_path, rng):
    entry, depth, mask = _floor_capture(rng)
    cs = write_capture_set(tmp_path, CAMERA, [(entry, depth, mask)])
    cap = cs.captures[0]
    cd = CaptureData.from_capture_entry(cs.camera, cap.to_dict(), cs.load_depth(cap.id), cs.load_mask(cap.id))
    assert cd.is_fitted and cd.geometry_origin == "fitted"
    np.testing.assert_array_equal(cd.target_pixels(), mask)
    np.testing.assert_allclose(cd.plane.normal, cap.plane.normal, atol=1e-12)
    assert cd.plane.offset_m == pytest.approx(cap.plane.offset_m, abs=1e-12)
    expect = depth.astype(float) * 0.001
    expect[depth == 0] = np.nan
    np.testing.assert_array_equal(cd.depth_m, expect)
    with pytest.raises(ValueError, match="mask must be a boolean image"):
        CaptureData.from_units(cd.geometry, depth, mask=mask[:, :-1])
    with pytest.raises(ValueError, match="geometry_origin"):
        CaptureData.from_units(cd.geometry, depth, geometry_origin="guessed")


def test_a_plane_target_renders_as_the_wall_it_is(rng):
    """The spec: a wall can be written as a plane (normal -R e_z, offset c . R e_z); both render alike."""
    for _ in range(20):
        yaw, pitch, dist = rng.uniform(-70, 70), rng.uniform(-70, 70), rng.uniform(0.3, 5.0)
        wall = {"kind": "wall", "distance_m": dist, "yaw_deg": yaw, "pitch_deg": pitch}
        p = target_plane(wall)
        assert p.normal[2] > 0 and p.offset_m > 0
        d2, yaw2, pitch2 = plane_pose(p)
        assert (d2, yaw2, pitch2) == pytest.approx((dist, yaw, pitch), abs=1e-9)
        as_plane = {"kind": "plane", "normal": (-p.normal).tolist(), "offset_m": p.offset_m}
        g_wall = capture_geometry(CAMERA, {"id": "w", "target": wall})
        g_plane = capture_geometry(CAMERA, {"id": "p", "target": as_plane})
        zw, tw = g_wall.render()
        zp, tp = g_plane.render()
        np.testing.assert_allclose(zp, zw, rtol=1e-9)
        np.testing.assert_allclose(tp, tw, atol=1e-9)
    # a hand-worked case: a fronto-parallel wall at 2 m is the plane -z + 2 = 0
    p = target_plane({"kind": "plane", "normal": [0.0, 0.0, -1.0], "offset_m": 2.0})
    assert p == Plane(p.normal, 2.0) and np.allclose(p.normal, [0, 0, 1])
    assert plane_pose(p) == pytest.approx((2.0, 0.0, 0.0))
    # 45 deg yaw: n = (sin 45, 0, cos 45), offset = 1 m cos 45
    d, yaw, pitch = plane_pose(Plane(np.array([math.sqrt(0.5), 0.0, math.sqrt(0.5)]), math.sqrt(0.5)))
    assert (d, yaw, pitch) == pytest.approx((1.0, 45.0, 0.0))


@pytest.mark.parametrize("target, match", [
    ({"kind": "plane", "offset_m": 1.0}, "missing required key 'normal'"),
    ({"kind": "plane", "normal": [0.0, 0.0, -1.0]}, "missing required key 'offset_m'"),
    ({"kind": "plane", "normal": [0.0, -1.0], "offset_m": 1.0}, "'normal' must be 3 finite numbers"),
    ({"kind": "plane", "normal": [0.0, 0.0, "x"], "offset_m": 1.0}, "'normal' must be 3 finite numbers"),
    ({"kind": "plane", "normal": [0.0, 0.0, -1.1], "offset_m": 1.0}, "must have unit length"),
    ({"kind": "plane", "normal": [0.0, 0.6, 0.8], "offset_m": 1.0}, r"towards the camera \(normal\[2\] < 0\)"),
    ({"kind": "plane", "normal": [0.0, 0.0, -1.0], "offset_m": 0.0}, "'offset_m' = 0.0 m must be > 0"),
    ({"kind": "sphere", "distance_m": 1.0}, "unknown kind 'sphere'"),
])
def test_bad_plane_targets_are_named_errors(tmp_path, rng, target, match):
    depth = rng.integers(0, 4000, (2, 24, 32), dtype=np.uint16)
    with pytest.raises(ValueError, match=f"capture 'c'.*{match}"):
        write_capture_set(tmp_path, CAMERA, [({"id": "c", "target": target}, depth)])
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("edit, match", [
    (lambda d: d.update(geometry="guessed"), "'geometry' must be 'measured' or 'fitted'"),
    (lambda d: d.update(background_m=3.0), "'background_m' is for a board"),
    (lambda d: d.update(mask="m.bmp"), "'mask' file 'm.bmp' must be a .png"),
    (lambda d: d.update(mask="missing.png"), "'mask' file .*missing.png does not exist"),
    (lambda d: d.update(mask="depth.npy"), "must be a .png"),
    (lambda d: d.update(mask="small.png"), "'mask' file .*small.png is 8x6, not the camera's 32x24"),
    (lambda d: d.update(mask="text.png"), "'mask' file .*text.png is not a PNG image"),
])
def test_bad_masks_and_geometry_are_named_errors_on_reading(tmp_path, rng, edit, match):
    import cv2

    entry, depth, mask = _floor_capture(rng)
    write_capture_set(tmp_path, CAMERA, [(entry, depth, mask)])
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((6, 8), np.uint8))
    (tmp_path / "text.png").write_text("not a picture")
    doc = json.loads((tmp_path / "captures.json").read_text())
    edit(doc["captures"][0])
    (tmp_path / "captures.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=f"capture 'floor_s1'.*{match}"):
        read_capture_set(tmp_path)


def test_masks_of_any_png_kind_and_bad_mask_arrays(tmp_path, rng):
    import cv2

    entry, depth, mask = _floor_capture(rng)
    cs = write_capture_set(tmp_path / "a", CAMERA, [(entry, depth, mask)])
    path = cs.capture("floor_s1").mask_path
    # a 16-bit grey and a colour PNG drawn by hand: non-zero in any channel is the target
    cv2.imwrite(str(path), mask.astype(np.uint16) * 7)
    np.testing.assert_array_equal(read_capture_set(tmp_path / "a").load_mask("floor_s1"), mask)
    rgb = np.zeros((24, 32, 3), np.uint8)
    rgb[..., 1] = mask * 200
    cv2.imwrite(str(path), rgb)
    np.testing.assert_array_equal(read_capture_set(tmp_path / "a").load_mask("floor_s1"), mask)
    # a truncated PNG: the header reads, the image does not decode
    path.write_bytes(path.read_bytes()[:40])
    with pytest.raises(ValueError, match="cannot be decoded"):
        read_capture_set(tmp_path / "a").load_mask("floor_s1")
    for bad, match in ((mask.astype(np.uint8), "boolean array"), (mask[:, :-1], "not the camera's 32x24"),
                       (np.zeros_like(mask), "selects no pixel")):
        with pytest.raises(ValueError, match=match):
            write_capture_set(tmp_path / "b", CAMERA, [(entry, depth, bad)])
        assert not (tmp_path / "b").exists()
    # an existing capture set is not overwritten, mask included
    with pytest.raises(ValueError, match="would overwrite"):
        write_capture_set(tmp_path / "a", CAMERA, [(entry, depth, mask)])
    # two captures cannot write one mask file
    other = {**entry, "id": "other", "mask": "floor_s1_mask.png"}
    with pytest.raises(ValueError, match="'mask' file 'floor_s1_mask.png' is also written"):
        write_capture_set(tmp_path / "c", CAMERA, [(entry, depth, mask), (other, depth, mask)])
    # a mask referenced, not written: the file must already be there
    ref = {**entry, "mask": "floor_s1_mask.png"}
    cv2.imwrite(str(path), mask.astype(np.uint8))
    cs2 = write_capture_set(tmp_path / "a", CAMERA, [(ref, depth)], overwrite=True)
    np.testing.assert_array_equal(cs2.load_mask("floor_s1"), mask)


def test_a_mask_written_for_a_depth_file_already_in_the_folder(tmp_path, rng):
    """A recording referenced (depth None) gets its mask written beside it; its frames are not touched."""
    entry, depth, mask = _floor_capture(rng)
    tmp_path.mkdir(exist_ok=True)
    np.save(tmp_path / "rec.npy", depth)
    before = (tmp_path / "rec.npy").read_bytes()
    cs = write_capture_set(tmp_path, CAMERA, [({**entry, "depth": "rec.npy"}, None, mask)])
    assert (tmp_path / "rec.npy").read_bytes() == before
    np.testing.assert_array_equal(cs.load_mask("floor_s1"), mask)
    np.testing.assert_array_equal(cs.load_depth("floor_s1"), depth)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["captures.json", "floor_s1_mask.png", "rec.npy"]
