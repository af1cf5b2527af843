"""A third optical model of a GelSight: a lookup table of the colour change by gradient, measured on real presses.

The fitted optical simulator (`optical.render_image`) inverts our own calibration's polynomial model, and the
shading sensor (`shading.py`) is physics calibrated from presses it renders itself. This one is neither: it is
read off real ball presses with no model form at all, as a lab would build a lookup-table renderer:

- each press's contact circle (from `ball_calibration.calibrate`, which also gives the calibration a benchmark
  reconstructs with) gives the true gel gradients inside the contact (the ball's sphere, `sphere_gradients`);
- the colour change against the background at those pixels (each press's small lighting drift removed), divided by
  the pixel's gain (its background level over the pad's mean, per channel: the lighting that reaches that pixel), is
  averaged in bins of (dz/dx, dz/dy) (`step` wide), separately for a coarse `places` x `places` grid of places on the
  pad (samples shared between neighbouring places by their bilinear weights), and bins no press reached copy the
  nearest bin that one did: slopes beyond the steepest seen saturate, nothing is extrapolated;
- rendering looks each pixel's gradient up (bilinear in the gradient and between places), multiplies it by the
  pixel's gain, blurs the colour change (`blur_px`, chosen against held-out real presses:
  `benchmarks/table_renderer_check.py`), adds the real background and Gaussian noise of the level measured between
  the real presses and the background.

Unlike our polynomial model, the table keeps what the real presses show at the bottom of a press: a pressed but
flat gel is not the background (median +5 / +5 / +10 levels on the 44 example presses where the ball's gradient is
zero). Untouched gel must render as the background, so that zero-gradient change is faded in with the depth of the
press (full at `pressed_depth_m` and deeper).

The defaults (0.05 bins, 5 x 5 places, 2 px blur, 0.8 mm, the per-pixel gain) are the held-out check's best: colour
RMS 6.19 levels against the real presses (the fitted renderer 6.59), and our calibration reads its held-out ball
presses about as it reads the real ones (median |radius error| 4.7%; real presses 3.3%, fitted renderer 4.4%). Without
the per-pixel gain (stop 16's table, `per_pixel_gain=False`) a press's colours were its place's average lighting, which
our calibration, knowing the real lighting per pixel, read 12% off (docs/journal/sensor.md, stops 16 and 17).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from yoto.errors import InputError
from yoto.sensor.spec import GELSIGHT_MINI, GelSightSpec


@dataclass(frozen=True)
class TableSensor:
    """A lookup-table GelSight renderer (module docstring). Levels on the 0-255 scale."""

    spec: GelSightSpec
    background: np.ndarray  # (rows, cols, 3) uint8: the real no-contact image
    table: np.ndarray  # (places, places, bins, bins, 3) float32: colour change at place (row, col), bin (gy, gx)
    step: float  # gradient bin width (dimensionless)
    limit: float  # bins span [-limit, limit] in each gradient component; beyond, the gradient is clamped
    blur_px: float  # Gaussian blur of the colour change (pixels)
    noise_std: np.ndarray  # (3,) per-channel noise of a real frame against the background
    pressed_depth_m: float  # the zero-gradient change is faded in from no depth to this depth
    gain: np.ndarray | None = None  # (rows, cols, 3) per-pixel gain the table's change is multiplied by (None: 1)

    def _place_weights(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Per pixel, the (row place, col place, weight) of the up to 4 places it blends (bilinear)."""
        return place_weights(self.table.shape[0], self.spec.height_px, self.spec.width_px)

    def lookup(self, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
        """(rows, cols, 3) colour change of each pixel's gradient (bilinear in gradient and place, clamped), before the
        per-pixel `gain`; `gx`, `gy` are whole frames ((rows, cols) of `spec`), as a pixel's place is its position."""
        bins = self.table.shape[2]
        fx = (np.clip(gx, -self.limit, self.limit) + self.limit) / self.step
        fy = (np.clip(gy, -self.limit, self.limit) + self.limit) / self.step
        ix = np.clip(np.floor(fx).astype(np.intp), 0, bins - 2)
        iy = np.clip(np.floor(fy).astype(np.intp), 0, bins - 2)
        tx, ty = (fx - ix)[..., None], (fy - iy)[..., None]
        change = np.zeros(gx.shape + (3,), np.float32)
        for place_row, place_col, weight in self._place_weights():
            cell = functools.partial(self._cell, place_row, place_col)
            blended = (1 - ty) * ((1 - tx) * cell(iy, ix) + tx * cell(iy, ix + 1)) + ty * (
                (1 - tx) * cell(iy + 1, ix) + tx * cell(iy + 1, ix + 1)
            )
            change += weight[..., None] * blended
        return change

    @functools.cached_property
    def flat_change(self) -> np.ndarray:
        """(rows, cols, 3) the colour change of a pressed but flat gel at each pixel (the zero-gradient lookup, before
        the gain): the same for every frame, so looked up once."""
        zero = np.zeros((self.spec.height_px, self.spec.width_px))
        return self.lookup(zero, zero)

    def _cell(self, place_row: np.ndarray, place_col: np.ndarray, bin_y: np.ndarray, bin_x: np.ndarray) -> np.ndarray:
        """The table's colour change at each pixel's place and gradient bin, (rows, cols, 3)."""
        return self.table[place_row, place_col, bin_y, bin_x]

    def render(self, height_map_m: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """The (rows, cols, 3) uint8 RGB image of a gel height map (metres, <= 0 where pressed); `rng`: noise."""
        from yoto.sensor.optical import height_gradients

        spec = self.spec
        height = np.asarray(height_map_m, dtype=np.float64)
        if height.shape != (spec.height_px, spec.width_px) or not np.isfinite(height).all():
            raise InputError(f"height map must be finite, ({spec.height_px}, {spec.width_px}); got {height.shape}")
        gx, gy = height_gradients(height, spec.pixel_size_m)
        change = self.lookup(gx, gy)
        # Untouched gel is the background: fade out the change a flat but pressed gel shows.
        unpressed = 1.0 - np.clip(-height / self.pressed_depth_m, 0.0, 1.0)
        change -= unpressed[..., None].astype(np.float32) * self.flat_change
        if self.gain is not None:
            change *= self.gain
        if self.blur_px > 0:
            change = ndimage.gaussian_filter(change, (self.blur_px, self.blur_px, 0), mode="nearest")
        image = self.background.astype(np.float32) + change
        if rng is not None:
            image += rng.normal(size=image.shape).astype(np.float32) * self.noise_std.astype(np.float32)
        return np.clip(np.rint(image), 0, 255).astype(np.uint8)


@functools.lru_cache(maxsize=8)
def place_weights(places: int, rows: int, cols: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Bilinear weights of each pixel on a `places` x `places` grid of place centres (clamped at the pad's edges):
    four (row place index, col place index, weight) arrays of shape (rows, cols)."""

    def axis(size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        position = np.clip((np.arange(size) + 0.5) / size * places - 0.5, 0.0, places - 1.0)
        low = np.minimum(np.floor(position).astype(np.intp), max(places - 2, 0))
        return low, np.minimum(low + 1, places - 1), position - low

    r0, r1, tr = axis(rows)
    c0, c1, tc = axis(cols)
    out = []
    for r_index, r_weight in ((r0, 1 - tr), (r1, tr)):
        for c_index, c_weight in ((c0, 1 - tc), (c1, tc)):
            out.append(
                (
                    np.broadcast_to(r_index[:, None], (rows, cols)),
                    np.broadcast_to(c_index[None, :], (rows, cols)),
                    (r_weight[:, None] * c_weight[None, :]).astype(np.float32),
                )
            )
    return out


def fit_table_sensor(
    background: np.ndarray,
    presses: Sequence[np.ndarray],
    circles: Sequence[tuple[float, float, float]],
    ball_radius_m: float,
    spec: GelSightSpec = GELSIGHT_MINI,
    *,
    step: float = 0.05,
    places: int = 5,
    inside_fraction: float = 0.9,
    min_weight: float = 2.0,
    blur_px: float = 2.0,
    pressed_depth_m: float = 8e-4,
    per_pixel_gain: bool = True,
) -> TableSensor:
    """A `TableSensor` read off real ball presses (uint8 RGB images) with their contact circles (x, y, radius px).

    Pixels within `inside_fraction` of each contact radius are the samples (there the gel follows the ball); a bin
    holds the weighted mean of its samples when their place weights add up to `min_weight`, else it copies the
    nearest bin that does (per place). `per_pixel_gain`: the samples are read relative to their pixel's background
    (module docstring); False gives stop 16's table, whose places average the lighting.
    """
    from yoto.sensor.sphere import sphere_gradients

    rows, cols = spec.height_px, spec.width_px
    ball_radius_px = ball_radius_m / spec.pixel_size_m
    background_f = background.astype(np.float32)
    gain = None
    if per_pixel_gain:  # each pixel's lighting: its background over the pad's mean, per channel
        lit = np.maximum(background_f, 1.0)
        gain = (lit / lit.mean(axis=(0, 1))).astype(np.float32)
    samples, far = [], []
    for image, (cx, cy, a) in zip(presses, circles, strict=True):
        change = image.astype(np.float32) - background_f
        tx, ty, r = sphere_gradients(cx, cy, ball_radius_px, (rows, cols))
        outside = r > 3 * a
        change -= np.median(change[outside], axis=0)  # the press's lighting drift
        # Pixel noise: the colour change less its 5x5 mean (the contact's smooth tail, the drift), white-noise scaled.
        fine = change - ndimage.uniform_filter(change, (5, 5, 1), mode="nearest")
        far.append(fine[outside] * np.sqrt(25 / 24))
        inside = r < inside_fraction * a
        relative_change = change if gain is None else change / gain
        samples.append((tx[inside], ty[inside], relative_change[inside], np.nonzero(inside)))
    seen = max(float(np.abs(np.concatenate([s[0] for s in samples] + [s[1] for s in samples])).max()), step)
    limit = step * np.ceil(seen / step)
    bins = int(round(2 * limit / step)) + 1
    sums = np.zeros((places, places, bins, bins, 3))
    weights = np.zeros((places, places, bins, bins))
    weight_maps = place_weights(places, rows, cols)
    for gx, gy, change, (pixel_rows, pixel_cols) in samples:
        ix = np.rint((gx + limit) / step).astype(np.intp)
        iy = np.rint((gy + limit) / step).astype(np.intp)
        for place_row, place_col, weight in weight_maps:
            w = weight[pixel_rows, pixel_cols].astype(np.float64)
            index = (place_row[pixel_rows, pixel_cols], place_col[pixel_rows, pixel_cols], iy, ix)
            np.add.at(weights, index, w)
            np.add.at(sums, index, w[:, None] * change)
    table = np.zeros_like(sums, dtype=np.float32)
    reached = np.zeros((places, places), bool)
    for row in range(places):
        for col in range(places):
            filled = weights[row, col] >= min_weight
            if not filled.any():
                continue
            reached[row, col] = True
            mean = sums[row, col] / np.maximum(weights[row, col], 1e-12)[..., None]
            _, (near_rows, near_cols) = ndimage.distance_transform_edt(~filled, return_indices=True)
            table[row, col] = mean[near_rows, near_cols]
    if not reached.any():
        raise InputError("no ball press gives a usable contact: the table renderer has nothing to read")
    _, (place_rows, place_cols) = ndimage.distance_transform_edt(~reached, return_indices=True)
    table = table[place_rows, place_cols]  # a place no press reached copies the nearest one that was
    differences = np.concatenate(far).astype(np.float64)
    low, high = np.percentile(differences, [0.5, 99.5], axis=0)
    noise_std = np.array(
        [differences[(differences[:, c] >= low[c]) & (differences[:, c] <= high[c]), c].std() for c in range(3)]
    )
    return TableSensor(spec, background.copy(), table, step, float(limit), blur_px, noise_std, pressed_depth_m, gain)


def read_press_folder(folder: str | Path, spec: GelSightSpec = GELSIGHT_MINI):
    """(background, press images, ball diameter in metres) of a folder laid out as the shared real presses:
    `background.png` and `presses/catalog.csv` (press folder, ball diameter in mm; one diameter)."""
    import csv

    from yoto.sensor.presses import list_press_images, load_image

    folder = Path(folder)
    catalog = folder / "presses" / "catalog.csv"
    if not catalog.is_file():
        raise InputError("a table renderer's folder needs background.png and presses/catalog.csv", folder)
    with open(catalog, newline="") as file:
        entries = list(csv.DictReader(file))
    diameters = {float(entry["ball_diameter_mm"]) for entry in entries}
    if len(diameters) != 1:
        raise InputError(f"the presses use {len(diameters)} ball diameters; the table renderer takes one", catalog)
    images = []
    for entry in entries:
        images += [load_image(path, spec) for path in list_press_images(folder / "presses" / entry["press_dir"])]
    return load_image(folder / "background.png", spec), images, diameters.pop() * 1e-3


@functools.lru_cache(maxsize=2)
def table_sensor_and_calibration(folder: str):
    """The table renderer of a press folder (`read_press_folder`) and the calibration `yoto sensor calibrate` makes
    from the same presses (its refined contact circles are the table's), built once per process."""
    from yoto.sensor.ball_calibration import calibrate

    background, images, diameter_m = read_press_folder(folder)
    calibration, report = calibrate(background, images, diameter_m)
    used = [(image, press) for image, press in zip(images, report.presses, strict=True) if press.used]
    circles = [(p.contact_x_px, p.contact_y_px, p.contact_radius_px) for _, p in used]
    sensor = fit_table_sensor(background, [image for image, _ in used], circles, diameter_m / 2, calibration.spec)
    return sensor, calibration
