"""The lookup-table renderer (yoto.sensor.table): read off ball presses, it renders presses it did not see."""

from __future__ import annotations

import numpy as np
import pytest

from yoto.errors import InputError
from yoto.sensor.shading import ShadingSensor
from yoto.sensor.spec import GELSIGHT_MINI
from yoto.sensor.sphere import press_height_map
from yoto.sensor.table import fit_table_sensor, place_weights, read_press_folder

BALL_RADIUS_M = 6.31e-3 / 2


@pytest.fixture(scope="module")
def presses():
    """A nominal shading sensor, its background and 24 noise-free ball presses over the pad with their circles."""
    sensor = ShadingSensor(blur_px=0.0, gel_sigma_m=0.0)
    rng = np.random.default_rng(4)
    circles = [
        (float(rng.uniform(20, 300)), float(rng.uniform(20, 220)), float(rng.uniform(22, 30))) for _ in range(24)
    ]
    images = [sensor.render(press_height_map(*c, BALL_RADIUS_M, GELSIGHT_MINI)) for c in circles]
    return sensor, sensor.background(), images, circles


def test_the_table_renders_an_unseen_press_like_the_sensor_and_untouched_gel_as_the_background(presses):
    sensor, background, images, circles = presses
    table = fit_table_sensor(background, images, circles, BALL_RADIUS_M, places=3, blur_px=0.0)
    assert np.array_equal(table.render(np.zeros((240, 320))), background)
    circle = (150.0, 110.0, 26.0)
    height = press_height_map(*circle, BALL_RADIUS_M, GELSIGHT_MINI)
    truth = sensor.render(height).astype(float) - background
    rendered = table.render(height).astype(float) - background
    ys, xs = np.mgrid[:240, :320]
    inside = np.hypot(xs - circle[0], ys - circle[1]) < 0.9 * circle[2]
    error = np.sqrt(np.mean((rendered - truth)[inside] ** 2))
    signal = np.sqrt(np.mean(truth[inside] ** 2))
    assert signal > 20.0 and error < 0.1 * signal, (error, signal)
    # Noise of the level measured between the presses and the background: none here (noise-free presses).
    assert np.all(table.noise_std < 0.5), table.noise_std


def test_the_per_pixel_gain_keeps_lighting_that_varies_faster_than_the_places(presses):
    """Lighting that varies pixel by pixel (as a real pad's does, and our calibration knows): read relative to each
    pixel's background, a table with 3 x 3 places renders an unseen press within 8% of its signal; the same table
    without the gain averages the lighting over its places and misses by more than 12%."""
    sensor, background, images, circles = presses
    ys, xs = np.mgrid[:240, :320]
    lighting = 1 + 0.4 * (np.sin(xs / 9.0) * np.cos(ys / 13.0))[..., None] * np.array([1.0, -0.6, 0.8])

    def lit(image: np.ndarray) -> np.ndarray:
        return np.clip(np.rint(image * lighting), 0, 255).astype(np.uint8)

    lit_background = lit(background)
    circle = (150.0, 110.0, 26.0)
    height = press_height_map(*circle, BALL_RADIUS_M, GELSIGHT_MINI)
    truth = lit(sensor.render(height)).astype(float) - lit_background
    inside = np.hypot(xs - circle[0], ys - circle[1]) < 0.9 * circle[2]
    signal = np.sqrt(np.mean(truth[inside] ** 2))
    errors = {}
    for gain in (True, False):
        table = fit_table_sensor(
            lit_background, [lit(i) for i in images], circles, BALL_RADIUS_M, places=3, blur_px=0.0, per_pixel_gain=gain
        )
        rendered = table.render(height).astype(float) - lit_background
        errors[gain] = np.sqrt(np.mean((rendered - truth)[inside] ** 2)) / signal
    assert signal > 20.0 and errors[True] < 0.08 and errors[False] > 0.12, errors


def test_slopes_beyond_the_steepest_pressed_saturate(presses):
    _, background, images, circles = presses
    table = fit_table_sensor(background, images, circles, BALL_RADIUS_M, places=1, blur_px=0.0)
    gx = np.zeros((240, 320))
    gx[:, 1], gx[:, 2] = table.limit, 3 * table.limit
    gx[:, 3] = 0.1
    change = table.lookup(gx, np.zeros_like(gx))
    assert np.allclose(change[:, 1], change[:, 2])
    assert not np.allclose(change[:, 3], change[:, 1], atol=1.0)


def test_place_weights_blend_to_one_and_follow_the_pad():
    weights = place_weights(3, 240, 320)
    total = sum(w for _, _, w in weights)
    assert np.allclose(total, 1.0)
    # The pad's top-left corner is all place (0, 0), its centre all place (1, 1).
    corner = {(int(r[0, 0]), int(c[0, 0])): float(w[0, 0]) for r, c, w in weights if w[0, 0] > 0}
    assert corner == {(0, 0): 1.0}
    centre = {(int(r[120, 160]), int(c[120, 160])): float(w[120, 160]) for r, c, w in weights if w[120, 160] > 0.01}
    assert list(centre) == [(1, 1)] and centre[(1, 1)] == pytest.approx(1.0, abs=0.02)


def test_a_press_folder_needs_its_catalog(tmp_path):
    with pytest.raises(InputError, match="catalog"):
        read_press_folder(tmp_path)


def test_pressed_flat_gel_keeps_the_presses_zero_slope_change_faded_in_by_depth(presses):
    """Real presses change colour where the ball's slope is zero (the gel pressed flat, not untouched): the table
    keeps it there, in proportion to the depth up to `pressed_depth_m`, and untouched gel stays the background."""
    _, background, images, circles = presses
    ys, xs = np.mgrid[:240, :320]
    offset = np.array([12, 0, 0], np.int16)  # a press's contact shows +12 levels of red beyond its shading
    tinted = []
    for image, (cx, cy, a) in zip(images, circles, strict=True):
        inside = np.hypot(xs - cx, ys - cy) < a
        tinted.append(np.clip(image.astype(np.int16) + inside[..., None] * offset, 0, 255).astype(np.uint8))
    # Without the per-pixel gain, so that the tint reads back as the same levels everywhere.
    settings = {"places": 1, "blur_px": 0.0, "pressed_depth_m": 8e-4, "per_pixel_gain": False}
    table = fit_table_sensor(background, tinted, circles, BALL_RADIUS_M, **settings)
    untinted = fit_table_sensor(background, images, circles, BALL_RADIUS_M, **settings)
    plateau = np.zeros((240, 320))
    plateau[60:180, 80:240] = -1e-3  # pressed flat 1 mm deep: the full change
    plateau[100:140, 120:200] = -4e-4  # 0.4 mm: half of it
    change = table.render(plateau).astype(float) - background
    tint = change - (untinted.render(plateau).astype(float) - background)
    assert np.median(tint[70:90, 90:110], axis=(0, 1)) == pytest.approx([12.0, 0.0, 0.0], abs=1.0)
    assert np.median(tint[110:130, 140:180], axis=(0, 1)) == pytest.approx([6.0, 0.0, 0.0], abs=1.0)
    assert np.abs(change[5:40, 5:60]).max() == 0.0
