"""--bag-out: the GridMap read back (with rosbags, from the definitions the bag carries) equals the map's
to_grid_map() cell for cell in both layouts; the Grid places the box where it is; the output policy."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from elevmap.cli import main
from elevmap.commands.bag import BagOutput
from elevmap.pipeline import MappingConfig, run_mapping
from elevmap.ros.bagout import BAG_LAYERS, GRID_TOPIC, MAP_TOPIC
from elevmap.ros.convert import stamp_seconds
from elevmap.ros.msgs import GRID_MAP_ROS1_MD5
from elevmap.sources.rosbag import RosbagSource
from rosbag_scenes import BOX_TOP_M, BOX_XY, N_FRAMES, frame_stamps, unmappable_extras, write_bag

CONFIG = MappingConfig(length_m=4.0, resolution_m=0.04, follow=False)


@pytest.fixture(scope="module")
def scene_bag(tmp_path_factory):
    return write_bag(tmp_path_factory.mktemp("in") / "scene.bag", "bag")


OUTPUTS = ("map.bag", "map.mcap", "map_db3")


@pytest.fixture(scope="module")
def mapped(tmp_path_factory, scene_bag):
    """One mapping run of the scene feeding a writer of each kind at 5 Hz: (the map, the output folder, summaries)."""
    folder = tmp_path_factory.mktemp("out")
    src = RosbagSource(scene_bag)
    outs = [BagOutput(folder / name, map_frame=src.map_frame, rate_hz=5.0) for name in OUTPUTS]
    emap = run_mapping(src, CONFIG, show_progress=False, callbacks=outs)["map"]
    return emap, folder, {name: out.finish(emap) for name, out in zip(OUTPUTS, outs)}


def _read(path):
    """{topic: [(bag time ns, message)]} and the connections, decoded with the bag's own definitions."""
    out = {}
    with AnyReader([path]) as reader:
        conns = {c.topic: c for c in reader.connections}
        for c, t, raw in reader.messages():
            out.setdefault(c.topic, []).append((t, reader.deserialize(raw, c.msgtype)))
    return out, conns


@pytest.mark.parametrize("name, ros1", [("map.bag", True), ("map.mcap", False), ("map_db3", False)])
def test_grid_map_read_back_equals_to_grid_map(mapped, name, ros1):
    emap, folder, written = mapped
    assert written[name]["ros_version"] == (1 if ros1 else 2)
    assert sorted(p.name for p in folder.iterdir()) == sorted(OUTPUTS)          # nothing temporary left
    msgs, conns = _read(folder / name)
    if ros1:
        assert conns[MAP_TOPIC].digest == GRID_MAP_ROS1_MD5
    # 5 Hz over 0.7 s of 10 Hz frames: at 0, 0.2, 0.4, 0.6 s, then the final map at 0.7 s
    stamps = [stamp_seconds((m.info.header if ros1 else m.header).stamp) for _, m in msgs[MAP_TOPIC]]
    assert stamps == pytest.approx([frame_stamps()[k] for k in (0, 2, 4, 6, 7)])
    assert len(msgs["/tf"]) == N_FRAMES and len(msgs[GRID_TOPIC]) == len(stamps)
    last = msgs[MAP_TOPIC][-1][1]
    expected = emap.to_grid_map(BAG_LAYERS, frame_id="map")
    assert list(last.layers) == list(BAG_LAYERS) and list(last.basic_layers) == ["elevation", "variance"]
    header = last.info.header if ros1 else last.header
    assert header.frame_id == "map" and hasattr(last.info, "header") == ros1 and hasattr(last, "header") != ros1
    assert (last.info.resolution, last.info.length_x, last.info.pose.position.x) == (0.04, 4.0, 0.0)
    for name_, arr in zip(last.layers, last.data):
        assert [d.label for d in arr.layout.dim] == ["column_index", "row_index"]
        np.testing.assert_array_equal(arr.data, expected["data"][name_])          # NaN in the same cells
    assert np.isnan(expected["data"]["elevation"]).any() and np.isfinite(expected["data"]["elevation"]).any()


def test_grid_places_the_box_at_its_world_position(mapped):
    msgs, _ = _read(mapped[1] / "map.mcap")
    grid = msgs[GRID_TOPIC][-1][1]
    names = [f.name for f in grid.fields]
    k = names.index("elevation")
    n_fields = grid.cell_stride // 4
    cells = np.asarray(grid.data, np.uint8).view("<f4").reshape(-1, grid.column_count, n_fields)[..., k]
    j, i = np.nonzero(cells > BOX_TOP_M - 0.01)                      # row j along y, column i along x
    x = grid.pose.position.x + (i + 0.5) * grid.cell_size.x
    y = grid.pose.position.y + (j + 0.5) * grid.cell_size.y
    # the box top's cells, with the box's edge smeared into its shadow (at most 4 cells beyond its far side)
    assert x.size >= 50
    assert np.all((x > BOX_XY[0] - 0.2) & (x < BOX_XY[0] + 0.2 + 0.17) & (np.abs(y - BOX_XY[1]) < 0.2))
    i0 = int((BOX_XY[0] - grid.pose.position.x) / grid.cell_size.x)
    j0 = int((BOX_XY[1] - grid.pose.position.y) / grid.cell_size.y)
    assert cells[j0, i0] == pytest.approx(BOX_TOP_M, abs=0.005)
    assert cells[j0, i0 - 10] == pytest.approx(0.0, abs=0.005)              # the floor 0.4 m before the box


def test_cli_run_bag_out_and_the_output_policy(tmp_path, scene_bag, capsys):
    out = tmp_path / "out.bag"
    assert main(["run", str(scene_bag), "--bag-out", str(out), "--map-rate", "1", "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert f"wrote {out} (2 maps)" in text and "8 frames mapped, 0 skipped" in text
    msgs, conns = _read(out)
    assert conns[MAP_TOPIC].msgtype == "grid_map_msgs/msg/GridMap" and len(msgs[MAP_TOPIC]) == 2
    before = out.read_bytes()
    assert main(["run", str(scene_bag), "--bag-out", str(out), "--no-progress"]) == 2
    assert "exists; pass --overwrite" in capsys.readouterr().err and out.read_bytes() == before
    assert main(["run", str(scene_bag), "--bag-out", str(scene_bag), "--overwrite", "--no-progress"]) == 2
    assert "is an input of this run" in capsys.readouterr().err
    assert main(["run", str(scene_bag), "--bag-out", str(tmp_path / "x.txt"), "--no-progress"]) == 2
    assert "NAME.bag (ROS 1), NAME.mcap (ROS 2)" in capsys.readouterr().err
    # a run that fails (every frame skipped) leaves no output and nothing temporary
    bad = tmp_path / "bad.mcap"
    assert main(["run", str(scene_bag), "--bag-out", str(bad), "--map-frame", "odom", "--no-progress"]) == 2
    assert "every depth frame was skipped" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.bag"]
    assert main(["run", str(scene_bag), "--map-rate", "2", "--no-progress"]) == 2
    assert "--map-rate goes with --bag-out or --foxglove" in capsys.readouterr().err


def test_cli_bag_info_says_what_is_missing(tmp_path, capsys):
    path = write_bag(tmp_path / "skips.bag", "bag", extra=unmappable_extras)
    assert main(["bag-info", str(path), "--json", str(tmp_path / "info.json")]) == 1
    text = capsys.readouterr().out
    assert "/rear/depth/image_rect_raw" in text and "camera info: MISSING" in text
    assert "cannot be mapped: no camera info" in text
    assert "transforms: map -> base_link -> camera_link -> camera_depth_optical_frame" in text
    assert "1 of 2 depth topic(s) can be mapped" in text
    assert (tmp_path / "info.json").is_file()


def test_map_rate_gate_with_interleaved_cameras():
    from elevmap.commands.bag import _RateGate

    gate = _RateGate(2.0)
    stamps = [0.0, -0.01, 0.1, 0.09, 0.5, 0.49, 0.99, 1.0, 0.6, -0.6]
    assert [gate(s) for s in stamps] == [True, False, False, False, True, False, False, True, False, True]
    with pytest.raises(ValueError, match="--map-rate must be a positive number"):
        _RateGate(0.0)
