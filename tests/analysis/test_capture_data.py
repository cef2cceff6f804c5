"""noise_model.analysis.capture_data: capture geometry from captures.json entries, regions, frames, and the
reference simulation of a capture (draw for draw the frames of noise_model.sim.targets.simulate_target_frames)."""

import dataclasses
import math

import numpy as np
import pytest

import noise_model as nm
from noise_model.analysis import capture_data as cd
from noise_model.analysis.capture_data import CaptureData, CaptureGeometry, simulate_capture
from noise_model.sim.targets import render_planar_target, simulate_target_frames

CAMERA = {"model": "D435", "width": 424, "height": 240, "fx": 212.0, "fy": 212.0, "ppx": 211.5, "ppy": 119.5,
          "depth_scale": 0.001, "baseline_m": 0.05, "unknown_key": 1}
BOARD = {"id": "board_z0.80_y30", "depth": "board_z0.80_y30.npy", "background_m": 3.0,
         "target": {"kind": "board", "distance_m": 0.8, "yaw_deg": 30.0, "pitch_deg": 0.0, "width_m": 0.6,
                    "height_m": 0.9}}
WALL = {"id": "wall_z1.00_y00", "depth": "wall_z1.00_y00.npy", "background_m": None,
        "target": {"kind": "wall", "distance_m": 1.0, "yaw_deg": 0.0, "pitch_deg": 0.0}}


def test_geometry_from_a_captures_json_entry():
    g = CaptureGeometry.from_capture_set_entry(CAMERA, BOARD)
    assert g.id == "board_z0.80_y30" and (g.width, g.height) == (424, 240)
    assert np.array_equal(g.K, [[212.0, 0, 211.5], [0, 212.0, 119.5], [0, 0, 1]])
    assert g.depth_scale == 0.001 and g.baseline_m == 0.05 and g.background_m == 3.0
    assert g.fb_px_m == pytest.approx(10.6)
    z, th = g.render()
    z0, th0 = render_planar_target(g.K, 424, 240, 0.8, 30.0, 0.0, "board", 0.6, 0.9, 3.0)
    assert np.array_equal(z, z0, equal_nan=True) and np.array_equal(th, th0, equal_nan=True)
    zs, _ = g.render((0.05, -0.05))                                 # a narrower board
    assert np.sum(zs < 2.9) < np.sum(z < 2.9)
    # the baseline defaults to the D435's; pitch and yaw to 0
    cam = {k: v for k, v in CAMERA.items() if k != "baseline_m"}
    w = CaptureGeometry.from_capture_set_entry(cam, {"id": "w", "target": {"kind": "wall", "distance_m": 2.0}})
    assert w.baseline_m == nm.D435.baseline_m and w.yaw_deg == 0.0 and w.background_m is None


@pytest.mark.parametrize("camera, capture, msg", [
    ({k: v for k, v in CAMERA.items() if k != "fx"}, WALL, "camera is missing required key 'fx'"),
    (CAMERA, {"target": WALL["target"]}, "'id'"),
    (CAMERA, {"id": "x"}, "x: capture is missing a 'target'"),
    (CAMERA, {"id": "x", "target": {"kind": "disc", "distance_m": 1.0}}, "x: target 'kind'"),
    (CAMERA, {"id": "x", "target": {"kind": "board", "distance_m": 1.0, "width_m": 0.5}}, "height_m"),
    (CAMERA, {"id": "x", "target": {"kind": "wall", "distance_m": -1.0}}, "distance_m"),
    (CAMERA, {"id": "x", "background_m": 0.5, "target": {"kind": "board", "distance_m": 1.0, "width_m": 0.5,
                                                         "height_m": 0.5}}, "behind the target"),
    (CAMERA, {"id": "x", "target": {"kind": "wall", "distance_m": 1.0, "yaw_deg": 95.0}}, "yaw_deg"),
    (dict(CAMERA, depth_scale=1.0), WALL, "depth_scale"),
    (dict(CAMERA, width=424.5), WALL, "width must be an integer"),
])
def test_bad_entries_are_named_errors(camera, capture, msg):
    with pytest.raises(ValueError, match=msg):
        CaptureGeometry.from_capture_set_entry(camera, capture)


def test_wall_regions_left_band_is_the_disparity_plus_margin():
    g = CaptureGeometry.from_capture_set_entry(CAMERA, WALL)
    r = g.regions()
    assert r.dtype == np.int8 and r.shape == (240, 424)
    # f B / z = 10.6 px, margin 10 px at 424 wide: columns u < 20.6 -> 0..20
    band = np.flatnonzero((r == cd.REGION_LEFT_BAND).all(axis=0))
    assert band.tolist() == list(range(21))
    assert (r[:, 21:] == cd.REGION_INTERIOR).all()
    r5 = g.regions(left_margin_px=4.0)
    assert np.flatnonzero((r5 == cd.REGION_LEFT_BAND).all(axis=0)).tolist() == list(range(15))


def test_board_regions():
    g = CaptureGeometry.from_capture_set_entry(CAMERA, dict(BOARD, target=dict(BOARD["target"], distance_m=1.5,
                                                                               yaw_deg=0.0)))
    r = g.regions()
    z, _ = g.render()
    board = z < 2.9
    # the board's columns at 1.5 m: |u - 211.5| <= 0.3 * 212 / 1.5 = 42.4 -> 170..253
    row = r[120]
    cols_board = np.flatnonzero(board[120])
    assert cols_board.min() == 170 and cols_board.max() == 253
    # edge zones: 2.5 sigma_L (0.108 m = 15.3 px) + 6 px each side of the left edge at u = 169.1
    left = np.flatnonzero(row == cd.REGION_EDGE_LEFT)
    assert left.min() == pytest.approx(169.1 - 15.3 - 6, abs=1.01) and left.max() == pytest.approx(169.1 + 15.3 + 6,
                                                                                                     abs=1.01)
    right = np.flatnonzero(row == cd.REGION_EDGE_RIGHT)
    assert right.min() > left.max() and right.max() == pytest.approx(253.9 + 0.1018 * 212 / 1.5 + 6, abs=1.01)
    interior = np.flatnonzero(row == cd.REGION_INTERIOR)
    assert interior.size and interior.min() > left.max() and interior.max() < right.min()
    assert (row[:100] == cd.REGION_BACKGROUND)[40:100].all()
    # the top and bottom edges (rows 119.5 -/+ 0.45 * 212 / 1.5 = 63.6: the board's rows are 56..183) are
    # left out, 6 rows on either side, over the board's width
    assert np.flatnonzero(board[:, 200])[[0, -1]].tolist() == [56, 183]
    assert (r[50:62, 200] == cd.REGION_NONE).all() and (r[178:190, 200] == cd.REGION_NONE).all()
    assert r[49, 200] == r[190, 200] == cd.REGION_BACKGROUND and r[62, 200] == r[177, 200] == cd.REGION_INTERIOR
    assert r[120, 200] == cd.REGION_INTERIOR and r[30, 200] == cd.REGION_BACKGROUND
    # the background's own left band: f B / 3 + 10 = 13.5 px
    assert (r[:, :14] == cd.REGION_LEFT_BAND).all() and (r[:, 14] != cd.REGION_LEFT_BAND).all()
    assert set(np.unique(r)) <= set(range(6)) and set(cd.REGION_NAMES) == {1, 2, 3, 4, 5}
    # without a background the surroundings are no hit
    nb = CaptureGeometry.from_capture_set_entry(CAMERA, dict(BOARD, background_m=None)).regions()
    assert not (nb == cd.REGION_BACKGROUND).any() and (nb == cd.REGION_NONE).any()


def test_interior_is_the_interior_region_inside_the_mask():
    g = CaptureGeometry.from_capture_set_entry(CAMERA, dict(BOARD, target=dict(BOARD["target"], distance_m=1.5,
                                                                               yaw_deg=0.0)))
    c = CaptureData.from_units(g, np.full((1, 240, 424), 1500, dtype=np.uint16))
    m, z = c.interior()
    assert np.array_equal(m, g.regions() == cd.REGION_INTERIOR)      # the 3 m background is never interior
    assert np.isclose(z[120, 200], 1.5) and np.isclose(z[120, 50], 3.0) and not m[120, 50] and m[120, 200]
    mask = np.zeros((240, 424), dtype=bool)
    mask[100:140, 195:225] = True                                       # inside the board, off its edge zones
    mi, _ = CaptureData.from_units(g, c.has_data().astype(np.uint16) * 1500, mask=mask).interior()
    assert np.array_equal(mi, m & mask) and mi.sum() == 40 * 30
    assert not c.interior(max_depth_m=1.0)[0].any()                   # every true depth is beyond 1 m
    for bad in (0.0, -1.0, float("nan"), "far"):
        with pytest.raises(ValueError, match="max_depth_m"):
            c.interior(max_depth_m=bad)


def test_capture_data_from_units():
    g = CaptureGeometry.from_capture_set_entry(CAMERA, WALL)
    units = np.full((2, 240, 424), 1000, dtype=np.uint16)
    units[0, 0, 0] = 0
    c = CaptureData.from_units(g, units)
    assert c.depth_m.shape == (2, 240, 424) and c.depth_m.dtype == np.float64 and c.n_frames == 2
    assert math.isnan(c.depth_m[0, 0, 0]) and c.depth_m[1, 0, 0] == 1.0 and c.id == g.id
    assert CaptureData.from_units(g, units[0]).n_frames == 1
    with pytest.raises(ValueError, match="shape"):
        CaptureData.from_units(g, units[:, :, :100])
    with pytest.raises(ValueError, match="integers"):
        CaptureData.from_units(g, units.astype(float))
    with pytest.raises(ValueError, match="metres"):
        CaptureData(g, units.astype(float) + 1.0)
    with pytest.raises(ValueError, match="<= 0"):
        CaptureData(g, np.zeros((1, 240, 424)))
    with pytest.raises(ValueError, match="metres"):
        CaptureData.from_units(g, np.full((1, 240, 424), 200_000, dtype=np.int64))     # 200 m: not millimetres


def test_capture_data_keeps_units_and_gives_the_same_metres():
    """Frames from units are kept as units; every accessor gives what the metres in float64 would."""
    g = CaptureGeometry.from_capture_set_entry(CAMERA, WALL)
    rng = np.random.default_rng(4)
    units = rng.integers(0, 3000, (3, 240, 424)).astype(np.uint16)
    metres = np.where(units > 0, units.astype(np.float64) * g.depth_scale, np.nan)
    c = CaptureData.from_units(g, units)
    units[:] = 7                                                   # the caller's array changes afterwards
    m = rng.random((240, 424)) < 0.3
    np.testing.assert_array_equal(c.depth_m, metres)
    np.testing.assert_array_equal(c.frame_m(2), metres[2])
    np.testing.assert_array_equal(c.pixels_m(m), metres[:, m])
    np.testing.assert_array_equal(c.has_data(), np.isfinite(metres))
    f = CaptureData(g, metres)                                     # the same frames given in metres
    np.testing.assert_array_equal(f.pixels_m(m), c.pixels_m(m))
    np.testing.assert_array_equal(f.has_data(), c.has_data())
    part = c.with_geometry(dataclasses.replace(g, id="part"), m)
    assert part.id == "part" and part.mask is not None and part.mask.sum() == m.sum() and part.n_frames == 3
    np.testing.assert_array_equal(part.depth_m, metres)
    with pytest.raises(ValueError, match="same image size"):
        c.with_geometry(CaptureGeometry.from_capture_set_entry(dict(CAMERA, width=212, height=120), WALL), None)


@pytest.mark.parametrize("capture", [WALL, BOARD, dict(WALL, target=dict(WALL["target"], yaw_deg=45.0))])
def test_simulate_capture_is_the_reference_simulation_draw_for_draw(capture):
    g = CaptureGeometry.from_capture_set_entry(CAMERA, capture)
    t = g.target
    r1, r2 = np.random.default_rng(3), np.random.default_rng(3)
    a = simulate_capture(g, 5, r1)
    b = simulate_target_frames(g.K, 424, 240, t["distance_m"], 5, r2, yaw_deg=t["yaw_deg"], kind=t["kind"],
                               width_m=t.get("width_m"), height_m=t.get("height_m"), background_m=g.background_m)
    assert a.dtype == np.uint16 and a.shape == (5, 240, 424)
    z, _ = g.render()
    near = ~(z > 20.0)               # a steep wall reaches far beyond the uint16 range: no data there
    assert np.array_equal(a[:, near], b[:, near]) and (a[:, z > 65.535] == 0).all()
    assert r1.random() == r2.random()                               # the same number of draws
    # the paper's noise at the image centre
    if capture is WALL:
        sd = (a[:, 100:140, 190:230].astype(float) * 0.001).std(axis=0, ddof=1).mean()
        assert sd == pytest.approx(math.sqrt(nm.axial_sigma(1.0, 0.0) ** 2 + 1e-6 / 12), rel=0.1)


def test_effects_see_the_documented_context_and_draw_from_the_generator():
    g = CaptureGeometry.from_capture_set_entry(CAMERA, BOARD)
    seen = []

    def probe(z, theta, rng, ctx):
        seen.append(dict(ctx))
        assert not ctx["z_true"].flags.writeable and not ctx["regions"].flags.writeable
        return z + rng.normal(0.0, 0.001, z.shape)

    a = simulate_capture(g, 3, np.random.default_rng(4), effects=[probe])
    assert [c["index"] for c in seen] == [0, 1, 2]
    c = seen[1]
    assert {"K", "width", "height", "index", "depth_scale", "z_true", "baseline_m", "capture_id", "regions",
            "z_ref"} <= set(c)
    assert c["capture_id"] == g.id and c["baseline_m"] == 0.05 and c["depth_scale"] == 0.001
    assert np.array_equal(c["regions"], g.regions())
    # boards move their edges every frame: each frame's z_true is its own
    assert not np.array_equal(seen[0]["z_true"], seen[1]["z_true"], equal_nan=True)
    assert not np.array_equal(a, simulate_capture(g, 3, np.random.default_rng(4)))
    with pytest.raises(ValueError, match="not callable"):
        simulate_capture(g, 1, np.random.default_rng(0), effects=["dropout"])
    with pytest.raises(ValueError, match="Generator"):
        simulate_capture(g, 1, 0)
    with pytest.raises(ValueError, match="n_frames"):
        simulate_capture(g, 0, np.random.default_rng(0))


def test_far_pixels_of_a_steep_wall_are_no_data():
    g = CaptureGeometry.from_capture_set_entry(CAMERA, {"id": "steep", "target": {"kind": "wall", "distance_m": 0.5,
                                                                                  "yaw_deg": 60.0}})
    z, _ = g.render()
    far = z > 65.535
    assert far.any()
    d = simulate_capture(g, 1, np.random.default_rng(0), effects=[lambda zz, t, r, c: zz])
    assert (d[0][far] == 0).all() and (d[0][z < 5] > 0).all()


def test_simulate_target_frames_takes_effects():
    from noise_model.sim.effects import invalid_band

    K = nm.D435.intrinsics(424, 240)
    plain = simulate_target_frames(K, 424, 240, 1.0, 2, np.random.default_rng(5))
    banded = simulate_target_frames(K, 424, 240, 1.0, 2, np.random.default_rng(5), effects=[invalid_band(4.0)])
    assert (banded[:, :, :15] == 0).all() and np.array_equal(banded[:, :, 15:], plain[:, :, 15:])
    assert np.array_equal(simulate_target_frames(K, 424, 240, 1.0, 2, np.random.default_rng(5), effects=()), plain)
