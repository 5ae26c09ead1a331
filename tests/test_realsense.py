"""The RealSense backend through Open3D's RealSense support: a clear error with no camera (the real
librealsense enumeration inside Open3D), depth units, configuration."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.depth.config import RealSenseConfig
from drivers.depth.projection import back_project, pinhole_fov_deg
from drivers.depth.realsense import RealSense, depth_from_raw
from drivers.errors import DriverError
from drivers.factory import make_sensor


def test_no_camera_is_a_clear_error():
    sensor = make_sensor(RealSenseConfig(type="realsense"), None, lambda: np.eye(4))
    assert isinstance(sensor, RealSense)
    with pytest.raises(DriverError, match="no RealSense camera found"):
        sensor.connect()
    assert not sensor.is_connected
    with pytest.raises(DriverError, match="disconnected"):
        sensor.capture()
    with pytest.raises(DriverError, match="once connected"):
        _ = sensor.model


def test_depth_units_and_range_gate():
    raw = np.array([[0, 99, 100, 1500], [2000, 2001, 65535, 500]], dtype=np.uint16)
    depth = depth_from_raw(raw, 1000.0, (0.1, 2.0))
    assert depth.dtype == np.float32
    np.testing.assert_allclose(depth, [[0.0, 0.0, 0.1, 1.5], [2.0, 0.0, 0.0, 0.5]], rtol=1e-6)
    K = np.array([[600.0, 0.0, 1.5], [0.0, 600.0, 0.5], [0.0, 0.0, 1.0]])
    pts = back_project(depth, K)
    assert pts.shape == (4, 3) and np.allclose(pts[:, 2], [0.1, 1.5, 2.0, 0.5])
    assert pts[0, 0] == pytest.approx((2 - 1.5) * 0.1 / 600.0)


def test_pinhole_field_of_view():
    K = np.array([[475.0, 0.0, 319.5], [0.0, 475.0, 239.5], [0.0, 0.0, 1.0]])
    fov_x, fov_y = pinhole_fov_deg(K, 640, 480)
    assert fov_x == pytest.approx(2 * np.degrees(np.arctan(320 / 475.0)))
    assert fov_y == pytest.approx(2 * np.degrees(np.arctan(240 / 475.0)))


def test_config_fields():
    cfg = RealSenseConfig(type="realsense", serial="123", preset="RS2_RS400_VISUAL_PRESET_HIGH_ACCURACY",
                          record_bag="/tmp/scan.bag")
    assert (cfg.width, cfg.height, cfg.fps) == (640, 480, 30)
    with pytest.raises(ValueError, match="below range_max_m"):
        RealSenseConfig(type="realsense", range_min_m=2.0, range_max_m=1.0)
