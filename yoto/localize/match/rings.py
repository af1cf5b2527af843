"""The coarse stage of the matched filter: height maps on rings, described independently of the sensor's roll.

Sample a height map on concentric rings around its centre, N angles per ring. Rolling the sensor about its
axis rotates each ring's height profile along the ring, which multiplies its angular Fourier coefficients by
phases: their magnitudes do not change (exactly for rolls by multiples of 2 pi / N, up to the sampling
otherwise). Removing the best plane leaves every ring's mean (minus one common
offset) and its harmonics m >= 2 untouched (a tilt is exactly the m = 1 harmonic). So a contact and an anchor
compare, for every roll at once, through

    D = sum_k r_k [ (a0_k - c0_k)^2 + 2 sum_{m=2..M} (|a_km| - |c_km|)^2 ]       (ring means centred)

which never exceeds the ring-sampled squared difference at the best roll and plane (|a e^{i m phi} - c| >=
| |a| - |c| |; the dropped m = 1 and m > M terms are non-negative): a lower bound on what the fine stage
computes, in a few matrix-vector products over all anchors. Only rings the contact covers (most of) enter.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from yoto.localize.match.contact import ContactImage


@dataclass(frozen=True)
class RingGrid:
    """Samples on rings of radius step, 2 step, ... up to `radius_m`, `angles` per ring."""

    step_m: float
    radius_m: float
    angles: int
    harmonics: int  # M: the highest angular harmonic described (2 <= M <= angles // 2)

    @cached_property
    def radii(self) -> np.ndarray:
        """(K,) ring radii."""
        return self.step_m * np.arange(1, int(np.floor(self.radius_m / self.step_m + 1e-9)) + 1)

    @cached_property
    def centres(self) -> np.ndarray:
        """(K * angles, 2) sample positions (x, y), ring by ring, counter-clockwise from +x."""
        theta = 2.0 * np.pi * np.arange(self.angles) / self.angles
        radii = self.radii[:, None]
        return np.stack([(radii * np.cos(theta)).ravel(), (radii * np.sin(theta)).ravel()], axis=1)

    def describe(self, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ring means (..., K) and harmonic magnitudes |m = 2..M| (..., K, M - 1) of samples (..., K * angles)."""
        rings = samples.reshape(samples.shape[:-1] + (len(self.radii), self.angles))
        spectrum = np.fft.rfft(rings, axis=-1) / self.angles
        return spectrum[..., 0].real, np.abs(spectrum[..., 2 : self.harmonics + 1])


@dataclass
class RingDescriptors:
    """Every anchor's ring description, ring by ring, laid out so that the coarse distance over the rings a
    contact covers is one matrix-vector product per ring."""

    grid: RingGrid
    terms: np.ndarray  # (K, A, 2 M) float32 per ring and anchor: mean, magnitudes m = 2..M, and their squares
    means: np.ndarray  # (K, A) float32 ring means (the common offset is removed per query)

    @classmethod
    def from_samples(cls, grid: RingGrid, heights: np.ndarray) -> RingDescriptors:
        """From (A, K * angles) anchor heights on the rings (absent surface given some height, see anchors.py)."""
        means, magnitudes = grid.describe(heights.astype(np.float64))
        values = np.concatenate([means[:, :, None], magnitudes], axis=2).transpose(1, 0, 2)  # (K, A, M)
        terms = np.concatenate([values, values * values], axis=2).astype(np.float32)
        return cls(grid, np.ascontiguousarray(terms), np.ascontiguousarray(means.T, dtype=np.float32))


@dataclass
class ContactRings:
    """The contact's ring description: which rings it covers, their means and harmonic magnitudes."""

    used: np.ndarray  # (K,) bool: rings the contact covers at least `min_coverage` of
    means: np.ndarray  # (K,) ring means (0 on unused rings)
    magnitudes: np.ndarray  # (K, M - 1) harmonic magnitudes (0 on unused rings)


def contact_rings(image: ContactImage, grid: RingGrid, min_coverage: float) -> ContactRings:
    """Sample the contact image on the rings; a ring counts when it covers `min_coverage` of its samples, the
    uncovered few filled by interpolation along the ring."""
    x, y = grid.centres.T
    heights, covered = image.sample(x, y, image.mask)
    heights = heights.reshape(-1, grid.angles)
    covered = covered.reshape(-1, grid.angles)
    used = covered.mean(axis=1) >= min_coverage
    positions = np.arange(grid.angles)
    for ring in np.flatnonzero(used & ~covered.all(axis=1)):
        seen = np.flatnonzero(covered[ring])
        heights[ring] = np.interp(positions, seen, heights[ring, seen], period=grid.angles)
    means, magnitudes = grid.describe(heights.ravel())
    return ContactRings(used, np.where(used, means, 0.0), np.where(used[:, None], magnitudes, 0.0))


def ring_distances(descriptors: RingDescriptors, contact: ContactRings) -> np.ndarray:
    """(A,) the roll- and plane-free lower bound D (module docstring) of every anchor against the contact.

    With ring weights w (r_k over the used rings, summing to 1) and the contact's centred means c0, D expands
    into per-ring products of anchor terms with contact terms, less the square of the anchors' weighted mean.
    """
    radii = descriptors.grid.radii
    weights = np.where(contact.used, radii, 0.0)
    weights = weights / weights.sum()
    centred = contact.means - weights @ contact.means
    distance = np.zeros(descriptors.means.shape[1], dtype=np.float32)
    offset = np.zeros_like(distance)
    constant = 0.0
    for ring in np.flatnonzero(contact.used):
        w = weights[ring]
        values = np.concatenate([[centred[ring]], contact.magnitudes[ring]])
        scale = np.full(len(values), 2.0 * w)
        scale[0] = w  # the mean counts once, each magnitude twice (m and -m)
        query = np.concatenate([-2.0 * scale * values, scale]).astype(np.float32)
        distance += descriptors.terms[ring] @ query
        offset += np.float32(w) * descriptors.means[ring]
        constant += float(scale @ values**2)
    return distance - offset * offset + np.float32(constant)
