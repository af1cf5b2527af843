"""A second optical model of a GelSight, deliberately unlike the fitted one: shading under coloured point lights.

The fitted optical simulator (`optical.render_image`) is the inverse of our own calibration's polynomial model,
so images it renders are easy for our reconstruction in a way no real sensor is. This model renders from
physics instead, with none of the calibration's forms: the gel's inner surface is a Lambertian membrane with a
little specular sheen, lit by three coloured point lights (LEDs) beside and behind the pad, seen by a camera
with vignetting, a tone curve, optical blur and noise; the membrane also smooths the indenter's shape.

    p = (x, y, h(x, y))                               gel surface point (sensor frame, h <= 0)
    n = (h_x, h_y, -1) / |(h_x, h_y, -1)|             surface normal facing the camera (behind the gel, at -z)
    l_k = (P_k - p) / |P_k - p|                       direction to light k at P_k
    I_c = vignette * (ambient_c + sum_k colour_kc * power * (max(0, n . l_k) + sheen * max(0, n . h_k)^shine)
                      / |P_k - p|^2 * D^2)            linear intensity of channel c (D: a light's distance
                                                      from the pad centre, so `power` is the level there)
    image = 255 * (I / 255)^gamma, blurred, plus noise, rounded to uint8

Use it to check that calibration, reconstruction and localization do not depend on the look of our own
simulator: calibrate from ball presses it renders (as a lab calibrates a new sensor), then reconstruct contacts
it renders. `ShadingSensor.varied(rng)` draws a sensor with other lights, gel and camera.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from yoto.errors import InputError
from yoto.sensor.calibration import SensorCalibration
from yoto.sensor.spec import GELSIGHT_MINI, GelSightSpec

EXPOSURE_LEVEL = 200.0  # a varied sensor's exposure puts its background's brightest pixels at this level


@dataclass(frozen=True)
class ShadingSensor:
    """A GelSight rendered by shading (module docstring). Lengths in metres, levels on the 0-255 scale."""

    spec: GelSightSpec = GELSIGHT_MINI  # image grid
    light_azimuth_deg: tuple[float, ...] = (0.0, 120.0, 240.0)  # where each LED sits around the pad
    light_distance_m: float = 0.03  # LEDs' horizontal distance from the pad centre
    light_height_m: float = 0.007  # LEDs' height behind the gel surface (toward the camera)
    light_colours: tuple[tuple[float, ...], ...] = (
        (1.0, 0.15, 0.05),
        (0.1, 1.0, 0.2),
        (0.05, 0.2, 1.0),
    )  # RGB of each LED (rows), a little of each in the other channels as real LEDs and dyes give
    power: float = 180.0  # linear level a light gives a surface facing it at the pad centre's distance
    ambient: tuple[float, ...] = (20.0, 30.0, 30.0)  # light that does not depend on the surface normal
    sheen: float = 0.15  # weight of the specular term
    shininess: float = 12.0  # its exponent
    gamma: float = 0.8  # camera tone curve (output = 255 (linear / 255)^gamma)
    vignetting: float = 0.25  # brightness falls by this fraction from the centre to the corners
    blur_px: float = 1.0  # optical blur (Gaussian sigma, pixels)
    noise_std: float = 1.5  # camera noise (levels)
    gel_sigma_m: float = 0.0001  # the membrane smooths the indenter's shape (Gaussian sigma; 0: not at all)

    def varied(self, rng: np.random.Generator, amount: float = 1.0) -> ShadingSensor:
        """Another sensor of this kind: LEDs moved and recoloured, other gel, camera and noise (`amount` 0..1+)."""

        def jitter(value: float, relative: float) -> float:
            return float(value * np.exp(amount * relative * rng.uniform(-1.0, 1.0)))

        colours = np.clip(
            np.asarray(self.light_colours) * np.exp(amount * 0.25 * rng.uniform(-1, 1, (3, 3))), 0.0, None
        )
        sensor = replace(
            self,
            light_azimuth_deg=tuple(float(a + amount * rng.uniform(-25.0, 25.0)) for a in self.light_azimuth_deg),
            light_distance_m=jitter(self.light_distance_m, 0.3),
            light_height_m=jitter(self.light_height_m, 0.4),
            light_colours=tuple(tuple(float(c) for c in row) for row in colours),
            power=jitter(self.power, 0.25),
            ambient=tuple(jitter(a, 0.4) for a in self.ambient),
            sheen=jitter(self.sheen, 0.7),
            shininess=jitter(self.shininess, 0.5),
            gamma=jitter(self.gamma, 0.2),
            vignetting=float(np.clip(self.vignetting + amount * rng.uniform(-0.15, 0.15), 0.0, 0.6)),
            blur_px=float(max(0.0, self.blur_px + amount * rng.uniform(-0.7, 1.5))),
            noise_std=jitter(self.noise_std, 0.6),
            gel_sigma_m=float(max(0.0, self.gel_sigma_m + amount * rng.uniform(-1e-4, 1.5e-4))),
        )
        return sensor.exposed()

    def exposed(self, brightest: float = EXPOSURE_LEVEL) -> ShadingSensor:
        """This sensor with its exposure set as a lab sets it: the background's brightest pixels at `brightest`."""
        level = float(np.percentile(self.background(), 99.9))
        if level <= brightest:
            return self
        gain = (brightest / level) ** (1.0 / self.gamma)
        return replace(self, power=self.power * gain, ambient=tuple(a * gain for a in self.ambient))

    def background(self, rng: np.random.Generator | None = None) -> np.ndarray:
        """The no-contact image (the flat gel), (rows, cols, 3) uint8."""
        return self.render(np.zeros((self.spec.height_px, self.spec.width_px)), rng)

    def render(self, height_map_m: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """The (rows, cols, 3) uint8 RGB image of a gel height map (metres, <= 0 where pressed); `rng`: noise."""
        spec = self.spec
        height = np.asarray(height_map_m, dtype=np.float64)
        if height.shape != (spec.height_px, spec.width_px) or not np.isfinite(height).all():
            raise InputError(f"height map must be finite, ({spec.height_px}, {spec.width_px}); got {height.shape}")
        if self.gel_sigma_m > 0:
            height = ndimage.gaussian_filter(height, self.gel_sigma_m / spec.pixel_size_m, mode="nearest")
        gy, gx = np.gradient(height, spec.pixel_size_m)
        x, y = spec.pixel_xy_sensor()
        normal = np.stack([gx, gy, -np.ones_like(gx)])
        normal /= np.linalg.norm(normal, axis=0)
        surface = np.stack([x, y, height])
        view = np.array([0.0, 0.0, -1.0])[:, None, None]  # toward the camera, far behind the gel
        linear = np.zeros((3,) + height.shape)
        for azimuth, colour in zip(self.light_azimuth_deg, self.light_colours, strict=True):
            angle = np.radians(azimuth)
            light = np.array(
                [self.light_distance_m * np.cos(angle), self.light_distance_m * np.sin(angle), -self.light_height_m]
            )
            to_light = light[:, None, None] - surface
            distance2 = np.einsum("kij,kij->ij", to_light, to_light)
            to_light /= np.sqrt(distance2)
            lambert = np.maximum(np.einsum("kij,kij->ij", normal, to_light), 0.0)
            half = to_light + view
            half /= np.linalg.norm(half, axis=0)
            specular = np.maximum(np.einsum("kij,kij->ij", normal, half), 0.0) ** self.shininess
            reference2 = self.light_distance_m**2 + self.light_height_m**2
            shade = self.power * (lambert + self.sheen * specular) * reference2 / distance2
            linear += np.asarray(colour)[:, None, None] * shade
        linear += np.asarray(self.ambient)[:, None, None]
        radius2 = (x / (spec.pad_size_m[0] / 2)) ** 2 + (y / (spec.pad_size_m[1] / 2)) ** 2
        linear *= 1.0 - self.vignetting * radius2 / 2.0
        image = 255.0 * (np.clip(linear, 0.0, None) / 255.0) ** self.gamma
        image = np.moveaxis(image, 0, 2)
        if self.blur_px > 0:
            image = ndimage.gaussian_filter(image, (self.blur_px, self.blur_px, 0), mode="nearest")
        if rng is not None and self.noise_std > 0:
            image = image + rng.normal(scale=self.noise_std, size=image.shape)
        return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def calibrate_shading_sensor(
    sensor: ShadingSensor,
    rng: np.random.Generator,
    presses: int = 44,
    ball_diameter_m: float = 6.31e-3,
    contact_radius_px: tuple[float, float] = (22.0, 30.0),
) -> SensorCalibration:
    """Calibrate a shading sensor as a lab calibrates a new GelSight: ball presses all over the pad, noisy frames.

    The presses are Hertz presses (`press_height_map`) of a ball of `ball_diameter_m` with contact radii uniform in
    `contact_radius_px`, centred anywhere on the pad (some cut by its border), as the shared real presses are.
    """
    from yoto.sensor.ball_calibration import calibrate
    from yoto.sensor.sphere import press_height_map

    spec = sensor.spec
    background = sensor.background(rng)
    images = []
    for _ in range(presses):
        radius = rng.uniform(*contact_radius_px)
        centre = rng.uniform(5.0, spec.width_px - 5.0), rng.uniform(5.0, spec.height_px - 5.0)
        images.append(sensor.render(press_height_map(*centre, radius, ball_diameter_m / 2, spec), rng))
    calibration, _ = calibrate(background, images, ball_diameter_m, spec=spec)
    return calibration
