"""``elevmap captures``: capture sets from static stretches, on a simulated wall and floor with known planes
and on the genuine aims_slam recording (REALDATA)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from elevmap.cli import main
from elevmap.commands.captures import parse_frame_ranges, parse_intrinsics, run_captures
from elevmap.sources.captures import read_capture_set
from noise_model.analysis.capture_data import CaptureData

W, H = 160, 120
FX = FY = 110.0
CX, CY = 79.5, 59.5
#: The true planes in the camera frame, n . p = offset with n pointing away from the camera.
_WALL_N = np.array([0.40, -0.30, 0.866]) / np.linalg.norm([0.40, -0.30, 0.866])
WALL = (_WALL_N, 1.6 * _WALL_N[2])                                   # meets the optical axis at 1.6 m
FLOOR = (np.array([0.0, math.cos(math.radians(20)), math.sin(math.radians(20))]), 0.6)  # 0.6 m below, 20 deg down
K_NOISE = 0.003          # temporal sigma = K_NOISE z^2 [m], as a real D435's (sigma_d ~ 0.06 px at f B = 19 px m)
BOX = (slice(95, 112), slice(20, 45))     # a box standing on the floor: 8 cm in front of it


def _plane_depth(n, d, shift=0.0):
    u, v = np.meshgrid((np.arange(W) - CX) / FX, (np.arange(H) - CY) / FY)
    den = n[0] * u + n[1] * v + n[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (d + shift) / den
    return np.where(den > 0, z, np.inf)


def _scene(wall_shift=0.0):
    """True depth [m] (inf = nothing), which surface each pixel sees (1 wall, 2 floor, 3 box)."""
    zw, zf = _plane_depth(*WALL, wall_shift), _plane_depth(*FLOOR)
    z = np.minimum(zw, zf)
    label = np.where(zw <= zf, 1, 2)
    z = np.where(z < 5.0, z, np.inf)
    label[~np.isfinite(z)] = 0
    box = np.zeros((H, W), dtype=bool)
    box[BOX] = True
    box &= label == 2
    z[box] -= 0.08
    label[box] = 3
    return z, label


def _frames(rng, n=12, static=(2, 9)):
    """uint16 mm frames: frames static[0]..static[1] one scene, the others with the wall 0.3 m nearer (a
    camera that moved); temporal noise K_NOISE z^2, a static error of half that, 3 % dropouts."""
    z0, label = _scene()
    z1, _ = _scene(-0.3)
    fixed = rng.normal(size=(H, W)) * 0.5 * K_NOISE * z0 ** 2
    out = []
    for k in range(n):
        zt = z0 if static[0] <= k <= static[1] else z1
        zt = np.where(np.isfinite(zt), zt, 0.0)
        z = zt + fixed + rng.normal(size=(H, W)) * K_NOISE * zt ** 2
        units = np.where((zt > 0) & (rng.random((H, W)) > 0.03), np.round(z / 0.001), 0)
        out.append(units.astype(np.uint16))
    return np.stack(out), label


@pytest.fixture
def recording(tmp_path, rng):
    """A PNG folder (0.png ... 11.png, 16-bit mm) with its intrinsics file, as a D435 recorder writes it."""
    import cv2

    frames, label = _frames(rng)
    folder = tmp_path / "rec"
    (folder / "depth").mkdir(parents=True)
    for k, f in enumerate(frames):
        assert cv2.imwrite(str(folder / "depth" / f"{k}.png"), f)
    (folder / "camera_intrinsic.json").write_text(json.dumps(
        {"width": W, "height": H, "intrinsic_matrix": [FX, 0, 0, 0, FY, 0, CX, CY, 1]}))
    return folder, frames, label


def _angle_deg(a, b):
    return math.degrees(math.acos(min(1.0, abs(float(np.dot(a, b)) / np.linalg.norm(a) / np.linalg.norm(b)))))


def test_a_simulated_wall_and_floor_are_found_written_and_read_back(recording, tmp_path):
    folder, frames, label = recording
    rep = run_captures(folder, "2-9", tmp_path / "set")
    cs = read_capture_set(tmp_path / "set")
    assert len(cs) == 2 and rep["captures"] == cs.ids == ["f2-9_plane1", "f2-9_plane2"]
    truth = {1: WALL, 2: FLOOR}
    seen = set()
    for cap in cs.captures:
        # the file's plane: normal towards the camera, offset its distance
        assert cap.kind == "plane" and cap.geometry == "fitted" and cap.is_fitted
        assert cap.target["normal"][2] < 0 and cap.target["offset_m"] > 0
        mask = cs.load_mask(cap.id)
        which = int(np.bincount(label[mask]).argmax())
        seen.add(which)
        n_true, d_true = truth[which]
        # refound within 0.3 deg and 2 mm (8 frames of ~5000-9000 pixels, sigma 1-8 mm)
        assert _angle_deg(cap.plane.normal, n_true) < 0.3
        assert cap.plane.offset_m == pytest.approx(d_true, abs=0.002)
        # the mask is that surface: at least 90 % of its pixels, nothing of the box standing on the floor
        surface = label == which
        assert (mask & surface).sum() >= 0.9 * surface.sum()
        assert (mask & ~surface).sum() <= 0.01 * mask.sum()
        assert not (mask & (label == 3)).any()
        # the round trip: the stretch's frames exactly as recorded, every pixel
        np.testing.assert_array_equal(cs.load_depth(cap.id), frames[2:10])
        # and what the diagnosis reads: the mask, fitted geometry, the plane
        cd = CaptureData.from_capture_entry(cs.camera, cap.to_dict(), cs.load_depth(cap.id), mask)
        assert cd.is_fitted and cd.n_frames == 8
        assert _angle_deg(cd.plane.normal, n_true) < 0.3
        # the stretch's temporal noise, measured: sigma = k z^2 with k = K_NOISE within 10 %
        assert cap["fit"]["temporal_sigma_per_z2"] == pytest.approx(K_NOISE, rel=0.1)
    assert seen == {1, 2}
    assert cs.camera["fx"] == FX and cs.camera["baseline_m"] == 0.05 and cs.extra["made_by"]["frames"] == [[2, 9]]


def test_frames_outside_the_stretch_are_not_used(recording, tmp_path):
    """Frames 0-1 and 10-11 saw the wall 0.3 m nearer: a stretch that takes one of them is not static."""
    folder, _, _ = recording
    rep = run_captures(folder, "1-9", tmp_path / "moved")
    dev = rep["stretches"][0]["frame_deviation_m"]
    assert dev[0] > 10 * np.median(dev[1:])          # the frame that moved stands out in the report


def test_captures_command_line(recording, tmp_path, capsys):
    folder, _, _ = recording
    out, js = tmp_path / "set", tmp_path / "found.json"
    assert main(["captures", str(folder / "depth"), "--frames", "2-9", "--out", str(out), "--json", str(js),
                 "--intrinsics", f"{FX},{FY},{CX},{CY}"]) == 0
    text = capsys.readouterr().out
    assert "f2-9_plane1" in text and "f2-9_plane2" in text
    assert json.loads(js.read_text())["captures"] == read_capture_set(out).ids
    # an existing set is not replaced without --overwrite; with it, it is
    assert main(["captures", str(folder), "--frames", "2-9", "--out", str(out)]) == 2
    assert "pass --overwrite" in capsys.readouterr().err
    assert main(["captures", str(folder), "--frames", "2-9", "--out", str(out), "--json", str(js), "--overwrite"]) == 0
    # the recording is never an output
    for rec, out_dir in ((folder / "depth", folder / "depth"), (folder, folder / "depth"), (folder / "depth", folder)):
        assert main(["captures", str(rec), "--frames", "2-9", "--out", str(out_dir), "--overwrite"]) == 2
        assert "holds an input" in (err := capsys.readouterr().err) or "holds other files" in err
    assert sorted(p.name for p in (folder / "depth").iterdir())[:2] == ["0.png", "1.png"]
    # a folder holding other files is not replaced
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    assert main(["captures", str(folder), "--frames", "2-9", "--out", str(tmp_path / "other"), "--overwrite"]) == 2
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"


@pytest.mark.parametrize("frames, match", [
    ("9-2", "at least 2 frames"), ("5-5", "at least 2 frames"), ("2-9,8-11", "overlap"), ("a-b", "not a range"),
    ("2-", "not a range"), ("10-15", r"recording has 12 frames \(0-11\)"),
])
def test_bad_frame_ranges(recording, tmp_path, frames, match):
    folder, _, _ = recording
    with pytest.raises(ValueError, match=match):
        run_captures(folder, frames, tmp_path / "set")
    assert not (tmp_path / "set").exists()


def test_frame_ranges_and_intrinsics_parse(tmp_path):
    assert parse_frame_ranges("141-156") == [(141, 156)]
    assert parse_frame_ranges("141-156, 1-8") == [(141, 156), (1, 8)]
    assert parse_intrinsics("383.8,383.8,321.7,238.2") == {"fx": 383.8, "fy": 383.8, "ppx": 321.7, "ppy": 238.2}
    with pytest.raises(ValueError, match="no such file"):
        parse_intrinsics(str(tmp_path / "none.json"))
    with pytest.raises(ValueError, match="four numbers"):
        parse_intrinsics("1,2,x,4")


def test_no_plane_is_an_error(tmp_path, rng):
    """A stretch of scattered depths (no surface covers 5 % of the image) writes nothing."""
    import cv2

    folder = tmp_path / "noise"
    folder.mkdir()
    for k in range(4):
        cv2.imwrite(str(folder / f"{k}.png"), rng.integers(300, 5000, (H, W)).astype(np.uint16))
    with pytest.raises(ValueError, match="no plane covers 5 %"):
        run_captures(folder, "0-3", tmp_path / "set", intrinsics={"fx": FX, "fy": FY, "ppx": CX, "ppy": CY})
    assert not (tmp_path / "set").exists()


@pytest.mark.realdata
def test_aims_slam_wall_and_floor_of_both_stretches(realdata, tmp_path):
    """The genuine recording: frames 141-156 (wall and floor) and 1-8 (floor), planes as its figures state."""
    import cv2

    root = realdata / "aims_slam_d435_robot_floor"
    fig = json.loads((root / "figures.json").read_text())
    intr = fig["intrinsics_estimate_640x480"]
    rep = run_captures(root / "depth", "141-156,1-8", tmp_path / "aims",
                       intrinsics={k: intr[k] for k in ("fx", "fy", "ppx", "ppy")})
    cs = read_capture_set(tmp_path / "aims")
    by_stretch = {tuple(s["frames"]): s["planes"] for s in rep["stretches"]}

    def match(planes, ref):
        best = min(planes, key=lambda p: _angle_deg(p["normal"], ref["normal"]))
        return best, _angle_deg(best["normal"], ref["normal"])

    for stretch, key in (((141, 156), "S1_wall"), ((141, 156), "S1_floor"), ((1, 8), "S0_floor")):
        ref = fig[key]["plane"]
        p, angle = match(by_stretch[stretch], ref)
        # within 0.5 deg and 5 mm of the figures' fits (the two stops' floors differ by 0.9 deg and 4.5 mm)
        assert angle < 0.5, (key, p["normal"], ref["normal"])
        assert p["offset_m"] == pytest.approx(ref["dist_m"], abs=0.005)
        # at least as many pixels as the figures' fit found in its region of the image
        assert p["pixels"] >= ref["inlier_pixels"]
        cap = cs.capture(p["id"])
        assert cap.is_fitted and np.dot(cap.target["normal"], ref["normal"]) > 0   # oriented as the figures
        # the frames as recorded, read back exactly
        depth = cs.load_depth(cap.id)
        for k in (0, depth.shape[0] - 1):
            png = cv2.imread(str(root / "depth" / f"{stretch[0] + k}.png"), cv2.IMREAD_UNCHANGED)
            np.testing.assert_array_equal(depth[k], png)
    # the stretch's own temporal noise, as a disparity sigma, is the figures' (wall ~0.08 px, floor ~0.06 px)
    wall, _ = match(by_stretch[(141, 156)], fig["S1_wall"]["plane"])
    floor, _ = match(by_stretch[(141, 156)], fig["S1_floor"]["plane"])
    assert 0.07 <= wall["sigma_d_px"] <= 0.095 and 0.05 <= floor["sigma_d_px"] <= 0.07


def test_the_physical_d435_wall_and_ground_are_refound(tmp_path):
    """The physical D435 (projector, infrared pair, matcher: its noise and static errors emerge) on a
    wall and the ground, 4 frames at 424x240: both planes within 0.5 deg and 5 mm of the scene's."""
    import cv2

    from noise_model.sim.scene import Scene, Target
    from noise_model.sim.stereo import StereoD435
    from noise_model.sim.targets import camera_extrinsics

    T_map_cam = camera_extrinsics((0.0, 0.0, 0.45), pitch_down_deg=30.0)
    wall = Target((1.6, 0.3, 1.0), 4.0, 2.0, 25.0)
    cam = StereoD435(424, 240, nthreads=1)
    frames = cam.frames(Scene([wall], ground_z=0.0), T_map_cam, 4, np.random.default_rng(0))
    folder = tmp_path / "stereo"
    folder.mkdir()
    for k, f in enumerate(frames):
        assert cv2.imwrite(str(folder / f"{k}.png"), f)
    K = cam.K
    rep = run_captures(folder, "0-3", tmp_path / "set", intrinsics={"fx": K[0, 0], "fy": K[1, 1], "ppx": K[0, 2],
                                                                     "ppy": K[1, 2]})
    R, c = T_map_cam[:3, :3], T_map_cam[:3, 3]
    yaw = math.radians(wall.yaw_deg)
    n_wall = np.array([math.cos(yaw), math.sin(yaw), 0.0])            # map frame, away from the camera
    truth = {"ground": (R.T @ np.array([0.0, 0.0, -1.0]), 0.45),
             "wall": (R.T @ n_wall, float(n_wall @ (np.array(wall.centre) - c)))}
    planes = rep["stretches"][0]["planes"]
    assert len(planes) == 2
    for name, (n, d) in truth.items():
        p = min(planes, key=lambda p: _angle_deg(-np.asarray(p["normal"]), n))
        assert _angle_deg(-np.asarray(p["normal"]), n) < 0.5, name
        assert p["offset_m"] == pytest.approx(d, abs=0.005), name
