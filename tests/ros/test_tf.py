"""elevmap.ros.tf: chains through a common ancestor, interpolation, and the extrapolation tolerance."""

from __future__ import annotations

import numpy as np
import pytest

from elevmap.ros.tf import TF_TOLERANCE_S, TfBuffer, TransformUnavailable


def _T(x=0.0, y=0.0, z=0.0, yaw=0.0):
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [x, y, z]
    return T


def _buffer():
    tf = TfBuffer()
    tf.add("map", "base", 10.0, _T(0.0, 0.0, 0.0, 0.0))
    tf.add("map", "base", 11.0, _T(2.0, 0.0, 0.0, np.pi / 2))
    tf.add_static("base", "cam", _T(0.5, 0.0, 1.0))
    tf.add_static("base", "lidar", _T(0.0, 0.2, 0.3, np.pi))
    return tf


def test_lookup_interpolates_translation_linearly_and_rotation_by_slerp():
    tf = _buffer()
    T = tf.lookup("map", "cam", 10.5)          # base halfway: at (1, 0, 0), yawed 45 deg; cam 0.5 m ahead of it
    c = np.sqrt(0.5)
    np.testing.assert_allclose(T[:3, 3], [1.0 + 0.5 * c, 0.5 * c, 1.0], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], _T(yaw=np.pi / 4)[:3, :3], atol=1e-12)
    np.testing.assert_allclose(tf.lookup("map", "cam", 11.0), _T(2.0, 0.0, 0.0, np.pi / 2) @ _T(0.5, 0.0, 1.0),
                               atol=1e-12)


def test_lookup_between_siblings_and_inverse():
    tf = _buffer()
    T_cam_lidar = tf.lookup("cam", "lidar", 10.3)
    np.testing.assert_allclose(T_cam_lidar, np.linalg.inv(_T(0.5, 0.0, 1.0)) @ _T(0.0, 0.2, 0.3, np.pi), atol=1e-12)
    np.testing.assert_allclose(tf.lookup("cam", "map", 10.3) @ tf.lookup("map", "cam", 10.3), np.eye(4), atol=1e-12)
    np.testing.assert_array_equal(tf.lookup("cam", "/cam", 3.0), np.eye(4))


def test_extrapolation_is_held_within_the_tolerance_only():
    tf = _buffer()
    assert TF_TOLERANCE_S == tf.tolerance
    np.testing.assert_allclose(tf.lookup("map", "base", 11.0 + 0.9 * TF_TOLERANCE_S), _T(2.0, 0.0, 0.0, np.pi / 2),
                               atol=1e-12)
    with pytest.raises(TransformUnavailable, match=r"transform map -> base: stamp 11.02 s is outside"):
        tf.lookup("map", "cam", 11.02)
    with pytest.raises(TransformUnavailable, match="outside"):
        tf.lookup("map", "cam", 9.9)
    wide = TfBuffer(tolerance=0.5)
    wide.add("map", "base", 10.0, _T(1.0))
    np.testing.assert_allclose(wide.lookup("map", "base", 10.4), _T(1.0), atol=1e-12)


def test_unknown_and_disconnected_frames_and_two_parents():
    tf = _buffer()
    tf.add_static("world", "other", _T(1.0))
    with pytest.raises(TransformUnavailable, match="'nowhere' is not in the transforms"):
        tf.lookup("map", "nowhere", 10.0)
    with pytest.raises(TransformUnavailable, match="not connected"):
        tf.lookup("map", "other", 10.0)
    with pytest.raises(ValueError, match="'cam' has two parents, 'base' and 'map'"):
        tf.add_static("map", "cam", _T())
    with pytest.raises(ValueError, match="both static and time-stamped"):
        tf.add("base", "lidar", 10.0, _T())
    with pytest.raises(ValueError, match="tolerance"):
        TfBuffer(tolerance=-1.0)


def test_path_names_the_frames_through_the_common_ancestor():
    tf = _buffer()
    assert tf.path("map", "cam") == ["map", "base", "cam"]
    assert tf.path("lidar", "cam") == ["lidar", "base", "cam"]
