"""The recording protocol of ``elevmap characterize`` (a light module: ``elevmap --help`` shows it)."""

__all__ = ["PROTOCOL"]

PROTOCOL = """\
Recording protocol (as Ahn et al. 2019 did for the D435):
  1. Put the camera on a tripod, level, and keep it still. Use the depth mode you will map with
     (848x480 is the D435's best); disable post-processing filters (record raw depth).
  2. Target: a flat, matte board (e.g. a 0.6 x 0.9 m white board; keep the IR emitter on, it gives
     the board texture) standing well clear of anything behind it (a wall >= 1 m behind it is fine),
     its centre on the optical axis (the image centre); or a flat wall (`wall` captures: axial noise
     and systematic error only, no edges).
  3. Settings: distance 0.4 to 2.1 m every 0.1 m, measured with a laser distance meter from the
     camera to the target's centre along the optical axis (the depth origin lies a few mm behind the
     front glass: the "depth start point" of Intel's D400 datasheet; add it to the meter's reading),
     and at each distance the target turned about its vertical axis by 0, 15, 30, 45, 60, 75 deg
     (yaw_deg; positive turns the target's right edge towards the camera). Keep both vertical edges
     of a board inside the image; at least 5 settings are needed for the fit.
  4. Record 100 frames per setting (one .npy of uint16 (frames, H, W), or a .bag/.db3 from the
     RealSense Viewer / SDK), named e.g. board_z0.80_y30.
  5. Write captures.json (format d435-captures/1): "camera" with width, height, fx, fy, ppx, ppy
     [px], depth_scale [m/unit] and baseline_m of the depth stream (rs-enumerate-devices -c prints
     them; a .bag's own values win), and one entry per capture:
       {"id": "board_z0.80_y30", "depth": "board_z0.80_y30.npy",
        "target": {"kind": "board", "distance_m": 0.80, "yaw_deg": 30, "pitch_deg": 0,
                   "width_m": 0.60, "height_m": 0.90}, "background_m": 3.0}
     (background_m, the wall behind the board, is optional). Optional per capture:
     "region_px": {"rows": [r0, r1], "cols": [c0, c1]} to give the central region yourself
     (half-open pixel ranges).
  `elevmap simulate --grid paper --frames 100 --out DIR` writes such a set from the paper's model.
"""
