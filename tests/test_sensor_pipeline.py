"""The whole sensor pipeline on a synthetic GelSight (no shared data needed): calibrate from rendered ball
presses, reconstruct held-out presses, the calibration file, the optical round trip, and bad input."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

from yoto.errors import InputError
from yoto.sensor.ball_calibration import calibrate, round_trip_gain
from yoto.sensor.calibration import SensorCalibration, load_calibration, with_background
from yoto.sensor.models import model_colour_change, monomial_exponents, monomials, normalised_xy
from yoto.sensor.optical import height_gradients, render_image
from yoto.sensor.reconstruction import reconstruct
from yoto.sensor.spec import GELSIGHT_MINI, GelSightSpec
from yoto.sensor.sphere import press_height_map
from yoto.sensor.validation import evaluate_press, find_press_circle

SPEC = GELSIGHT_MINI
BALL_RADIUS_M = 3.155e-3
BALL_RADIUS_PX = BALL_RADIUS_M / SPEC.pixel_size_m


def synthetic_background() -> np.ndarray:
    """A smooth, uneven illumination like the Mini's (teal corners, a brighter middle)."""
    y, x = np.mgrid[: SPEC.height_px, : SPEC.width_px] / np.array([SPEC.height_px, SPEC.width_px])[:, None, None]
    glow = np.exp(-((x - 0.5) ** 2 + (y - 0.5) ** 2) / 0.08)
    background = np.stack([70 + 50 * glow, 90 + 10 * glow, 100 + 20 * glow - 10 * x], axis=2)
    return np.clip(background, 0, 255).astype(np.uint8)


def synthetic_sensor_image(height_m: np.ndarray, background: np.ndarray, rng=None) -> np.ndarray:
    """The synthetic sensor's optics: three lights whose response to the slope varies across the pad."""
    gx, gy = height_gradients(height_m, SPEC.pixel_size_m)
    x = np.linspace(-1, 1, SPEC.width_px)[None, :]
    gain = 1.0 + 0.25 * x
    change = np.stack(
        [
            110 * gain * gx + 40 * gx * gx,
            100 * gy - 20 * gy * gy,
            -(70 * gx + 60 * gy) * (1.1 - 0.2 * x) + 30 * (gx * gx + gy * gy),
        ],
        axis=2,
    )
    change = ndimage.gaussian_filter(change, (1.0, 1.0, 0))
    image = background + change
    if rng is not None:
        image = image + rng.normal(0, 2.0, image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def _press_circles(rng, count):
    circles = []
    for _ in range(count):
        a = rng.uniform(22, 30)
        circles.append((rng.uniform(a + 4, SPEC.width_px - a - 4), rng.uniform(a + 4, SPEC.height_px - a - 4), a))
    return circles


def synthetic_calibration(presses: int) -> SensorCalibration:
    """A calibration of the synthetic sensor from `presses` rendered ball presses (seed 7), for other stages' tests."""
    rng = np.random.default_rng(7)
    background = synthetic_background()
    images = [
        synthetic_sensor_image(press_height_map(cx, cy, a, BALL_RADIUS_M), background, rng)
        for cx, cy, a in _press_circles(rng, presses)
    ]
    return calibrate(background, images, 2 * BALL_RADIUS_M)[0]


@pytest.fixture(scope="module")
def synthetic():
    """A calibration of the synthetic sensor from 16 presses, and 6 held-out presses with their truth."""
    rng = np.random.default_rng(7)
    background = synthetic_background()
    circles = _press_circles(rng, 22)
    images = [
        synthetic_sensor_image(press_height_map(cx, cy, a, BALL_RADIUS_M), background, rng) for cx, cy, a in circles
    ]
    calibration, report = calibrate(background, images[:16], 2 * BALL_RADIUS_M)
    return {
        "calibration": calibration,
        "report": report,
        "background": background,
        "circles": circles,
        "images": images,
    }


def test_calibration_recovers_the_contact_circles(synthetic):
    """Self-calibration lands on the true centres and near the true contact radii of the training presses."""
    report = synthetic["report"]
    assert all(p.used for p in report.presses)
    for press, (cx, cy, a) in zip(report.presses, synthetic["circles"][:16], strict=False):
        assert np.hypot(press.contact_x_px - cx, press.contact_y_px - cy) < 1.0
        assert abs(press.contact_radius_px - a) < 0.12 * a
    assert report.gradient_rmse < 0.05


def test_held_out_presses_give_the_ball_radius(synthetic):
    """Held-out presses reconstruct to spheres of the ball's radius (median within 3%, each within 8%)."""
    radii = []
    for k in range(16, 22):
        result, recon = evaluate_press(synthetic["images"][k], synthetic["calibration"], BALL_RADIUS_M, str(k), 0)
        assert result.found and recon.contact
        cx, cy, a = synthetic["circles"][k]
        assert np.hypot(result.centre_x_px - cx, result.centre_y_px - cy) < 1.0
        radii.append(result.fitted_radius_mm)
        assert result.profile_rmse_mm < 0.03  # shape error of the height profile inside the contact
    errors = np.array(radii) / (BALL_RADIUS_M * 1e3) - 1
    assert abs(np.median(errors)) < 0.03
    assert np.abs(errors).max() < 0.08


def test_reconstruction_fields_and_frame(synthetic):
    """Shapes, dtypes, z <= 0, and the points are the masked pixels in the SPEC sensor frame."""
    recon = reconstruct(synthetic["images"][17], synthetic["calibration"])
    assert recon.contact and recon.reason == ""
    assert recon.height_map_m.shape == (SPEC.height_px, SPEC.width_px)
    assert recon.mask.dtype == bool and recon.mask.shape == recon.height_map_m.shape
    assert recon.points_sensor.dtype == np.float64 and recon.points_sensor.shape[1] == 3
    assert (recon.points_sensor[:, 2] <= 0).all() and (recon.height_map_m <= 0).all()
    expected = SPEC.height_map_to_points(recon.height_map_m, recon.mask)
    np.testing.assert_array_equal(recon.points_sensor, expected)
    # The contact sits where the press is: the deepest point's pixel is within 2 px of the true centre.
    cx, cy, a = synthetic["circles"][17]
    row, col = np.unravel_index(np.argmin(recon.height_map_m), recon.height_map_m.shape)
    assert np.hypot(col - cx, row - cy) < 2.0
    # The core is the contact disc (Hertz: the edge is at half the depth); the contact the gel felt (the mask,
    # for localization) holds the core and the gel pressed around it, one connected region.
    disc = np.hypot(*np.meshgrid(np.arange(SPEC.width_px) - cx, np.arange(SPEC.height_px) - cy)) < a
    assert (recon.core_mask & disc).sum() / (recon.core_mask | disc).sum() > 0.75
    assert not (recon.core_mask & ~recon.mask).any() and recon.mask.sum() > 1.5 * disc.sum()
    assert ndimage.label(recon.mask)[1] == 1


def test_fast_gradients_match_the_polynomial_reference(synthetic):
    """Table + per-pixel maps (fast) match the fitted polynomial (slow) up to the table's quantisation."""
    calibration = synthetic["calibration"]
    change = model_colour_change(synthetic["images"][18], calibration.background_i16, calibration.smooth)
    fast = calibration.gradient_model.predict(change)
    slow = calibration.gradient_model.predict_reference(change)
    for got, ref in zip(fast, slow, strict=True):
        touched = np.abs(change).max(axis=2) > 3
        assert np.abs(got - ref)[touched].max() < 0.06
        assert np.abs(got - ref)[touched].mean() < 0.01
    # A window of the frame gives the same gradients as the full frame there.
    window = calibration.gradient_model.predict(change[40:120, 100:260], origin=(40, 100))
    np.testing.assert_allclose(window[0], fast[0][40:120, 100:260], atol=1e-6)


def test_unchanged_colour_reads_as_flat_and_faint_changes_at_their_linear_gain(synthetic):
    """The gradient model is anchored: zero colour change is flat gel, exactly, everywhere on the pad; and a change
    of a level or two is read at the model's gain, not at its table cell's centre (cells are 4 levels wide)."""
    model = synthetic["calibration"].gradient_model
    assert model.config.anchored
    shape = (SPEC.height_px, SPEC.width_px, 3)
    zero = model.predict(np.zeros(shape, np.int16))
    assert np.abs(zero).max() < 1e-3
    for channel in range(3):
        reads = []
        for level in (1, 2, 4):
            change = np.zeros(shape, np.int16)
            change[..., channel] = level
            reads.append(np.stack(model.predict(change)))
        gain = reads[2] / 4
        for level, read in zip((1, 2), reads[:2], strict=True):
            assert np.abs(read - level * gain).max() < 0.1 * np.abs(level * gain).max()


def test_no_contact_is_an_explicit_empty_result(synthetic, rng):
    calibration = synthetic["calibration"]
    frame = np.clip(synthetic["background"] + rng.normal(0, 2.0, synthetic["background"].shape), 0, 255)
    recon = reconstruct(frame.astype(np.uint8), calibration)
    assert not recon.contact and recon.reason.startswith("no contact")
    assert recon.points_sensor.shape == (0, 3) and not recon.mask.any()


@pytest.mark.parametrize("kind", ["cap", "hertz"])
def test_optical_round_trip(synthetic, rng, kind):
    """render_image then reconstruct returns the height map inside the contact, with sensor noise.

    A cap (gel flat outside the contact): RMS error < 0.06 mm at depths of 0.2-0.5 mm. A Hertz press: shape
    error (offset removed) < 0.03 mm; its depth is underestimated by up to 0.15 mm because the far, faint
    part of the gel's rim lies outside the touched box, where the gel is taken as flat (docs/sensor.md).
    """
    calibration = synthetic["calibration"]
    for cx, cy, a in [(160.0, 120.0, 20.0), (90.0, 80.0, 26.0), (230.0, 150.0, 24.0)]:
        height = press_height_map(cx, cy, a, BALL_RADIUS_M)
        disc = np.hypot(*np.meshgrid(np.arange(SPEC.width_px) - cx, np.arange(SPEC.height_px) - cy)) < a
        if kind == "cap":  # a sphere pressed into a gel that stays flat outside the contact
            height = np.minimum(np.where(disc, height - height[~disc].min(), 0.0), 0.0)
        image = render_image(height, calibration, rng)
        recon = reconstruct(image, calibration)
        error = (recon.height_map_m - height)[disc]
        if kind == "cap":
            assert np.sqrt(np.mean(error**2)) < 6e-5, (cx, cy, a)
        else:
            assert np.sqrt(np.mean((error - error.mean()) ** 2)) < 3e-5, (cx, cy, a)
            assert 0 <= error.mean() < 1.5e-4, (cx, cy, a)
        assert recon.contact


def test_render_image_is_the_background_where_the_gel_is_flat(synthetic):
    calibration = synthetic["calibration"]
    flat = render_image(np.zeros((SPEC.height_px, SPEC.width_px)), calibration, blur_px=0.0)
    np.testing.assert_array_equal(flat, calibration.background)
    noisy = render_image(np.zeros((SPEC.height_px, SPEC.width_px)), calibration, np.random.default_rng(0))
    assert 0.5 < np.std(noisy.astype(float) - calibration.background) < 5.0


def test_render_matches_the_synthetic_optics(synthetic):
    """The fitted inverse model reproduces the synthetic sensor's image of a new press (RMS < 4 levels)."""
    cx, cy, a = synthetic["circles"][20]
    height = press_height_map(cx, cy, a, BALL_RADIUS_M)
    truth = synthetic_sensor_image(height, synthetic["background"])
    rendered = render_image(height, synthetic["calibration"])
    near = np.hypot(*np.meshgrid(np.arange(SPEC.width_px) - cx, np.arange(SPEC.height_px) - cy)) < 1.5 * a
    assert np.sqrt(np.mean((rendered.astype(float) - truth)[near] ** 2)) < 4.0


# ------------------------------------------------------------------------------------------ the file


def test_calibration_file_round_trip(synthetic, tmp_path):
    calibration = synthetic["calibration"]
    path = calibration.save(tmp_path / "cal.npz")
    loaded = load_calibration(path, SPEC)
    import json

    meta = json.loads(np.load(path)["meta_json"].tobytes())
    assert meta["format"] == "yoto-sensor-calibration" and meta["version"] == 1
    assert meta["sensor"] == {"name": "gelsight_mini", "width_px": 320, "height_px": 240, "mm_per_px": 0.0634}
    assert meta["background_sha256"] == calibration.background_sha256
    assert meta["model"]["type"] == "polynomial-lut"
    image = synthetic["images"][19]
    a, b = reconstruct(image, calibration), reconstruct(image, loaded)
    np.testing.assert_array_equal(a.points_sensor, b.points_sensor)
    np.testing.assert_array_equal(render_image(a.height_map_m, calibration), render_image(a.height_map_m, loaded))


def test_render_gain_makes_rendered_presses_read_like_the_real_ones(synthetic):
    """A renderer that draws every colour change 25% faint: the round-trip gain, fitted on the training presses,
    restores what the gradient model reads on rendered presses (about 1 / 0.75 over the pad), and held-out presses
    rendered with it read within 3% of their real images (the faint renderer: 15-30% short)."""
    calibration = synthetic["calibration"]
    ungained = replace(calibration.image_model, gain=None)
    faint = replace(calibration, image_model=replace(ungained, coefficients=0.75 * ungained.coefficients))
    changes = {
        i: model_colour_change(image, calibration.background_i16, calibration.smooth)
        for i, image in enumerate(synthetic["images"][:16])
    }
    circles = dict(enumerate(synthetic["circles"][:16]))
    gain, before, after = round_trip_gain(faint, changes, circles, BALL_RADIUS_PX, 0.8)
    assert before < 0.85 and abs(after - 1.0) < 0.03
    x, y = (v[20:-20:10, 20:-20:10].ravel() for v in normalised_xy(SPEC.height_px, SPEC.width_px))
    exponents = monomial_exponents(2, faint.image_model.config.position_degree)
    assert np.all(np.abs(monomials(np.stack([x, y], 1), exponents) @ gain * 0.75 - 1.0) < 0.1)
    fixed = replace(faint, image_model=replace(faint.image_model, gain=gain))
    ratios = []
    for (cx, cy, a), image in zip(synthetic["circles"][16:], synthetic["images"][16:], strict=True):
        height = press_height_map(cx, cy, a, BALL_RADIUS_M)
        inside = np.hypot(*np.meshgrid(np.arange(SPEC.width_px) - cx, np.arange(SPEC.height_px) - cy)) < 0.8 * a
        gx, gy = height_gradients(height, SPEC.pixel_size_m)

        def read(frame, gx=gx, gy=gy, inside=inside):
            rx, ry = calibration.gradient_model.predict(
                model_colour_change(frame, calibration.background_i16, calibration.smooth)
            )
            return np.sum((rx * gx + ry * gy)[inside]) / np.sum((gx * gx + gy * gy)[inside])

        real = read(image)
        ratios.append((read(render_image(height, faint)) / real, read(render_image(height, fixed)) / real))
    ratios = np.array(ratios)
    assert np.all(ratios[:, 0] < 0.85) and np.all(np.abs(ratios[:, 1] - 1.0) < 0.03)


def test_render_region_draws_only_there_and_exactly_inside(synthetic):
    calibration = synthetic["calibration"]
    cx, cy, a = 150.0, 110.0, 25.0
    height = press_height_map(cx, cy, a, BALL_RADIUS_M)
    r = np.hypot(*np.meshgrid(np.arange(SPEC.width_px) - cx, np.arange(SPEC.height_px) - cy))
    full, part = render_image(height, calibration), render_image(height, calibration, region=r < a + 12)
    np.testing.assert_array_equal(part[r < a], full[r < a])  # the blur (2 px) reaches 8 px: the rest is exact
    np.testing.assert_array_equal(part[r > a + 24], calibration.background[r > a + 24])
    assert np.abs(full[r > a + 24].astype(int) - calibration.background[r > a + 24]).max() > 0


def test_calibration_files_without_a_render_gain_load_as_before(synthetic, tmp_path):
    calibration = synthetic["calibration"]
    assert calibration.image_model.gain is not None
    plain = replace(calibration, image_model=replace(calibration.image_model, gain=None))
    loaded = load_calibration(plain.save(tmp_path / "plain.npz"), SPEC)
    assert loaded.image_model.gain is None
    height = press_height_map(150.0, 110.0, 25.0, BALL_RADIUS_M)
    np.testing.assert_array_equal(render_image(height, loaded), render_image(height, plain))
    gained = load_calibration(calibration.save(tmp_path / "gained.npz"), SPEC)
    np.testing.assert_array_equal(gained.image_model.gain, calibration.image_model.gain)


def test_calibration_for_another_sensor_is_refused(synthetic, tmp_path):
    other = GelSightSpec(name="gelsight_r15", width_px=320, height_px=240, mm_per_px=0.0634)
    path = replace_spec(synthetic["calibration"], other).save(tmp_path / "r15.npz")
    with pytest.raises(InputError, match="calibration is for sensor 'gelsight_r15'") as info:
        load_calibration(path, SPEC)
    assert info.value.path == path
    assert load_calibration(path).spec == other  # without an expected sensor it loads


def test_frame_of_another_size_is_refused(synthetic):
    big = np.zeros((480, 640, 3), np.uint8)
    with pytest.raises(InputError, match="640x480"):
        reconstruct(big, synthetic["calibration"], source="frame.png")
    with pytest.raises(InputError, match="uint8"):
        reconstruct(synthetic["images"][0].astype(np.float32), synthetic["calibration"])


def test_saturated_frame_is_refused(synthetic):
    frame = synthetic["images"][16].copy()
    frame[:60] = 255
    with pytest.raises(InputError, match="saturated"):
        reconstruct(frame, synthetic["calibration"])


def test_frame_from_another_sensor_is_refused(synthetic):
    """A frame whose untouched gel does not look like the calibration's background (another sensor)."""
    foreign = np.roll(synthetic["images"][16], 1, axis=2)  # channels swapped: other LEDs
    with pytest.raises(InputError, match="differs from the calibration's background"):
        reconstruct(foreign, synthetic["calibration"])


def test_background_from_another_sensor_is_refused(synthetic):
    foreign = np.roll(synthetic["background"], 1, axis=2)
    with pytest.raises(InputError, match="background does not match the press images"):
        calibrate(foreign, synthetic["images"][:6], 2 * BALL_RADIUS_M, background_path="bg.png")
    with pytest.raises(InputError, match="from another sensor"):
        with_background(synthetic["calibration"], foreign, "bg.png")
    # A fresh background of the same sensor (a little brighter) is accepted and used.
    fresh = np.clip(synthetic["background"].astype(int) + 2, 0, 255).astype(np.uint8)
    assert (
        with_background(synthetic["calibration"], fresh).background_sha256 != synthetic["calibration"].background_sha256
    )


def test_not_a_calibration_file(tmp_path):
    from yoto.io import save_npz_atomic

    other = save_npz_atomic(tmp_path / "model.npz", {"x": np.zeros(3)}, {"format": "yoto-object-model"})
    with pytest.raises(InputError, match="not a sensor calibration file"):
        load_calibration(other)
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not an npz")
    with pytest.raises(InputError, match="not a readable sensor calibration file"):
        load_calibration(garbage)
    with pytest.raises(InputError, match="not found"):
        load_calibration(tmp_path / "missing.npz")


def test_render_refuses_bad_height_maps(synthetic):
    calibration = synthetic["calibration"]
    with pytest.raises(InputError, match="shape"):
        render_image(np.zeros((10, 10)), calibration)
    with pytest.raises(InputError, match="millimetres"):
        render_image(np.full((SPEC.height_px, SPEC.width_px), -0.8), calibration)  # mm, not m


def test_presses_without_contact_are_left_out_with_a_reason(synthetic):
    images = synthetic["images"][:5] + [synthetic["background"].copy()]
    _, report = calibrate(synthetic["background"], images, 2 * BALL_RADIUS_M)
    assert [p.used for p in report.presses] == [True] * 5 + [False]
    assert "no contact" in report.presses[-1].reason
    with pytest.raises(InputError, match="usable presses"):
        calibrate(synthetic["background"], [synthetic["background"]] * 5, 2 * BALL_RADIUS_M)


def test_find_press_circle_uses_the_model(synthetic):
    cx, cy, a = synthetic["circles"][21]
    x, y, r = find_press_circle(synthetic["images"][21], synthetic["calibration"], BALL_RADIUS_PX)
    assert np.hypot(x - cx, y - cy) < 1.0 and abs(r - a) < 0.12 * a


def replace_spec(calibration: SensorCalibration, spec: GelSightSpec) -> SensorCalibration:
    return replace(calibration, spec=spec)


def test_cli_reconstruct_render_bench(synthetic, tmp_path, capsys):
    """`yoto sensor reconstruct|render|bench` on a saved calibration; an empty cloud for no contact."""
    from PIL import Image

    from yoto.cli import main
    from yoto.io import read_ply_points

    calibration = synthetic["calibration"].save(tmp_path / "cal.npz")
    frames = tmp_path / "frames"
    frames.mkdir()
    Image.fromarray(synthetic["images"][16]).save(frames / "press.png")
    Image.fromarray(synthetic["background"]).save(frames / "empty.png")
    assert (
        main(
            [
                "sensor",
                "reconstruct",
                str(frames / "press.png"),
                "--calibration",
                str(calibration),
                "--out",
                str(tmp_path / "press.ply"),
            ]
        )
        == 0
    )
    points, _ = read_ply_points(tmp_path / "press.ply")
    expected = reconstruct(synthetic["images"][16], synthetic["calibration"]).points_sensor
    np.testing.assert_allclose(points, expected, atol=1e-9)  # float32 in the file
    assert (
        main(
            [
                "sensor",
                "reconstruct",
                str(frames),
                "--calibration",
                str(calibration),
                "--out",
                str(tmp_path / "out"),
            ]
        )
        == 0
    )
    assert len(read_ply_points(tmp_path / "out" / "empty.ply")[0]) == 0
    assert main(["sensor", "render", "--calibration", str(calibration), "--out", str(tmp_path / "r.png")]) == 0
    assert np.asarray(Image.open(tmp_path / "r.png")).shape == (SPEC.height_px, SPEC.width_px, 3)
    assert main(["sensor", "bench", "--calibration", str(calibration), "--repeats", "20"]) == 0
    assert "image -> point cloud" in capsys.readouterr().out
    big = tmp_path / "big.png"
    Image.fromarray(np.zeros((480, 640, 3), np.uint8)).save(big)
    assert (
        main(
            [
                "sensor",
                "reconstruct",
                str(big),
                "--calibration",
                str(calibration),
                "--out",
                str(tmp_path / "x.ply"),
            ]
        )
        == 2
    )
    assert "640x480" in capsys.readouterr().err


def test_a_video_is_read_frame_by_frame(tmp_path):
    """The `video` extra decodes a GelSight clip into frames (mp4 is lossy: names, shapes and levels survive)."""
    iio = pytest.importorskip("imageio.v3", reason="the video extra (pip install 'yoto[video]') is not installed")
    pytest.importorskip("av", reason="the video extra (pip install 'yoto[video]') is not installed")
    from yoto.sensor.cli import _read_frames

    frames = np.zeros((3, 240, 320, 3), np.uint8)
    frames[1] = 128
    frames[2, :, :160] = 255
    path = tmp_path / "clip.mp4"
    iio.imwrite(path, frames, plugin="pyav", codec="mpeg4", fps=10)
    read = list(_read_frames(path))
    assert [name for name, _ in read] == ["frame_00000", "frame_00001", "frame_00002"]
    for (_, frame), original in zip(read, frames, strict=True):
        assert frame.shape == (240, 320, 3) and frame.dtype == np.uint8
        assert abs(float(frame.mean()) - float(original.mean())) < 5


def test_image_path_reconstructor_feeds_the_contact_simulator(synthetic, builtin_models):
    """Simulated presses through rendered images and their reconstruction: clouds on the same surface as the
    geometric path, deterministic for a height map, ground truth following the observed cloud."""
    from yoto.sensor.optical import image_path_reconstructor
    from yoto.simulate.scenarios import PairSimulator

    calibration = synthetic["calibration"]
    hook = image_path_reconstructor(calibration)
    model = builtin_models["fruit"]
    simulated = PairSimulator(model, reconstruct=hook).pair(seed=3, index=0)
    height_map = simulated.height_maps["left"]
    points = simulated.pair.left.points_sensor
    assert np.array_equal(hook(height_map), points)  # seeded from the height map itself
    # The reconstructed surface lies on the simulated gel surface: compare heights at the same pixels.
    from yoto.sensor.spec import GELSIGHT_MINI

    pixel = GELSIGHT_MINI.pixel_size_m
    cols = np.round(points[:, 0] / pixel + (GELSIGHT_MINI.width_px - 1) / 2).astype(int)
    rows = np.round(points[:, 1] / pixel + (GELSIGHT_MINI.height_px - 1) / 2).astype(int)
    assert np.median(np.abs(points[:, 2] - height_map[rows, cols])) < 0.1e-3
    # Ground truth is the surface point nearest the observed cloud's centroid (SPEC), not the gel's full contact.
    from yoto.geometry import transform_points

    for side in ("left", "right"):
        press = simulated.contacts[side].press
        centroid = transform_points(press.T_object_sensor, simulated.pair.contact(side).points_sensor.mean(axis=0))
        assert np.linalg.norm(press.p_object - model.nearest_surface_point(centroid)) < 1.5 * model.point_spacing_m


@pytest.mark.parametrize("unknown_box", [(5, 12, 2, 38), (1, 29, 17, 21), (0, 30, 0, 40)])
def test_harmonic_fill_solves_the_five_point_equations(unknown_box):
    """Each unknown cell: (neighbours on the grid + 1e-6) * u = sum of its neighbours (known: their values), whether
    the unknowns are numbered along rows (a wide region) or along columns (a tall one), and with no known cell."""
    from yoto.sensor.reconstruction import _harmonic_fill

    rng = np.random.default_rng(4)
    known = np.ones((30, 40), bool)
    row0, row1, col0, col1 = unknown_box
    known[row0:row1, col0:col1] = rng.random((row1 - row0, col1 - col0)) < (0.0 if row1 - row0 == 30 else 0.1)
    values = rng.normal(0.0, 1e-4, known.shape)
    filled = np.where(known, values, 0.0)
    filled[~known] = _harmonic_fill(known, values)
    worst = 0.0
    for r, c in zip(*np.nonzero(~known), strict=True):
        neighbours = [(r + dr, c + dc) for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1))]
        neighbours = [(i, j) for i, j in neighbours if 0 <= i < 30 and 0 <= j < 40]
        residual = (len(neighbours) + 1e-6) * filled[r, c] - sum(filled[i, j] for i, j in neighbours)
        worst = max(worst, abs(residual))
    assert worst < 1e-15
    if not known.any():  # nothing known: the small diagonal term holds everything at zero
        assert np.abs(filled).max() == 0.0
    else:
        assert np.abs(filled[~known]).max() > 1e-6  # the known values reach the unknown cells


def test_press_folders_laid_out_per_press_or_per_ball(tmp_path):
    """`--presses` takes images, one sub-folder per press, or the shared example's one sub-folder per ball
    (presses/6.310mm/k/gelsight.png); two balls' folders are refused with both named, never mixed."""
    from PIL import Image

    from yoto.sensor.presses import list_press_images

    def write_presses(folder, count):
        for k in range(count):
            (folder / str(k)).mkdir(parents=True)
            Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(folder / str(k) / "gelsight.png")

    write_presses(tmp_path / "presses" / "6.310mm", 11)
    (tmp_path / "presses" / "catalog.csv").write_text("press_dir,ball_diameter_mm\n6.310mm,6.31\n")
    per_ball = list_press_images(tmp_path / "presses")
    assert [p.relative_to(tmp_path / "presses").as_posix() for p in per_ball[:3]] == [
        "6.310mm/0/gelsight.png",
        "6.310mm/1/gelsight.png",
        "6.310mm/2/gelsight.png",
    ]
    assert len(per_ball) == 11 and per_ball == list_press_images(tmp_path / "presses" / "6.310mm")
    write_presses(tmp_path / "presses" / "4.000mm", 2)
    with pytest.raises(InputError, match=r"4.000mm \(2 images\).*6.310mm \(11 images\)"):
        list_press_images(tmp_path / "presses")
    (tmp_path / "empty" / "a" / "b").mkdir(parents=True)
    with pytest.raises(InputError, match="no image files"):
        list_press_images(tmp_path / "empty")
