"""GelSight image -> surface gradients -> height map -> contact mask -> tactile point cloud (sensor frame).

Steps, for one 320x240 RGB frame:
1. checks and the touched region: the frame's colour change against the calibration's background is
   averaged over 8x8 blocks; a frame that differs from the background almost everywhere and is no contact
   over the whole pad (another sensor, changed lighting: `pad_wide_contact`) or is saturated raises
   InputError. Blocks whose mean colour changed are "touched";
   their bounding box plus a margin is the only region where gradients are computed. Elsewhere the gel is
   flat to within the sensor noise and its gradient is set to zero (the fitted model would only add its
   small bias there, which integrates into a spurious tilt).
2. gradients inside the box: colour change (int16, 3x3 binomial smoothing), then the calibration's lookup
   table and per-pixel gain maps (models.GradientModel).
3. height map by Poisson integration in the touched box: the Laplacian of z equals the divergence of the
   gradients, solved with discrete cosine/sine transforms using precomputed eigenvalues, float32; box edges
   inside the frame lie on flat gel (zero height), edges on the frame's border are free (a press cut by the
   frame's edge is not forced to zero there). Where an edge is free, untouched gel inside the box is brought back
   to zero by a harmonic correction (`anchor_untouched`), unless those blocks are a face pressed over the pad
   (`anchors_are_gel`): then the least-pressed part of the pad is the gel's level. Heights are then clamped to z <= 0.
4. contact masks: if at least `min_area_px` pixels changed colour by `colour_threshold` (or the frame is a faint
   contact: a tilted face's colour change of a few levels over many blocks that no lighting change explains,
   integrated over the whole frame), the core (pixels
   pressed at least half as deep as the deepest point: a ball's contact, for sphere fits) and the contact the
   gel felt (pixels deeper than the noise floor, connected to the core or in a region itself pressed well below
   the floor: what localization needs, the whole shape of a broad or tilted contact). Depth, not colour: the
   middle of a contact is flat, so its colour barely changes.
5. points: the contact's pixels' sensor-frame (x, y, z) in metres (SPEC: z <= 0 where the gel is pressed).

Bad input never yields a silent garbage cloud: a wrong size or dtype, a saturated frame or a frame that
does not look like the calibration's background raise InputError; a frame without contact gives an
explicit empty result (`contact` False, `reason`, (0, 3) points).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import scipy.fft
import scipy.linalg
from scipy import ndimage

from yoto.errors import InputError
from yoto.sensor.calibration import MaskConfig, SensorCalibration
from yoto.sensor.models import model_colour_change
from yoto.sensor.presses import check_image
from yoto.sensor.spec import GelSightSpec

# A frame shows the calibration's background where it is untouched when its median block colour change against
# the background is at most MAX_BACKGROUND_CHANGE (0-255 levels: a small contact, a little lighting drift) or its
# least-changed blocks (BACKGROUND_PERCENTILE) changed by at most MAX_UNTOUCHED_CHANGE (a broad contact covering
# most of the pad; untouched gel stays within about 1 level). Otherwise the frame is from another sensor, or the
# lighting or a camera setting changed: the calibration does not apply.
MAX_BACKGROUND_CHANGE = 10.0
BACKGROUND_PERCENTILE = 10.0
MAX_UNTOUCHED_CHANGE = 3.0
# A contact pressing nearly the whole pad (a fruit's broad face) changes every block too. Such a frame is told from
# another sensor or changed lighting by what its colour change means (`pad_wide_contact`): a lighting or exposure
# change is explained per channel by a gain and an offset on the background (share of the block changes' energy
# at least LIGHTING_EXPLAINED: 0.998-1.0 for gains of 0.9-1.15 or an offset, 0.09-0.73 for pad-wide contacts),
# and a frame from another sensor (or with its channels swapped) maps to gradients that no surface has: not
# integrable (RMS gradient residual of the Poisson fit over the frame above MAX_NONINTEGRABLE of the gradients'
# RMS: 0.27-0.48 measured, pad-wide contacts 0.09-0.20) or steeper than a contact's (RMS slope over the frame
# above MAX_FRAME_SLOPE: 0.28-1.1 measured, contacts 0.07-0.13).
# The misfit is relative, so on a gentle pad-wide contact (RMS slope 0.05-0.07) a small non-integrable part (the
# gradient model's noise, a pressed gel's colour change that is no slope) reaches it: a frame is refused as not a
# surface's only when its residual is also large in slope units, above MIN_NONINTEGRABLE_RMS (the 44 real presses with
# their channels permuted: 0.20 and more; pad-wide contacts through three renderers at most 0.037; the cracker box's
# faces through the table renderer 0.018-0.019 at a relative misfit of 0.27-0.35, refused before: stop 16).
LIGHTING_EXPLAINED = 0.95
MAX_NONINTEGRABLE = 0.25
MIN_NONINTEGRABLE_RMS = 0.08
MAX_FRAME_SLOPE = 0.22
# A frame with more than this fraction of saturated pixels (any channel at 255) is overexposed. Fewer are steep
# slopes facing a bright LED: their colour change is clipped, so their slope is underestimated, nothing worse.
MAX_SATURATED_FRACTION = 0.05
# Touched-region detection: block size (pixels), the block-mean colour change (levels, largest channel)
# that marks a block as touched (the noise of an 8x8 mean is about 0.3 levels), and the margin (pixels)
# added around the touched blocks.
BLOCK_PX = 8
TOUCHED_LEVEL = 3.0
BOX_MARGIN_PX = 8
# Untouched gel inside a touched box that reaches the frame's border is brought back to z = 0 (`anchor_untouched`)
# where it lies at most this fraction of the contact's depth below the gel's level (`gel_level_blocks`): a broad
# contact's flat middle barely changes colour too, but lies deep; the drift anchoring removes is 0.02-0.1 mm.
ANCHOR_RELATIVE_DEPTH = 0.15
# Untouched gel shows the calibration's background within the noise of an 8x8 block mean (about 0.3 levels): blocks
# taken for the gel's level whose median colour change exceeds MAX_GEL_BLOCK_CHANGE levels are a face pressed over the
# pad with a tilt too gentle to change them by TOUCHED_LEVEL (`anchors_are_gel`). On the cracker box's contacts through
# the table renderer (seed 11, zero-slope change off) the gel's blocks changed by a median 0.30-0.41 levels, those of
# 12 of the 13 faces the anchoring flattened by 1.1-2.2 (true gel beside lemon and figurine contacts through
# `shading:3`: 0.28).
MAX_GEL_BLOCK_CHANGE = 0.75
# ... checked only where the touched box covers at least this share of the frame (a face pressed over the pad).
PAD_WIDE_BOX_SHARE = 0.75
# Refits of the plane that gives the untouched gel's level under drift (`gel_level_blocks`).
GEL_LEVEL_ITERATIONS = 3
# A faint contact: a face pressed tilted across the pad changes colour by a few levels over thousands of pixels, no
# pixel by the mask's colour threshold. Such a frame shows a contact when at least FAINT_MIN_BLOCKS blocks are touched
# (each mean changed by more than TOUCHED_LEVEL, ten times an 8x8 mean's noise) and a lighting or exposure change does
# not explain them (`lighting_explained` below LIGHTING_EXPLAINED: tilted faces 0.34-0.77, lighting 0.99). A flat
# press changes no colour at all and stays "no contact".
FAINT_MIN_BLOCKS = 8
# The depth scale of a reconstructed contact (true heights over reconstructed ones) is known only to a few percent:
# on ball presses the calibration did not see, the sphere fitted to the reconstruction has its radius 3.3% off
# (median |error|, `yoto sensor validate`, docs/sensor.md), and an object's contact can be further off (broad faces
# read shallow, slopes beyond the calibrated range read short). DEPTH_SCALE_SIGMA is the 1-sigma of its
# log that a reconstructed cloud carries to the pose stage (`Reconstruction.depth_scale_sigma`), which estimates
# the scale per contact under that prior. Wider priors (0.1, 0.2) let wrong poses fit as well (docs/journal/sensor.md).
DEPTH_SCALE_SIGMA = 0.05


@dataclass
class Reconstruction:
    """One frame's reconstruction."""

    height_map_m: np.ndarray  # (rows, cols) float32, gel surface z (metres), <= 0 where pressed
    mask: np.ndarray  # (rows, cols) bool, the contact the gel felt (what localization uses)
    core_mask: np.ndarray  # (rows, cols) bool, the pixels at least half as deep as the deepest (sphere fits)
    points_sensor: np.ndarray  # (N, 3) float64, the masked pixels in the sensor frame, metres; (0, 3) if none
    contact: bool  # False: no contact found (points empty); `reason` says why
    reason: str = ""  # why there is no contact, or ""
    box: tuple[int, int, int, int] | None = None  # (row0, row1, col0, col1) where gradients were computed
    gradients: tuple[np.ndarray, np.ndarray] | None = None  # (gx, gy) maps when asked for, else None

    @property
    def max_depth_m(self) -> float:
        return float(-self.points_sensor[:, 2].min()) if len(self.points_sensor) else 0.0

    @property
    def depth_scale_sigma(self) -> float:
        """1-sigma of the log of the factor the cloud's heights may be off by (`DEPTH_SCALE_SIGMA`)."""
        return DEPTH_SCALE_SIGMA if self.contact else 0.0

    @property
    def touches_border(self) -> bool:
        """The contact reaches the frame's edge: part of it is unseen, its depth is less reliable."""
        m = self.mask
        return bool(m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any())


# ---------------------------------------------------------------------------------------------------------
# Poisson integration


# One axis of the separable Poisson solve. Boundary condition at each end of the axis: "free" (zero normal
# slope, Neumann) or "fixed" (zero height half a pixel outside, Dirichlet). Each pair has its real
# trigonometric transform (orthonormal; scipy.fft type, DCT or DST) and Laplacian eigenvalue offset:
# lambda_k = 2 cos(pi (k + offset) / n) - 2.
_AXIS_TRANSFORMS = {
    (True, True): ("dct", 2, 0.0),
    (False, False): ("dst", 2, 1.0),
    (True, False): ("dct", 4, 0.5),
    (False, True): ("dst", 4, 0.5),
}


@lru_cache(maxsize=64)
def _eigenvalues(rows: int, cols: int, free: tuple[bool, bool, bool, bool]) -> np.ndarray:
    """Eigenvalues of the 5-point Laplacian for the edge conditions (top, bottom, left, right), float32.

    With all four edges free, the (0, 0) entry (the undetermined constant) is set to 1; its coefficient is
    zeroed by the solver.
    """
    _, _, row_offset = _AXIS_TRANSFORMS[free[0], free[1]]
    _, _, col_offset = _AXIS_TRANSFORMS[free[2], free[3]]
    eig_rows = 2 * np.cos(np.pi * (np.arange(rows) + row_offset) / rows) - 2
    eig_cols = 2 * np.cos(np.pi * (np.arange(cols) + col_offset) / cols) - 2
    eig = eig_rows[:, None] + eig_cols[None, :]
    if all(free):
        eig[0, 0] = 1.0
    return eig.astype(np.float32)


def divergence(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """d(gx)/dx + d(gy)/dy (pixel units), from gradients averaged onto the half-pixel edges.

    f[n] = (g[n+1] - g[n-1]) / 2 inside; at the first and last pixel the edge half a pixel outside has zero
    normal gradient (f[0] = (g[0] + g[1]) / 2), which is exact for a free edge and, for a fixed edge,
    holds where the gel is flat (the touched box has a flat margin).
    """
    f = np.empty_like(gx)
    f[:, 1:-1] = gx[:, 2:]
    f[:, 1:-1] -= gx[:, :-2]
    f[:, 0] = gx[:, 0] + gx[:, 1]
    f[:, -1] = -gx[:, -1] - gx[:, -2]
    f[1:-1, :] += gy[2:, :]
    f[1:-1, :] -= gy[:-2, :]
    f[0, :] += gy[0, :] + gy[1, :]
    f[-1, :] -= gy[-1, :] + gy[-2, :]
    f *= 0.5
    return f


def poisson_integrate(
    gx: np.ndarray,
    gy: np.ndarray,
    spacing: float = 1.0,
    free: tuple[bool, bool, bool, bool] = (True, True, True, True),
) -> np.ndarray:
    """Height map whose gradients best match (gx, gy), by a fast Poisson solve.

    gx = dz/dx along columns, gy = dz/dy along rows (dimensionless); `spacing` is the pixel size, so the
    result has the unit of `spacing`. `free` gives, for the (top, bottom, left, right) edges, whether the
    surface is free there (zero normal slope) or fixed (zero height half a pixel outside). With all edges
    free the result has zero mean (the constant is the caller's to fix). Solves the 5-point Poisson
    equation exactly with separable DCT/DST transforms (scipy.fft) and precomputed eigenvalues, float32,
    O(n log n).
    """
    f = divergence(np.asarray(gx, dtype=np.float32), np.asarray(gy, dtype=np.float32))
    free = (bool(free[0]), bool(free[1]), bool(free[2]), bool(free[3]))  # hashable plain bools: cache keys
    row_kind, row_type, _ = _AXIS_TRANSFORMS[free[0], free[1]]
    col_kind, col_type, _ = _AXIS_TRANSFORMS[free[2], free[3]]
    forward = {"dct": scipy.fft.dct, "dst": scipy.fft.dst}
    inverse = {"dct": scipy.fft.idct, "dst": scipy.fft.idst}
    coefficients = forward[col_kind](f, type=col_type, axis=1, norm="ortho", overwrite_x=True)
    coefficients = forward[row_kind](coefficients, type=row_type, axis=0, norm="ortho", overwrite_x=True)
    coefficients /= _eigenvalues(*f.shape, free)
    if all(free):
        coefficients[0, 0] = 0.0
    z = inverse[row_kind](coefficients, type=row_type, axis=0, norm="ortho", overwrite_x=True)
    z = inverse[col_kind](z, type=col_type, axis=1, norm="ortho", overwrite_x=True)
    if spacing != 1.0:
        z *= np.float32(spacing)
    return z


# ---------------------------------------------------------------------------------------------------------
# Checks and the touched region


def block_change(image: np.ndarray, background_i16: np.ndarray, block: int = BLOCK_PX) -> np.ndarray:
    """(rows // block, cols // block) largest-channel |mean colour change| of each block, float32 levels."""
    diff = np.subtract(image, background_i16, dtype=np.int16)
    rows = (diff.shape[0] // block) * block
    cols = (diff.shape[1] // block) * block
    strips = diff[0:rows:block, :cols].astype(np.int32)  # row sums by strided adds: fast, contiguous rows
    for k in range(1, block):
        strips += diff[k:rows:block, :cols]
    sums = np.add.reduceat(strips, np.arange(0, cols, block), axis=1)
    np.abs(sums, out=sums)
    level = np.maximum(np.maximum(sums[..., 0], sums[..., 1]), sums[..., 2]).astype(np.float32)
    level *= np.float32(1.0 / (block * block))
    return level


def check_frame(image: np.ndarray, calibration: SensorCalibration, source: str | Path | None = None) -> np.ndarray:
    """Raise InputError for a frame the calibration cannot reconstruct; return its block colour change.

    Checks: size and dtype, saturation, and that the frame shows the calibration's background where it is
    not touched: the median block changed by at most MAX_BACKGROUND_CHANGE levels, or (a broad contact can
    cover 80% of the pad) the least-changed tenth by at most MAX_UNTOUCHED_CHANGE. A frame from another sensor
    or under other lighting changes nearly all blocks (a real frame with its channels permuted: median 25
    levels, least-changed tenth 5; the frame itself: 1 and 0.5-0.8).
    """
    check_image(image, calibration.spec, source, "frame")
    if image.max() >= 255:
        saturated = float((image == 255).any(axis=2).mean())
        if saturated > MAX_SATURATED_FRACTION:
            raise InputError(
                f"frame is saturated: {saturated:.1%} of the pixels have a channel at 255 (limit "
                f"{MAX_SATURATED_FRACTION:.1%}); lower the camera exposure or the LED brightness",
                source,
            )
    blocks = block_change(image, calibration.background_i16)
    least, median = (float(v) for v in np.percentile(blocks, [BACKGROUND_PERCENTILE, 50.0]))
    if median > MAX_BACKGROUND_CHANGE and least > MAX_UNTOUCHED_CHANGE:
        why = pad_wide_contact(image, calibration)
        if why:
            raise InputError(
                f"frame differs from the calibration's background almost everywhere (median change {median:.0f} "
                f"levels, limit {MAX_BACKGROUND_CHANGE:.0f}; even the least-changed tenth of the frame changed by "
                f"{least:.1f}, limit {MAX_UNTOUCHED_CHANGE:.0f}) and is no contact ({why}): another sensor, or "
                "the lighting or a camera setting changed; recalibrate, or give a background taken with this "
                "sensor now",
                source,
            )
    return blocks


def pad_wide_contact(image: np.ndarray, calibration: SensorCalibration) -> str:
    """Why a frame that changed colour almost everywhere is not a contact over the whole pad, or "" if it is one.

    See LIGHTING_EXPLAINED, MAX_NONINTEGRABLE and MAX_FRAME_SLOPE. Runs only on such frames (about 6 ms CPU).
    """
    explained = lighting_explained(image, calibration)
    if explained >= LIGHTING_EXPLAINED:
        why = f"a gain and offset on the background explain {explained:.1%} of its colour change"
        return why + f", limit {LIGHTING_EXPLAINED:.0%}: the lighting or exposure changed"
    gx, gy, _ = box_gradients(image, calibration, (0, image.shape[0], 0, image.shape[1]))
    z = poisson_integrate(gx, gy)
    zy, zx = np.gradient(z)
    slope = float(np.sqrt(np.mean(gx * gx + gy * gy)))
    residual = float(np.sqrt(np.mean((zx - gx) ** 2 + (zy - gy) ** 2)))
    misfit = residual / max(slope, 1e-12)
    if misfit > MAX_NONINTEGRABLE and residual > MIN_NONINTEGRABLE_RMS:
        return (
            f"gradients not a surface's: Poisson residual {misfit:.2f} of their RMS (limit {MAX_NONINTEGRABLE}), "
            f"{residual:.3f} in slope (limit {MIN_NONINTEGRABLE_RMS})"
        )
    if slope > MAX_FRAME_SLOPE:
        return f"RMS slope {slope:.2f} over the frame, steeper than a contact's (limit {MAX_FRAME_SLOPE})"
    return ""


def lighting_explained(image: np.ndarray, calibration: SensorCalibration) -> float:
    """Share of the frame's block colour change (energy) a per-channel gain and offset on the background explain.

    A lighting or exposure change is such a gain and offset (0.99-1.0 measured); a contact's shading is not.
    """
    background = calibration.background.astype(np.float64)
    rows = (image.shape[0] // BLOCK_PX) * BLOCK_PX
    cols = (image.shape[1] // BLOCK_PX) * BLOCK_PX

    def block_means(values: np.ndarray) -> np.ndarray:
        return values[:rows, :cols].reshape(rows // BLOCK_PX, BLOCK_PX, cols // BLOCK_PX, BLOCK_PX, 3).mean((1, 3))

    change = block_means(image - background).reshape(-1, 3)
    level = block_means(background).reshape(-1, 3)
    residual = 0.0
    for channel in range(3):
        design = np.stack([np.ones(len(level)), level[:, channel]], axis=1)
        coefficients, *_ = np.linalg.lstsq(design, change[:, channel], rcond=None)
        residual += float(np.sum((change[:, channel] - design @ coefficients) ** 2))
    return 1.0 - residual / max(float(np.sum(change**2)), 1e-12)


def touched_box(
    blocks: np.ndarray, shape: tuple[int, int], block: int = BLOCK_PX, margin: int = BOX_MARGIN_PX
) -> tuple[int, int, int, int] | None:
    """(row0, row1, col0, col1) pixel box around the touched blocks, or None when nothing is touched."""
    touched = blocks > TOUCHED_LEVEL
    rows = np.nonzero(touched.any(axis=1))[0]
    if len(rows) == 0:
        return None
    cols = np.nonzero(touched.any(axis=0))[0]
    row0 = max(0, rows[0] * block - margin)
    row1 = min(shape[0], (rows[-1] + 1) * block + margin)
    col0 = max(0, cols[0] * block - margin)
    col1 = min(shape[1], (cols[-1] + 1) * block + margin)
    if shape[0] - row1 < block:  # blocks do not reach a ragged last strip; extend into it
        row1 = shape[0]
    if shape[1] - col1 < block:
        col1 = shape[1]
    return int(row0), int(row1), int(col0), int(col1)


# ---------------------------------------------------------------------------------------------------------
# Reconstruction


def reconstruct(
    image: np.ndarray,
    calibration: SensorCalibration,
    *,
    source: str | Path | None = None,
    keep_gradients: bool = False,
) -> Reconstruction:
    """Reconstruct one (rows, cols, 3) uint8 RGB frame into a height map, contact mask and point cloud.

    `source` names the frame in error messages. Raises InputError for frames the calibration cannot
    reconstruct (module docstring); a frame without contact returns `contact=False` and no points.
    """
    spec = calibration.spec
    blocks = check_frame(image, calibration, source)
    shape = (spec.height_px, spec.width_px)
    box = touched_box(blocks, shape)
    if box is None:
        empty = Reconstruction(
            np.zeros(shape, np.float32),
            np.zeros(shape, bool),
            np.zeros(shape, bool),
            np.zeros((0, 3)),
            False,
            f"no contact: no 8x8 block changed colour by more than {TOUCHED_LEVEL:g} levels",
        )
        if keep_gradients:
            empty.gradients = (np.zeros(shape, np.float32), np.zeros(shape, np.float32))
        return empty
    gx, gy, changed = box_gradients(image, calibration, box)
    faint = (
        changed < calibration.mask.min_area_px
        and int(np.count_nonzero(blocks > TOUCHED_LEVEL)) >= FAINT_MIN_BLOCKS
        and lighting_explained(image, calibration) < LIGHTING_EXPLAINED
    )
    if faint:
        # A faint face tilted across the pad changes blocks by less than TOUCHED_LEVEL where it is pressed too: the
        # whole frame is integrated, its level set by the least-pressed block (every block counts as touched).
        box = (0, shape[0], 0, shape[1])
        gx, gy, changed = box_gradients(image, calibration, box)
        height = integrate_box(gx, gy, box, np.full_like(blocks, np.inf), spec.pixel_size_m)
    else:
        height = integrate_box(gx, gy, box, blocks, spec.pixel_size_m)
    mask, core, reason = contact_masks(changed, height, calibration.mask, box, faint)
    if mask is None or core is None:
        points = np.zeros((0, 3))
        mask = core = np.zeros(shape, dtype=bool)
    else:
        x, y = _pixel_xy(spec)
        pixels = np.flatnonzero(mask)  # row-major, as boolean indexing orders them: found once, gathered thrice
        points = np.empty((len(pixels), 3))
        points[:, 0] = x.ravel().take(pixels)
        points[:, 1] = y.ravel().take(pixels)
        points[:, 2] = height.ravel().take(pixels)
    return Reconstruction(
        height, mask, core, points, bool(mask.any()), reason, box, (gx, gy) if keep_gradients else None
    )


def box_gradients(
    image: np.ndarray, calibration: SensorCalibration, box: tuple[int, int, int, int]
) -> tuple[np.ndarray, np.ndarray, int]:
    """Full-frame gradient maps, zero outside `box`, and the number of pixels whose colour changed by at
    least the mask's colour threshold."""
    row0, row1, col0, col1 = box
    rows, cols = image.shape[:2]
    # One extra pixel around the box so the 3x3 smoothing inside it matches a full-frame smoothing.
    r0, r1, c0, c1 = max(0, row0 - 1), min(rows, row1 + 1), max(0, col0 - 1), min(cols, col1 + 1)
    change = model_colour_change(image[r0:r1, c0:c1], calibration.background_i16[r0:r1, c0:c1], calibration.smooth)
    change = change[row0 - r0 : row1 - r0, col0 - c0 : col1 - c0]
    box_gx, box_gy = calibration.gradient_model.predict(change, origin=(row0, col0))
    gx = np.zeros((rows, cols), np.float32)
    gy = np.zeros((rows, cols), np.float32)
    gx[row0:row1, col0:col1] = box_gx
    gy[row0:row1, col0:col1] = box_gy
    threshold = np.float32(calibration.mask.colour_threshold**2)
    changed = int(np.count_nonzero(colour_distance2(change) >= threshold))
    return gx, gy, changed


def integrate_box(
    gx: np.ndarray, gy: np.ndarray, box: tuple[int, int, int, int], blocks: np.ndarray, pixel_size_m: float
) -> np.ndarray:
    """Full-frame height map, z <= 0: the Poisson solution inside the touched box, zero outside.

    The box's edges inside the frame lie on flat gel: fixed at zero height. Edges on the frame's border
    are free (a contact cut by the border is not forced to zero there). Where an edge is free, untouched gel
    inside the box is no longer held at zero and drifts with the gradients' errors integrated across the contact
    (0.1 mm over a mug's contact crossing the pad); `anchor_untouched` pulls it back.
    """
    row0, row1, col0, col1 = box
    rows, cols = gx.shape
    free = (row0 == 0, row1 == rows, col0 == 0, col1 == cols)
    inside = (slice(row0, row1), slice(col0, col1))
    height = np.zeros((rows, cols), np.float32)
    height[inside] = poisson_integrate(gx[inside], gy[inside], pixel_size_m, free)
    if any(free):
        anchor_untouched(height, blocks, box)
    np.minimum(height, 0.0, out=height)
    return height


def untouched_blocks(blocks: np.ndarray) -> np.ndarray:
    """Blocks that are neither touched nor next to a touched block (8-neighbourhood): flat gel, z = 0."""
    touched = blocks > TOUCHED_LEVEL
    return ~ndimage.binary_dilation(touched, structure=np.ones((3, 3), bool))


def anchor_untouched(height: np.ndarray, blocks: np.ndarray, box: tuple[int, int, int, int]) -> None:
    """Bring untouched gel inside the box back to z = 0, in place, by subtracting a harmonic correction.

    A Poisson solve with other edge conditions differs from this one by a harmonic function, so the drift is
    removed as one: on the block grid, the correction equals each untouched block's mean height (and zero
    outside the box), is harmonic (5-point Laplace) over the touched blocks and their neighbours, with free
    (zero-slope) frame borders; it is interpolated bilinearly to the pixels. With no untouched block in the box
    and the box covering the frame (a contact over the whole pad) the least-pressed block (95th percentile of the
    block means) is taken as the gel's level; with none and edges inside the frame, those hold the level. So is it
    where the box covers most of the frame and the untouched blocks cannot be gel (`anchors_are_gel`): a face pressed
    over the pad, whose gentle tilt changes their colour faintly, or its plateau.
    """
    row0, row1, col0, col1 = box
    grid_rows, grid_cols = blocks.shape
    centre_rows = np.arange(grid_rows) * BLOCK_PX + (BLOCK_PX - 1) / 2
    centre_cols = np.arange(grid_cols) * BLOCK_PX + (BLOCK_PX - 1) / 2
    box_rows = np.flatnonzero((centre_rows >= row0) & (centre_rows < row1))
    box_cols = np.flatnonzero((centre_cols >= col0) & (centre_cols < col1))
    if len(box_rows) == 0 or len(box_cols) == 0:
        return
    in_box = np.zeros((grid_rows, grid_cols), bool)
    block_rows = slice(box_rows[0], box_rows[-1] + 1)
    block_cols = slice(box_cols[0], box_cols[-1] + 1)
    in_box[block_rows, block_cols] = True
    # Block means inside the box only (the rest is never read): the same reduction, the same float32 sums.
    means = np.zeros((grid_rows, grid_cols), np.float32)
    pixels = height[
        block_rows.start * BLOCK_PX : block_rows.stop * BLOCK_PX,
        block_cols.start * BLOCK_PX : block_cols.stop * BLOCK_PX,
    ]
    means[block_rows, block_cols] = pixels.reshape(len(box_rows), BLOCK_PX, len(box_cols), BLOCK_PX).mean(axis=(1, 3))
    untouched = untouched_blocks(blocks) & in_box
    known = gel_level_blocks(means, untouched, float(height.min())) | ~in_box
    if not (known & in_box).any():
        if in_box.all():
            height -= np.float32(np.percentile(means, 95.0))
        return
    values = np.where(in_box, means, 0.0).astype(np.float64)
    correction = np.where(known, values, 0.0)
    unknown = np.flatnonzero(~known)
    if len(unknown):
        correction.flat[unknown] = _harmonic_fill(known, values)
    if in_box.mean() >= PAD_WIDE_BOX_SHARE and not anchors_are_gel(blocks, means, correction, known & in_box, in_box):
        # The untouched blocks are a face pressed over the pad (tilted too gently to change colour, or its flat
        # plateau), not the gel: anchoring them at zero would flatten the face or lift the rest above the gel.
        # The least-pressed part of the pad is taken as the gel's level instead (its depth is then a lower bound).
        height[row0:row1, col0:col1] -= np.float32(np.percentile(means[in_box], 95.0))
        return
    # Bilinear interpolation from block centres to pixels (clamped at the frame's edges), inside the box only.
    pixel_rows = np.interp(np.arange(row0, row1), centre_rows, np.arange(grid_rows))
    pixel_cols = np.interp(np.arange(col0, col1), centre_cols, np.arange(grid_cols))
    r0 = np.minimum(np.floor(pixel_rows).astype(int), grid_rows - 2)
    c0 = np.minimum(np.floor(pixel_cols).astype(int), grid_cols - 2)
    wr = (pixel_rows - r0)[:, None]
    wc = (pixel_cols - c0)[None, :]
    along_cols = correction[:, c0] * (1 - wc) + correction[:, c0 + 1] * wc  # separable: block rows first
    height[row0:row1, col0:col1] -= (along_cols[r0] * (1 - wr) + along_cols[r0 + 1] * wr).astype(np.float32)


def anchors_are_gel(
    blocks: np.ndarray, means: np.ndarray, correction: np.ndarray, anchors: np.ndarray, in_box: np.ndarray
) -> bool:
    """Whether the blocks `anchor_untouched` holds at z = 0 can be untouched gel (block grids; heights in metres).

    They are not when (1) their median colour change exceeds MAX_GEL_BLOCK_CHANGE: untouched gel shows the background
    within the noise, a face pressed over the pad with a gentle tilt changes them faintly (by less than
    TOUCHED_LEVEL); or (2) once anchored, the least-pressed part of the box (95th percentile of its block means) lies
    above them by more than ANCHOR_RELATIVE_DEPTH of the contact's depth: the gel is pressed only downwards, so the
    anchors are the flat plateau of a face pressed over the whole pad.
    """
    if float(np.median(blocks[anchors])) > MAX_GEL_BLOCK_CHANGE:
        return False
    anchored = (means - correction)[in_box]
    top = float(np.percentile(anchored, 95.0))
    return top <= ANCHOR_RELATIVE_DEPTH * (top - float(anchored.min()))


def gel_level_blocks(means: np.ndarray, untouched: np.ndarray, deepest_z: float) -> np.ndarray:
    """The untouched blocks that lie at the gel's level, not on a pressed plateau: (grid_rows, grid_cols) bool.

    The flat middle of a broad contact changes no colour either, but lies deep. The gel's level is the top of the
    untouched blocks (the gel is pressed only downwards), tilted by the integration's drift: a plane is fitted to
    the blocks within ANCHOR_RELATIVE_DEPTH of the contact's depth below it, starting from the highest block, and
    refitted on those it then selects. Measured from the zero-mean solve's zero instead (every edge free), a broad
    contact's plateau passed for untouched gel and was pulled up to z = 0: the face read bent and shallow.
    """
    rows, cols = np.nonzero(untouched)
    if len(rows) == 0:
        return untouched
    heights = means[rows, cols]
    tolerance = ANCHOR_RELATIVE_DEPTH * (float(heights.max()) - deepest_z)
    design = np.column_stack([np.ones(len(rows)), rows, cols]).astype(np.float64)
    at_level = heights >= heights.max() - tolerance
    for _ in range(GEL_LEVEL_ITERATIONS):
        fitted = design[at_level]  # normal equations, least-norm where the blocks lie on a line
        level = design @ np.linalg.lstsq(fitted.T @ fitted, fitted.T @ heights[at_level], rcond=None)[0]
        refitted = heights >= level - tolerance
        if np.array_equal(refitted, at_level):
            break
        at_level = refitted
    known = np.zeros_like(untouched)
    known[rows, cols] = at_level
    return known


def _harmonic_fill(known: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Values at the unknown cells of a grid (row-major order) that make them harmonic (5-point Laplace), given the
    known cells.

    Neighbours beyond the grid's edge are left out (zero normal slope there). A small diagonal term keeps a region
    that no known cell reaches at zero instead of undetermined. The system is symmetric positive definite and banded
    (unknowns numbered along the grid's shorter extent of them): one banded Cholesky solve (LAPACK pbsv).
    """
    grid_rows, grid_cols = known.shape
    unknown = ~known
    rows_u, cols_u = np.nonzero(unknown)
    n = len(rows_u)
    # Number the unknowns along the axis they span less of: the band is at most that span wide.
    transposed = int(np.ptp(rows_u)) < int(np.ptp(cols_u))
    if transposed:
        unknown, values = unknown.T, values.T
        grid_rows, grid_cols = grid_cols, grid_rows
        order_rows, order_cols = np.nonzero(unknown)
    else:
        order_rows, order_cols = rows_u, cols_u
    index = np.full(unknown.shape, -1, dtype=np.int64)
    index[order_rows, order_cols] = np.arange(n)
    diagonal = np.full(n, 1e-6)
    rhs = np.zeros(n)
    upper: list[tuple[np.ndarray, np.ndarray]] = []  # (row index i, offset j - i > 0) of the -1 entries
    for d_row, d_col in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        r, c = order_rows + d_row, order_cols + d_col
        on_grid = (r >= 0) & (r < grid_rows) & (c >= 0) & (c < grid_cols)
        me = np.flatnonzero(on_grid)
        r, c = r[on_grid], c[on_grid]
        diagonal[me] += 1.0
        neighbour = index[r, c]
        unknown_neighbour = neighbour >= 0
        rhs_cells = me[~unknown_neighbour]
        rhs[rhs_cells] += values[r[~unknown_neighbour], c[~unknown_neighbour]]  # one neighbour per cell and side
        if d_row > 0 or d_col > 0:  # each symmetric pair once: the neighbour after this cell
            upper.append((me[unknown_neighbour], neighbour[unknown_neighbour] - me[unknown_neighbour]))
    width = max([int(offset.max()) for _, offset in upper if len(offset)], default=0)
    band = np.zeros((width + 1, n))  # LAPACK upper band storage: band[width + i - j, j] = A[i, j]
    band[width] = diagonal
    for i, offset in upper:
        band[width - offset, i + offset] = -1.0
    solution = scipy.linalg.solveh_banded(band, rhs, check_finite=False)
    if not transposed:
        return solution
    filled = np.zeros(unknown.shape)  # back to the caller's row-major order of the unknowns
    filled[order_rows, order_cols] = solution
    return filled.T[rows_u, cols_u]


def colour_distance2(change: np.ndarray) -> np.ndarray:
    """Squared RGB distance of each pixel's colour change, (rows, cols) float32."""
    c = change.astype(np.float32)
    distance2 = c[..., 0] * c[..., 0]
    distance2 += c[..., 1] * c[..., 1]
    distance2 += c[..., 2] * c[..., 2]
    return distance2


def contact_masks(
    changed_px: int, height_m: np.ndarray, config: MaskConfig, box: tuple[int, int, int, int], faint: bool = False
) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    """The contact the gel felt and its core, or None, None and the reason when the frame shows no contact.

    A frame shows contact when at least `min_area_px` pixels changed colour by `colour_threshold` levels, or when
    it is `faint`: a broad, faint colour change that is no lighting change (FAINT_MIN_BLOCKS, `reconstruct`).
    The core is the pixels pressed at least `relative_depth` as deep as the deepest point: a ball's contact
    edge lies at half its indentation (Hertz), and it measured best for sphere fits on the real presses
    (docs/sensor.md). The contact (for localization) is every pixel pressed deeper than the reconstruction's
    noise floor (`min_depth_m`, and `felt_relative_depth` of the deepest) in a connected region that holds
    core pixels, or that reaches `separate_floor_multiple` times that floor itself and has `min_area_px` pixels (an
    object's second feature pressed apart from the first): a broad or tilted contact keeps its whole shape, the
    core alone is a small featureless patch.
    Heights outside `box` are zero, so the regions are found inside it.
    """
    if changed_px < config.min_area_px and not faint:
        reason = (
            f"no contact: {changed_px} pixels changed colour by {config.colour_threshold:g} levels or more, "
            f"fewer than {config.min_area_px}, and no broad faint change that is not a lighting change"
        )
        return None, None, reason
    row0, row1, col0, col1 = box
    window = height_m[row0:row1, col0:col1]
    deepest = float(-window.min())
    floor = max(config.min_depth_m, config.felt_relative_depth * deepest)
    felt = window <= -np.float32(floor)
    count = int(np.count_nonzero(felt))
    if count < config.min_area_px:
        reason = (
            f"no contact: {count} pixels are pressed {floor * 1e3:.3f} mm deep or more (deepest "
            f"{deepest * 1e3:.3f} mm), fewer than {config.min_area_px}"
        )
        return None, None, reason
    core = window <= -np.float32(max(floor, config.relative_depth * deepest))
    labels, count = ndimage.label(felt)
    kept = np.zeros(count + 1, dtype=bool)
    kept[labels[core]] = True
    if count > 1:  # a region apart from the core's that is pressed clearly deeper than the noise floor
        region_deepest = ndimage.minimum(window, labels, np.arange(1, count + 1))
        region_area = np.bincount(labels.ravel(), minlength=count + 1)[1:]
        separate = config.separate_floor_multiple * floor
        kept[1:] |= (np.asarray(region_deepest) <= -separate) & (region_area >= config.min_area_px)
    kept[0] = False
    shape = height_m.shape
    mask = np.zeros(shape, dtype=bool)
    mask[row0:row1, col0:col1] = kept[labels]
    core_mask = np.zeros(shape, dtype=bool)
    core_mask[row0:row1, col0:col1] = core
    return mask, core_mask, ""


@lru_cache(maxsize=4)
def _pixel_xy(spec: GelSightSpec) -> tuple[np.ndarray, np.ndarray]:
    """Cached sensor-frame x and y of every pixel (read-only), as GelSightSpec.pixel_xy_sensor."""
    x, y = spec.pixel_xy_sensor()
    x.setflags(write=False)
    y.setflags(write=False)
    return x, y
