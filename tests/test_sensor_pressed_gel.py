"""The pressed gel's colour change at zero slope (`calibration.PressedGelChange`): a synthetic GelSight whose gel,
pressed flat, is not the background. Calibration must learn the change from the ball presses, and reconstruction
must not read it as slope."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_sensor_pipeline import BALL_RADIUS_M, SPEC, _press_circles, synthetic_background, synthetic_sensor_image

from yoto.sensor.ball_calibration import PRESSED_GEL_DEGREES, CalibrationConfig, calibrate
from yoto.sensor.calibration import load_calibration
from yoto.sensor.optical import render_image
from yoto.sensor.reconstruction import box_gradients, pressed_gel_amount, reconstruct
from yoto.sensor.sphere import press_height_map
from yoto.sensor.validation import evaluate_press

FLAT_CHANGE = np.array([8.0, 6.0, 14.0])  # levels of a gel pressed flat, at and beyond FULL_DEPTH_M
FULL_DEPTH_M = 6e-4  # no deeper than the shallowest calibration press (a 22 px contact: 0.62 mm)


def pressed_sensor_image(height_m: np.ndarray, background: np.ndarray, rng) -> np.ndarray:
    """The synthetic sensor's image plus a pressed gel's change: FLAT_CHANGE, brighter to the right, faded in with
    the depth."""
    x = np.linspace(-1, 1, SPEC.width_px)[None, :, None]
    pressed = np.clip(-height_m / FULL_DEPTH_M, 0.0, 1.0)[..., None]
    change = pressed * FLAT_CHANGE * (1.0 + 0.3 * x)
    return np.clip(
        synthetic_sensor_image(height_m, background, rng).astype(np.float64) + np.rint(change), 0, 255
    ).astype(np.uint8)


@pytest.fixture(scope="module")
def pressed():
    """Calibrations from 12 such presses (0.6-1.2 mm deep) with and without the pressed-gel model, and 6 shallow
    held-out presses."""
    rng = np.random.default_rng(11)
    background = synthetic_background()
    circles = _press_circles(rng, 12)
    for _ in range(6):  # held out: shallow presses (0.2-0.4 mm), whose gel shows part of the change
        a = rng.uniform(13, 18)
        circles.append((rng.uniform(a + 4, SPEC.width_px - a - 4), rng.uniform(a + 4, SPEC.height_px - a - 4), a))
    images = [
        pressed_sensor_image(press_height_map(cx, cy, a, BALL_RADIUS_M), background, rng) for cx, cy, a in circles
    ]
    modelled, _ = calibrate(
        background, images[:12], 2 * BALL_RADIUS_M, CalibrationConfig(pressed_gel_degrees=PRESSED_GEL_DEGREES)
    )
    unmodelled, _ = calibrate(background, images[:12], 2 * BALL_RADIUS_M)  # the default: not modelled
    return {"modelled": modelled, "unmodelled": unmodelled, "images": images, "circles": circles}


def test_calibration_learns_the_pressed_gel_change(pressed):
    change = pressed["modelled"].pressed_gel
    assert change is not None
    levels = change.levels((SPEC.height_px, SPEC.width_px))
    expected = FLAT_CHANGE * (1.0 + 0.3 * np.linspace(-1, 1, SPEC.width_px))[:, None]  # (cols, 3) along a row
    middle_row = levels[SPEC.height_px // 2]
    assert np.abs(np.median(middle_row - expected, axis=0)).max() < 3.0  # of 6-18 levels
    assert pressed["unmodelled"].pressed_gel is None


def test_held_out_presses_read_true_with_the_change_modelled(pressed):
    """Shallow held-out presses show part of the change: modelled, their sphere's radius and Hertz profile come back
    (measured: 19% and 4.8 um with the amount read per frame; 8% and 2.6 um when the whole change was taken off at
    every depth); read as slope, as calibrations before it did, the radius is 67% off and the profile 11.3 um."""
    errors = {}
    for key in ("modelled", "unmodelled"):
        rows = []
        for k in range(12, 18):
            result, _ = evaluate_press(pressed["images"][k], pressed[key], BALL_RADIUS_M, str(k), 0)
            assert result.found
            rows.append((abs(result.fitted_radius_mm / (BALL_RADIUS_M * 1e3) - 1), result.profile_rmse_mm))
        errors[key] = np.median(rows, axis=0)
    assert errors["modelled"][0] < 0.25 and errors["modelled"][1] < 0.006  # small caps: radius known to ~10%
    assert errors["unmodelled"][0] > 0.3 and errors["unmodelled"][1] > 2 * errors["modelled"][1]


def test_a_calibration_without_the_change_reads_as_before(pressed, tmp_path):
    """The change survives the calibration file; a file without it (written before) loads with none."""
    path = pressed["modelled"].save(tmp_path / "cal.npz")
    loaded = load_calibration(path)
    assert loaded.pressed_gel is not None
    assert np.array_equal(loaded.pressed_gel.coefficients, pressed["modelled"].pressed_gel.coefficients)
    assert loaded.pressed_gel.full_depth_m == pressed["modelled"].pressed_gel.full_depth_m
    image = pressed["images"][14]
    assert np.array_equal(reconstruct(image, loaded).height_map_m, reconstruct(image, pressed["modelled"]).height_map_m)
    old = load_calibration(pressed["unmodelled"].save(tmp_path / "old.npz"))
    assert old.pressed_gel is None


def test_rendering_shows_the_pressed_gel_change(pressed):
    """The optical simulator of a calibration with the change renders it where the gel is pressed flat, in proportion
    to the depth."""
    calibration = pressed["modelled"]
    for k in (3, 14):  # a deep calibration press, a shallow held-out one
        cx, cy, a = pressed["circles"][k]
        height = press_height_map(cx, cy, a, BALL_RADIUS_M)
        middle = (slice(int(cy) - 2, int(cy) + 3), slice(int(cx) - 2, int(cx) + 3))
        rendered = render_image(height, calibration)[middle].astype(float) - calibration.background[middle]
        pressed_fraction = min(-height.min() / calibration.pressed_gel.full_depth_m, 1.0)
        expected = calibration.pressed_gel.levels((SPEC.height_px, SPEC.width_px))[middle] * pressed_fraction
        assert np.abs((rendered - expected).mean(axis=(0, 1))).max() < 1.5


def test_each_frame_reads_how_much_of_the_change_it_shows(pressed):
    """Reconstruction reads per frame how much of the learnt change the gel shows (`pressed_gel_amount`): the change
    lies off the colours a slope makes. Presses rendered by the calibration's own optical model with the whole learnt
    change, half of it and none read about 1, 0.5 and 0 at the true depths (measured: 1.01-1.04, 0.50-0.55,
    0.00-0.03). At the first solve's depths, which the change makes shallow, the amount reads larger (1.6-2.7 here
    before the MAX_PRESSED_GEL_AMOUNT clip: it scales a fade read too small); a frame without it still reads ~0."""
    calibration = pressed["modelled"]
    change = calibration.pressed_gel
    at_truth: dict[float, list[float]] = {1.0: [], 0.5: [], 0.0: []}
    at_first_solve: dict[float, list[float]] = {1.0: [], 0.5: [], 0.0: []}
    for cx, cy, a in pressed["circles"][:6]:
        height = press_height_map(cx, cy, a, BALL_RADIUS_M)
        for shown in at_truth:
            optics = replace(calibration, pressed_gel=replace(change, coefficients=change.coefficients * shown))
            image = render_image(height, optics, np.random.default_rng(1))
            read = reconstruct(image, calibration)
            at_first_solve[shown].append(read.pressed_gel_amount)
            assert read.box is not None
            gx, gy, _ = box_gradients(image, calibration, read.box)
            at_truth[shown].append(pressed_gel_amount(image, calibration, read.box, height.astype(np.float32), gx, gy))
    truth = {shown: float(np.median(values)) for shown, values in at_truth.items()}
    assert 0.9 < truth[1.0] < 1.1 and 0.4 < truth[0.5] < 0.6 and truth[0.0] < 0.05
    first = {shown: float(np.median(values)) for shown, values in at_first_solve.items()}
    assert first[1.0] > 0.9 and first[0.5] > 0.5 and first[0.0] < 0.1
