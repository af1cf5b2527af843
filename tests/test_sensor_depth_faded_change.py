"""A depth-faded change read as slope, estimated from one frame's non-integrable residual (stop 21, not used by
reconstruction: on rendered object contacts the colour model's other errors dominate that residual)."""

from __future__ import annotations

import numpy as np

from yoto.sensor.depth_faded_change import estimate_change, remove_change
from yoto.sensor.optical import height_gradients
from yoto.sensor.reconstruction import integrate_box
from yoto.sensor.spec import GELSIGHT_MINI

SPEC = GELSIGHT_MINI
BOX = (90, 210, 60, 200)  # inside the frame: fixed edges on flat gel
BLOCKS = np.zeros((SPEC.height_px // 8, SPEC.width_px // 8), np.float32)


def contact() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An oval contact 0.5 mm deep that returns smoothly to flat gel inside the box, and its true gradients."""
    rows, cols = np.mgrid[0 : SPEC.height_px, 0 : SPEC.width_px]
    r2 = ((rows - 140.0) / 35.0) ** 2 + ((cols - 120.0) / 45.0) ** 2
    truth = (-5e-4 * np.clip(1.0 - r2, 0.0, None) ** 2).astype(np.float32)
    gx, gy = (g.astype(np.float32) for g in height_gradients(truth, SPEC.pixel_size_m))
    outside = np.ones(truth.shape, bool)
    outside[BOX[0] : BOX[1], BOX[2] : BOX[3]] = False
    gx[outside] = gy[outside] = 0.0
    return truth, gx, gy


def rms_um(height: np.ndarray, truth: np.ndarray) -> float:
    felt = truth < -5e-5
    return float(np.sqrt(np.mean((height[felt] - truth[felt]) ** 2)) * 1e6)


def test_a_depth_faded_change_is_recovered_from_the_residual_and_taken_off():
    truth, gx, gy = contact()
    c_true = np.array([0.03, -0.02])  # slope per mm of depth
    depth_mm = -1e3 * truth
    read_x, read_y = gx + np.float32(c_true[0]) * depth_mm, gy + np.float32(c_true[1]) * depth_mm
    first = integrate_box(read_x, read_y, BOX, BLOCKS, SPEC.pixel_size_m)
    c, explained = estimate_change(read_x, read_y, first, BOX)
    assert np.abs(c - c_true).max() < 0.002  # from the first solve's depth: within 0.0001 measured
    assert explained > 0.9
    corrected, applied = remove_change(read_x, read_y, first, BOX, BLOCKS, SPEC.pixel_size_m)
    assert np.allclose(applied, c)
    before, after = rms_um(first, truth), rms_um(corrected, truth)
    assert before > 4.0 and after < 0.1 * before  # 4.8 -> 0.16 um measured


def test_gradients_without_a_change_are_left_as_they_are():
    truth, gx, gy = contact()
    first = integrate_box(gx, gy, BOX, BLOCKS, SPEC.pixel_size_m)
    c, _ = estimate_change(gx, gy, first, BOX)
    assert np.hypot(*c) < 1e-4  # 3e-9 measured: the true gradients leave no residual d c explains
    corrected, applied = remove_change(gx, gy, first, BOX, BLOCKS, SPEC.pixel_size_m)
    assert not applied.any() and np.array_equal(corrected, first)


def test_a_change_larger_than_the_limit_is_taken_off_only_up_to_it():
    truth, gx, gy = contact()
    depth_mm = -1e3 * truth
    read_x = gx + np.float32(0.2) * depth_mm
    first = integrate_box(read_x, gy, BOX, BLOCKS, SPEC.pixel_size_m)
    corrected, applied = remove_change(read_x, gy, first, BOX, BLOCKS, SPEC.pixel_size_m)
    assert np.isclose(np.hypot(*applied), 0.05) and applied[0] > 0.049
    assert rms_um(corrected, truth) < 0.8 * rms_um(first, truth)  # 26.7 -> 20.1 um measured
