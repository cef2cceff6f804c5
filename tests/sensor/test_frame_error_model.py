"""The sensor model's per-frame error: its file format (/3), old files (/1, /2) read without one, checks."""

import json

import numpy as np

import pytest

import noise_model as nm
from noise_model.d435 import MODEL_FORMAT, MODEL_FORMAT_DISPARITY, MODEL_FORMAT_FRAME_ERROR


@pytest.mark.parametrize("base", [nm.D435.with_coefficients((3e-4, -6e-4, 3.3e-3, 6e-5)), nm.D435.with_disparity(0.04)])
def test_a_model_with_a_frame_error_round_trips_through_its_file(tmp_path, base):
    from dataclasses import replace

    m = replace(base, frame_variance_ratio=1.98, error_correlation_px=4.11, error_correlation_fx_px=212.0)
    m.save(tmp_path / "m.json")
    doc = json.loads((tmp_path / "m.json").read_text())
    assert doc["format"] == MODEL_FORMAT_FRAME_ERROR and doc["family"] == base.family
    back = nm.SensorModel.load(tmp_path / "m.json")
    assert back == m and back.has_frame_error
    # the map's view: the length scales with the frame's focal length
    assert back.frame_error(424.0) == pytest.approx((8.22, 1.98))
    assert back.frame_error(212.0) == pytest.approx((4.11, 1.98))
    # a ratio without a correlation is kept too
    r = replace(base, frame_variance_ratio=1.5)
    assert nm.SensorModel.from_dict(r.to_dict()) == r and r.frame_error(300.0) == (0.0, 1.5)


def test_old_model_files_read_with_no_frame_error(tmp_path):
    for model, fmt in [(nm.D435, MODEL_FORMAT), (nm.D435.with_disparity(0.08), MODEL_FORMAT_DISPARITY)]:
        d = model.to_dict()
        assert d["format"] == fmt and "frame_variance_ratio" not in d and "error_correlation_px" not in d
        back = nm.SensorModel.from_dict(d)
        assert not back.has_frame_error and back.frame_error(212.0) == (0.0, 1.0)


@pytest.mark.parametrize("changes, msg", [
    ({"frame_variance_ratio": 0.5}, "frame_variance_ratio"),
    ({"frame_variance_ratio": float("nan")}, "frame_variance_ratio"),
    ({"error_correlation_px": -1.0, "error_correlation_fx_px": 212.0}, "error_correlation_px"),
    ({"error_correlation_px": 4.0}, "error_correlation_fx_px"),
    ({"error_correlation_px": 4.0, "error_correlation_fx_px": 0.0}, "error_correlation_fx_px"),
    ({"frame_variance_ratio": "2"}, "frame_variance_ratio"),
])
def test_a_bad_frame_error_is_refused(changes, msg):
    from dataclasses import replace

    with pytest.raises(ValueError, match=msg):
        replace(nm.D435, **changes)


def test_a_v3_file_missing_a_key_names_it():
    from dataclasses import replace

    d = replace(nm.D435, frame_variance_ratio=2.0).to_dict()
    del d["error_correlation_px"]
    with pytest.raises(ValueError, match="error_correlation_px"):
        nm.SensorModel.from_dict(d)


def test_the_per_frame_sigma_replaces_the_temporal_one_for_the_map(tmp_path):
    from dataclasses import replace

    paper = replace(nm.D435.with_coefficients((3.4e-4, -6.6e-4, 3.3e-3, 5.8e-5)), frame_variance_ratio=2.2,
                    error_correlation_px=4.0, error_correlation_fx_px=212.0, frame_noise=(3e-4, 4e-4, 3.5e-3, 3e-4))
    m = paper.for_map()
    assert m.axial_coefficients == (3e-4, 4e-4, 3.5e-3, 3e-4) and m.frame_noise is None
    assert m.frame_error(212.0) == (4.0, 1.0)                  # the ratio is inside the per-frame sigma
    assert nm.axial_sigma(1.0, 0.5, model=m) > nm.axial_sigma(1.0, 0.5, model=paper)
    paper.save(tmp_path / "p.json")
    assert nm.SensorModel.load(tmp_path / "p.json") == paper
    disp = replace(nm.D435.with_disparity(0.04), frame_variance_ratio=2.0, frame_noise=(0.06, 0.01))
    assert disp.for_map().disparity_sigma_px == (0.06, 0.01) and disp.for_map().frame_error(100.0) == (0.0, 1.0)
    assert nm.SensorModel.from_dict(disp.to_dict()) == disp
    assert nm.D435.for_map() is nm.D435
    for bad in [(1e-3, 1e-3), (0.0, -1.0, 0.0, 0.0, 0.0), (np.nan, 0, 0, 0)]:
        with pytest.raises(ValueError, match="frame_noise"):
            replace(nm.D435, frame_noise=bad)
    with pytest.raises(ValueError, match="frame_noise"):
        replace(nm.D435.with_disparity(0.04), frame_noise=(-0.01, 0.0))
