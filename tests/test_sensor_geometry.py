"""Sensor pieces that need no calibration: circles, ball ground truth, Poisson integration, sphere fit."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from yoto.sensor.optical import height_gradients
from yoto.sensor.presses import CircleConfig, NoCircleError, find_contact_circle, ring_circle
from yoto.sensor.reconstruction import divergence, poisson_integrate
from yoto.sensor.spec import GELSIGHT_MINI
from yoto.sensor.sphere import press_height_map, refine_centre, sphere_gradients
from yoto.sensor.validation import fit_sphere

SPEC = GELSIGHT_MINI
BALL_RADIUS_M = 3.155e-3
BALL_RADIUS_PX = BALL_RADIUS_M / SPEC.pixel_size_m


def _synthetic_press(rng, cx, cy, a, background_level=90):
    """A press-like image: colour change ~ the Hertz press's slope, tinted by its direction, plus noise."""
    height = press_height_map(cx, cy, a, BALL_RADIUS_M)
    gx, gy = height_gradients(height, SPEC.pixel_size_m)
    background = np.full((SPEC.height_px, SPEC.width_px, 3), background_level, np.float64)
    change = np.stack([120 * gx, 120 * gy, -80 * gx - 60 * gy], axis=2)
    image = background + change + rng.normal(0, 2.0, background.shape)
    return np.clip(image, 0, 255).astype(np.uint8), background.astype(np.uint8)


@pytest.mark.parametrize("cx, cy, a", [(160.0, 120.0, 25.0), (90.3, 170.6, 30.0), (300.0, 60.0, 28.0)])
def test_circle_found_on_synthetic_press(rng, cx, cy, a):
    """The colour disc's rim is found around the press (centre within 2 px), also when cut by the border."""
    image, background = _synthetic_press(rng, cx, cy, a)
    circle = find_contact_circle(image, background)
    assert np.hypot(circle.centre_x_px - cx, circle.centre_y_px - cy) < 2.0
    # The rim of the coloured disc lies outside the contact edge (the gel bends back to flat beyond it).
    assert a < circle.radius_px < 1.6 * a
    assert circle.residual_px < 1.5


def test_ring_circle_peak_mode_recovers_radius(rng):
    """On a clean ring map (slope magnitude peaking at the contact edge), peak mode returns the edge.

    Central differences round the slope's kink at the edge, which moves the sampled peak about a pixel in.
    """
    cx, cy, a = 140.4, 101.7, 27.0
    height = press_height_map(cx, cy, a, BALL_RADIUS_M)
    gx, gy = height_gradients(height, SPEC.pixel_size_m)
    circle = ring_circle(np.hypot(gx, gy), CircleConfig(mode="peak"), initial=(cx + 3, cy - 2))
    assert np.hypot(circle.centre_x_px - cx, circle.centre_y_px - cy) < 0.5
    assert abs(circle.radius_px - a) < 1.5


def test_no_circle_in_a_blank_image(rng):
    background = np.full((SPEC.height_px, SPEC.width_px, 3), 90, np.uint8)
    image = np.clip(background + rng.normal(0, 2.0, background.shape), 0, 255).astype(np.uint8)
    with pytest.raises(NoCircleError, match="no contact"):
        find_contact_circle(image, background)


def test_sphere_gradients_match_the_analytic_cap():
    """Ground-truth gradients equal finite differences of the sphere inside the contact circle."""
    cx, cy, a = 150.3, 110.8, 26.0
    height = press_height_map(cx, cy, a, BALL_RADIUS_M)
    fd_x, fd_y = height_gradients(height, SPEC.pixel_size_m)
    gx, gy, r = sphere_gradients(cx, cy, BALL_RADIUS_PX, height.shape)
    inside = r < a - 2
    assert np.abs(gx[inside] - fd_x[inside]).max() < 5e-3
    assert np.abs(gy[inside] - fd_y[inside]).max() < 5e-3
    # The slope at the contact edge is a / sqrt(R^2 - a^2): exactly the sphere's.
    assert np.hypot(gx, gy)[r < a].max() == pytest.approx(a / np.sqrt(BALL_RADIUS_PX**2 - a**2), rel=0.02)


def test_press_height_map_is_hertz():
    """Edge at half the Hertz indentation, the sphere inside, continuous, flat far away, z <= 0."""
    a = 27.0
    height = press_height_map(159.5, 119.5, a, BALL_RADIUS_M)
    a_m = a * SPEC.pixel_size_m
    cap = BALL_RADIUS_M - np.sqrt(BALL_RADIUS_M**2 - a_m**2)
    # The centre pixel is half a pixel from the ball's axis in x and y.
    assert -height.min() == pytest.approx(cap + a_m**2 / BALL_RADIUS_M / 2, rel=2e-3)
    assert height.max() <= 0
    row = height[120]  # the centre row passes half a pixel from the centre
    edge = int(159.5 + a)
    slope = a / np.sqrt(BALL_RADIUS_PX**2 - a**2)  # the sphere's slope at the edge, continued outside
    assert abs(row[edge + 1] - row[edge]) == pytest.approx(slope * SPEC.pixel_size_m, rel=0.2)  # no step
    assert abs(height[0, 0]) < 0.15 * a_m**2 / BALL_RADIUS_M


def test_refine_centre_recovers_the_ball_centre(rng):
    cx, cy = 171.2, 93.6
    gx, gy, _ = sphere_gradients(cx, cy, BALL_RADIUS_PX, (SPEC.height_px, SPEC.width_px))
    noisy = gx + rng.normal(0, 0.05, gx.shape), gy + rng.normal(0, 0.05, gy.shape)
    x, y = refine_centre(*noisy, (cx + 4.0, cy - 3.0), 24.0, BALL_RADIUS_PX)
    assert np.hypot(x - cx, y - cy) < 0.3


@pytest.mark.parametrize("free", list(itertools.product([True, False], repeat=4)))
def test_poisson_recovers_an_analytic_height_map(free):
    """Integrating the gradients of a smooth bump recovers it, for every edge condition (<1% of depth)."""
    rows, cols = 90, 120
    y, x = np.mgrid[:rows, :cols].astype(np.float64)
    z = -5.0 * np.exp(-((x - 61) ** 2 + (y - 44) ** 2) / (2 * 11.0**2))
    gy, gx = np.gradient(z)
    got = poisson_integrate(gx, gy, 1.0, free).astype(np.float64)
    if all(free):  # free on all edges: defined up to a constant
        got += np.median(z[:4, :4] - got[:4, :4])
    assert np.abs(got - z).max() < 0.01 * 5.0


def test_poisson_scales_with_pixel_size_and_is_exact_for_its_own_stencil(rng):
    """The solve inverts the discrete operator exactly: gradients of its own output map back to them."""
    z = rng.normal(size=(40, 50))
    z = z - z.mean()
    gy, gx = np.gradient(z)
    f = divergence(gx.astype(np.float32), gy.astype(np.float32))
    got = poisson_integrate(gx, gy, 2.0) / 2.0
    # The 5-point Laplacian of the result (free edges: mirrored) equals the divergence of the input.
    padded = np.pad(got, 1, mode="edge")
    laplacian = padded[2:, 1:-1] + padded[:-2, 1:-1] + padded[1:-1, 2:] + padded[1:-1, :-2] - 4 * got
    assert np.abs(laplacian - (f - f.mean())).max() < 1e-4


def test_fit_sphere_recovers_radius_and_centre(rng):
    centre = np.array([1e-3, -2e-3, 2.5e-3])
    directions = rng.normal(size=(400, 3))
    directions[:, 2] = -np.abs(directions[:, 2]) - 1.0  # a lower cap
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    points = centre + BALL_RADIUS_M * directions + rng.normal(0, 2e-6, (400, 3))
    got_centre, got_radius = fit_sphere(points)
    assert got_radius == pytest.approx(BALL_RADIUS_M, rel=2e-3)
    assert np.linalg.norm(got_centre - centre) < 2e-5
