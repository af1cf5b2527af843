"""Which bins of a frame `contact_samples` registers: chosen by the frame's own depths, which its pixel noise barely
moves (journal stop 23; choosing them by the predicted press instead is at tag `measured-s23-rimselect`)."""

import dataclasses

import numpy as np

from yoto.tracking.config import CorrectionConfig
from yoto.tracking.frame_registration import contact_samples

RADIUS_M, PRESS_M = 0.015, 0.001


def _whole_pad(error_m: float) -> np.ndarray:
    """The gel under a sphere (r 15 mm) pressed PRESS_M deep, every 0.1 mm over 12 x 10 mm (free gel read at z = 0,
    as a whole-pad cloud; sensor frame, pressed points below z = 0), plus a smooth reading error of amplitude
    `error_m` fixed on the pad (a 6 mm wave)."""
    x, y = (g.ravel() for g in np.meshgrid(np.arange(-0.006, 0.006, 1e-4), np.arange(-0.005, 0.005, 1e-4)))
    surface = RADIUS_M - PRESS_M - np.sqrt(np.maximum(RADIUS_M**2 - x**2 - y**2, 0.0))
    z = np.minimum(surface, 0.0) + error_m * np.sin(2.0 * np.pi * (x + 0.3 * y) / 0.006 + 0.7)
    return np.stack([x, y, z], axis=1)


def _chosen(points: np.ndarray, config: CorrectionConfig) -> set[tuple[int, int]]:
    """The bins (0.4 mm cells over the pad) whose means `contact_samples` keeps."""
    kept = contact_samples(points, config)
    return {tuple(cell) for cell in np.floor(kept[:, :2] / config.voxel_m).astype(int)}


def test_pixel_noise_moves_two_of_the_frame_s_341_chosen_bins_at_most_a_smooth_error_seven():
    """A whole-pad frame of the sphere pressed 1 mm, read with white pixel noise of 15 um (the simulator's, three
    draws) or with a smooth error of 20 um fixed on the pad: chosen by the frame's own depths (0.4 of the deepest
    bin's, each bin's depth averaged with its neighbours'), the noise moves at most 2 of the 341 bins at the patch's
    rim, the smooth error 7: the rim a frame chooses is not its pixel noise's."""
    config = dataclasses.replace(CorrectionConfig(), points_per_contact=10_000)
    clean = _whole_pad(0.0)
    chosen = _chosen(clean, config)
    assert len(chosen) == 341
    for seed in range(3):
        noise = np.random.default_rng(seed).normal(scale=1.5e-5, size=len(clean))
        assert len(chosen ^ _chosen(clean + noise[:, None] * [0.0, 0.0, 1.0], config)) <= 2
    assert len(chosen ^ _chosen(_whole_pad(2e-5), config)) == 7
