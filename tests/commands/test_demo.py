"""The noise-model demo and the rerun helpers of elevmap.viz: content, statistics and atomic writes."""

from __future__ import annotations

import os
from collections import defaultdict

import numpy as np
import pytest
from rerun.chunk import RrdReader
from scipy.spatial.transform import Rotation

import noise_model as nm
from elevmap.commands import demo
from elevmap import viz

DT = {6: np.uint8, 7: np.int8, 8: np.uint16, 9: np.int16, 10: np.uint32, 11: np.int32, 34: np.float32,
      35: np.float64}


def read_static(path, entity: str, components: list[str]) -> dict:
    """Last logged value of each component of ``entity`` (pyarrow arrays), read with RrdReader."""
    out = {}
    for ch in RrdReader(path).stream().filter(content=entity, components=components):
        rb = ch.to_record_batch()
        for c in components:
            if c in rb.schema.names:
                col = rb.column(c)
                for r in range(rb.num_rows):
                    if col[r].is_valid:
                        out[c] = col[r].values
    return out


def entity_components(path) -> dict:
    ents = defaultdict(set)
    for ch in RrdReader(path).stream():
        ents[ch.entity_path].update(ch.to_record_batch().schema.names)
    return ents


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("demo")
    path = folder / "demo.rrd"
    summary = demo.run_noise_demo(path, seed=0, show_progress=False)
    return path, summary


# -- the demo ----------------------------------------------------------------------------------------
def test_demo_writes_a_small_complete_file(demo_run):
    path, summary = demo_run
    assert path.is_file()
    size = path.stat().st_size
    assert size > 0 and size == summary["file_size_bytes"]
    assert size < 5_000_000, f"demo.rrd is {size / 1e6:.1f} MB"
    assert summary["path"] == str(path.resolve())
    assert os.listdir(path.parent) == ["demo.rrd"], "temporary files left behind"
    assert (path.stat().st_mode & 0o777) != 0o600, "file kept mkstemp's private mode"


def test_demo_measured_noise_matches_model(demo_run):
    _, summary = demo_run
    caps = summary["captures"]
    assert [(c["distance_m"], c["yaw_deg"]) for c in caps] == [(1.0, 0.0), (1.0, 45.0), (2.0, 0.0), (2.0, 45.0)]
    for c in caps:
        assert c["n_samples"] > 100_000
        assert abs(c["measured_std_m"] / c["model_sigma_m"] - 1.0) < 0.05, c
        assert abs(c["normalized_residual_std"] - 1.0) < 0.05, c
    # at 0 deg the model's sigma_z is 5.74 mm at 1 m and 18.3 mm at 2 m (paper's coefficients)
    assert caps[0]["model_sigma_m"] == pytest.approx(nm.axial_sigma(1.0, 0.0), rel=1e-6)
    assert caps[2]["model_sigma_m"] == pytest.approx(nm.axial_sigma(2.0, 0.0), rel=1e-6)
    assert [c["pose_cov"] for c in caps] == [False, False, False, True]
    assert summary["points_logged"] == sum(c["points_logged"] for c in caps) == 4 * 1500


def test_demo_rrd_reads_back(demo_run):
    path, summary = demo_run
    ents = entity_components(path)
    assert "ViewCoordinates:xyz" in ents["/world"]
    for i in range(4):
        cam = f"/world/camera_{i}"
        assert {"Transform3D:translation", "Transform3D:quaternion"} <= ents[cam]
        assert {"DepthImage:buffer", "DepthImage:format", "Pinhole:image_from_camera",
                "Pinhole:resolution"} <= ents[f"{cam}/depth"]
        assert {"Ellipsoids3D:centers", "Ellipsoids3D:half_sizes",
                "Ellipsoids3D:quaternions"} <= ents[f"/world/points_cov/camera_{i}/ellipsoids"]
        assert "Points3D:positions" in ents[f"/world/points_cov/camera_{i}/points"]
    assert "TextDocument:text" in ents["/notes"]
    assert "LineStrips2D:strips" in ents["/plots/sigma_z_vs_z/curves"]

    # the depth image of camera 0 (1 m, fronto-parallel): 424x240 uint16 mm around 1000
    c = read_static(path, "/world/camera_0/depth", ["DepthImage:buffer", "DepthImage:format", "DepthImage:meter",
                                                    "Pinhole:image_from_camera", "Pinhole:resolution"])
    fmt = c["DepthImage:format"][0].as_py()
    depth = (c["DepthImage:buffer"][0].values.to_numpy(zero_copy_only=False)
             .view(DT[fmt["channel_datatype"]]).reshape(fmt["height"], fmt["width"]))
    assert depth.shape == (240, 424) and depth.dtype == np.uint16
    assert abs(float(np.median(depth)) - 1000.0) < 2.0
    assert c["DepthImage:meter"][0].as_py() == pytest.approx(1000.0)
    K = c["Pinhole:image_from_camera"].flatten().to_numpy().reshape(3, 3).T     # stored column-major
    np.testing.assert_allclose(K, nm.D435.intrinsics(424, 240), rtol=1e-6)
    np.testing.assert_allclose(c["Pinhole:resolution"].flatten().to_numpy(), [424, 240])

    # camera 3 sits at (0, -18, 1) m looking along world +x; its ellipsoids are 2-sigma, world frame
    t = read_static(path, "/world/camera_3", ["Transform3D:translation", "Transform3D:quaternion"])
    np.testing.assert_allclose(t["Transform3D:translation"].flatten().to_numpy(), [0.0, -18.0, 1.0], atol=1e-6)
    R = Rotation.from_quat(t["Transform3D:quaternion"].flatten().to_numpy()).as_matrix()
    np.testing.assert_allclose(R, demo.R_WORLD_CAM, atol=1e-6)
    e = read_static(path, "/world/points_cov/camera_3/ellipsoids",
                    ["Ellipsoids3D:centers", "Ellipsoids3D:half_sizes"])
    centers = e["Ellipsoids3D:centers"].flatten().to_numpy().reshape(-1, 3)
    half = e["Ellipsoids3D:half_sizes"].flatten().to_numpy().reshape(-1, 3)
    assert len(centers) == len(half) == 1500
    assert np.all(centers[:, 0] > 0.3) and np.all(np.abs(centers[:, 1] + 18.0) < 6.0)
    assert np.all(half > 0)


# -- atomic writes -----------------------------------------------------------------------------------
@pytest.mark.parametrize("exc", [RuntimeError, KeyboardInterrupt])
def test_failed_run_leaves_no_file(tmp_path, monkeypatch, exc):
    def boom(*args, **kwargs):
        raise exc("simulated failure while logging")

    monkeypatch.setattr(viz, "log_covariance_ellipsoids", boom)
    path = tmp_path / "demo.rrd"
    with pytest.raises(exc):
        demo.run_noise_demo(path, seed=0, show_progress=False, n_frames=1)
    assert not path.exists()
    assert os.listdir(tmp_path) == [], "a partial or temporary file was left behind"


def test_failed_run_keeps_existing_file(tmp_path, monkeypatch):
    path = tmp_path / "demo.rrd"
    path.write_bytes(b"the user's own recording")
    calls = {"n": 0}
    real = viz.log_points

    def fail_on_third_capture(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("simulated failure")
        return real(*args, **kwargs)

    monkeypatch.setattr(viz, "log_points", fail_on_third_capture)
    with pytest.raises(RuntimeError):
        demo.run_noise_demo(path, seed=0, show_progress=False, n_frames=1)
    assert path.read_bytes() == b"the user's own recording"
    assert os.listdir(tmp_path) == ["demo.rrd"]


def test_successful_recording_replaces_existing_file(tmp_path):
    path = tmp_path / "plot.rrd"
    path.write_bytes(b"old")
    os.chmod(path, 0o640)
    with viz.open_recording(path, "elevmap_test") as rec:
        for k in range(5):
            viz.set_time(rec, "frame", sequence=k)
            viz.log_scalar(rec, "plots/value", 0.5 * k)
        assert path.read_bytes() == b"old", "destination touched before the recording was finalised"
        parts = [n for n in os.listdir(tmp_path) if n != "plot.rrd"]
        assert len(parts) == 1 and parts[0].startswith(".plot.rrd.") and parts[0].endswith(".part")
    assert path.stat().st_mode & 0o777 == 0o640
    values = {}
    for ch in RrdReader(path).stream().filter(content="/plots/value", components=["Scalars:scalars"]):
        rb = ch.to_record_batch()
        for r in range(rb.num_rows):
            values[int(rb.column("frame")[r].as_py())] = rb.column("Scalars:scalars")[r].values.to_numpy()[0]
    assert values == {k: 0.5 * k for k in range(5)}
    assert os.listdir(tmp_path) == ["plot.rrd"]


def test_float_depth_and_camera_pose(tmp_path):
    path = tmp_path / "cam.rrd"
    K = nm.D435.intrinsics(424, 240)
    T_world_cam = np.eye(4)
    T_world_cam[:3, :3] = demo.R_WORLD_CAM
    T_world_cam[:3, 3] = [1.0, 2.0, 3.0]
    depth_m = np.full((240, 424), 1.5)
    depth_m[0, 0] = np.nan
    with viz.open_recording(path, "elevmap_test") as rec:
        viz.log_camera(rec, "world/cam", K, 424, 240, T_parent_cam=T_world_cam)
        viz.log_depth(rec, "world/cam", depth_m, static=True)
        with pytest.raises(ValueError):
            viz.log_depth(rec, "world/cam", np.full((240, 424), 1500, np.uint16))   # units need meter=
    c = read_static(path, "/world/cam", ["DepthImage:buffer", "DepthImage:format", "DepthImage:meter",
                                         "Transform3D:translation", "Pinhole:image_from_camera"])
    fmt = c["DepthImage:format"][0].as_py()
    img = (c["DepthImage:buffer"][0].values.to_numpy(zero_copy_only=False)
           .view(DT[fmt["channel_datatype"]]).reshape(fmt["height"], fmt["width"]))
    assert img.dtype == np.float32 and img[0, 0] == 0.0 and img[1, 1] == np.float32(1.5)
    assert c["DepthImage:meter"][0].as_py() == 1.0
    np.testing.assert_allclose(c["Transform3D:translation"].flatten().to_numpy(), [1.0, 2.0, 3.0])


def test_open_recording_rejects_bad_targets(tmp_path):
    with pytest.raises(ValueError):
        viz.open_recording(None, "elevmap_test")
    with pytest.raises(FileNotFoundError):
        viz.open_recording(tmp_path / "missing" / "x.rrd", "elevmap_test")
    with pytest.raises(IsADirectoryError):
        viz.open_recording(tmp_path, "elevmap_test")
    assert os.listdir(tmp_path) == []


# -- pure helpers --------------------------------------------------------------------------------------
def test_ellipsoid_parameters_reconstruct_covariances():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(200, 3, 3))
    covs = A @ np.swapaxes(A, 1, 2) * 1e-4                   # SPD [m^2]
    covs[0] = np.diag([4e-4, 1e-6, 0.0])                     # degenerate: one zero axis
    half, q = viz.ellipsoid_parameters(covs, n_sigma=2.0)
    R = Rotation.from_quat(q).as_matrix()
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    rebuilt = R @ (((half / 2.0) ** 2)[:, :, None] * np.swapaxes(R, 1, 2))
    np.testing.assert_allclose(rebuilt, covs, atol=1e-12)
    np.testing.assert_allclose(np.sort(half[0]), [0.0, 2e-3, 4e-2], atol=1e-12)


def test_colormap():
    c = viz.colormap([0.0, 1.0, np.nan, -5.0, 5.0], 0.0, 1.0, name="viridis")
    assert c.dtype == np.uint8 and c.shape == (5, 3)
    np.testing.assert_array_equal(c[0], [68, 1, 84])
    np.testing.assert_array_equal(c[1], [253, 231, 37])
    np.testing.assert_array_equal(c[2], [128, 128, 128])
    np.testing.assert_array_equal(c[3], c[0])                # clipped
    t = viz.colormap([0.002, 0.02, 0.2], 0.002, 0.2, log=True)
    np.testing.assert_array_equal(t[0], [48, 18, 59])
    np.testing.assert_array_equal(t[2], [122, 4, 3])
    np.testing.assert_allclose(t[1], [164, 252, 60], atol=3)   # geometric midpoint -> middle of turbo
    with pytest.raises(ValueError):
        viz.colormap([1.0], 1.0, 1.0)
