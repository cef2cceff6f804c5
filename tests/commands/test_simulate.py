"""`elevmap simulate`: capture sets on a grid, read back per the spec, with the paper's noise."""

import numpy as np
import pytest

from elevmap.cli import main
from elevmap.commands.simulate import paper_grid, simulate_capture_set
from elevmap.sources.captures import read_capture_set
from noise_model import axial_sigma


def test_the_papers_grid():
    g = paper_grid()
    assert len(g) == 108 and g[0] == (0.4, 0.0) and g[-1] == (2.1, 75.0)
    assert sorted({d for d, _ in g}) == [round(0.4 + 0.1 * i, 2) for i in range(18)]


def test_capture_set_reads_back_with_the_papers_noise(tmp_path):
    out = tmp_path / "caps"
    simulate_capture_set(out, [(1.0, 0.0), (1.5, 45.0)], n_frames=40, seed=3, show_progress=False)
    cs = read_capture_set(out)
    assert [c["id"] for c in cs.captures] == ["board_z1.00_y00", "board_z1.50_y45"]
    d = cs.load_depth("board_z1.00_y00")
    assert d.shape == (40, 240, 424) and d.dtype == np.uint16
    centre = d[:, 110:130, 200:224].astype(float) * 0.001          # the middle of the board, 1 m away
    assert centre.std(axis=0).mean() == pytest.approx(axial_sigma(1.0, 0.0), rel=0.1)
    assert d[:, 5, 5].mean() == pytest.approx(3000, abs=15)          # the (noisy) wall at 3 m behind the board
    with pytest.raises(ValueError, match="already holds a capture set"):
        simulate_capture_set(out, [(1.0, 0.0)], n_frames=2, show_progress=False)


def test_cli_simulate_checks_its_arguments(tmp_path, capsys):
    assert main(["simulate", "--out", str(tmp_path / "x")]) == 2
    assert "exactly one of --grid paper and --walk SCENE" in capsys.readouterr().err
    assert main(["simulate", "--walk", "stairs"]) == 2
    assert "--walk needs --rrd" in capsys.readouterr().err
    assert main(["simulate", "--walk", "nowhere", "--rrd", str(tmp_path / "w.rrd")]) == 2
    assert "unknown scene" in capsys.readouterr().err
    assert main(["simulate", "--walk", "slope", "--frames", "2", "--rrd", str(tmp_path / "w.rrd"),
                 "--no-progress"]) == 0
    assert (tmp_path / "w.rrd").is_file()
