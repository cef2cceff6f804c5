"""``elevmap gap --jobs N``: the captures of each model simulated in worker processes give the same report."""

from __future__ import annotations

import json

import numpy as np
import pytest

from noise_model import D435
from noise_model.analysis import diagnosis as G
from noise_model.analysis.capture_data import CaptureData, CaptureGeometry, simulate_capture
from noise_model.sim import effects as E

CAM = {"width": 106, "height": 60, "fx": 53.0, "fy": 53.0, "ppx": 52.5, "ppy": 29.5, "depth_scale": 0.001,
       "baseline_m": 0.05}


def _entries():
    """Walls at 3 distances x 2 angles, pseudo-real with a correlated per-frame field and a dead left band."""
    fx = [E.make_effect("invalid_band", margin_px=4.0),
          E.make_effect("correlated_noise", sigma_z_fraction=1.2, length_px=3.0)]
    out = []
    for i, (d, y) in enumerate([(d, y) for d in (0.6, 1.0, 1.4) for y in (0.0, 30.0)]):
        entry = {"id": f"wall_z{d:.2f}_y{int(y):02d}",
                 "target": {"kind": "wall", "distance_m": d, "yaw_deg": y, "pitch_deg": 0.0}}
        g = CaptureGeometry.from_capture_set_entry(CAM, entry)
        out.append((entry, simulate_capture(g, 8, np.random.default_rng([91, i]), D435, E.canonical_order(fx))))
    return out


def _without_time(report: dict) -> dict:
    return {k: v for k, v in json.loads(json.dumps(report)).items() if k != "seconds"}


def test_jobs_give_the_same_report_as_one_process(tmp_path):
    from elevmap.commands import gap as EG
    from elevmap.sources.captures import write_capture_set

    write_capture_set(tmp_path / "real", CAM, _entries())
    kw = dict(effects="invalid_band,correlated_noise,static_noise", show_progress=False, n_splits=16, n_boot=16)
    one = EG.run_gap(tmp_path / "real", **kw)
    two = EG.run_gap(tmp_path / "real", n_jobs=2, **kw)
    assert {e["name"] for e in one["effects"]} >= {"invalid_band", "correlated_noise"}
    assert _without_time(two) == _without_time(one)           # every gap, parameter, round and test, to the bit
    with pytest.raises(ValueError, match="jobs"):
        EG.run_gap(tmp_path / "real", n_jobs=0, **kw)


def test_the_simulators_sums_are_those_of_its_frames():
    """The workers' path (simulate and reduce to sums in one task) equals simulating the frames and summing
    them here, for a model with effects, and the Diagnosis takes the same sums either way."""
    entries = _entries()[:3]
    geoms = {e["id"]: CaptureGeometry.from_capture_set_entry(CAM, e) for e, _ in entries}
    caps = {i: G.gap_capture_of(g) for i, g in geoms.items()}
    sampling = G.frame_sampling(8, 3, 4, 4)
    fx = [("correlated_noise", {"sigma_z_fraction": 0.7, "length_px": 2.5}), ("invalid_band", {"margin_px": 3.0})]
    sim = G.CaptureSimulator(geoms, D435, seed=5)
    frames = sim(list(geoms), fx, 8)
    got = sim.sums(list(geoms), fx, 8, caps, sampling)
    for i in geoms:
        np.testing.assert_array_equal(got[i], G.capture_sums(caps[i], frames[i], sampling))
    # a simulate without ``sums`` (frames only) gives the Diagnosis the same gaps
    real = {i: CaptureData.from_units(geoms[i], u).depth_m for (e, u), i in zip(entries, geoms)}
    ids = list(geoms)

    def frames_only(which, effects, n):
        return sim(which, effects, n)

    a = G.Diagnosis(list(caps.values()), real, ids[:2], ids[2:], sim, n_splits=8, n_boot=8)
    b = G.Diagnosis(list(caps.values()), real, ids[:2], ids[2:], frames_only, n_splits=8, n_boot=8)
    for model in ([], fx):
        ra, rb = a.evaluate(model, ids), b.evaluate(model, ids)
        assert ra.G == rb.G and ra.p_value == rb.p_value


def test_the_fits_base_simulations_from_the_workers_are_the_fits_own():
    """With workers, the fits' base simulations are made there and put in the fits' cache: the same
    entries, to the bit, as the fits' own simulations, and the same fitted parameters."""
    from noise_model.analysis.effect_fits._common import _base_sims

    real = [CaptureData.from_units(CaptureGeometry.from_capture_set_entry(CAM, e), u) for e, u in _entries()[:3]]
    base = [("invalid_band", {"margin_px": 3.0}), ("correlated_noise", {"sigma_z_fraction": 0.8, "length_px": 2.0})]
    geoms = {c.id: c.geometry for c in real}
    with G.CaptureSimulator(geoms, D435, seed=4, jobs=2) as sim:
        fitter = G.EffectFitter(real, D435, 4, None, sim)
        params = fitter("correlated_noise", base)
        filled = dict(fitter._cache)
        assert fitter.n_prefilled == len(real)                # made in the workers, not by the fit
    own: dict = {}
    expected = _base_sims(real, D435, [E.make_effect(n, **p) for n, p in base], 4, own)
    assert set(filled) >= set(own) and len(own) == len(real)
    for key, c in zip(own, expected):
        assert filled[key].id == c.id
        np.testing.assert_array_equal(filled[key].depth_m, c.depth_m)
    assert params == G.EffectFitter(real, D435, 4)("correlated_noise", base)
