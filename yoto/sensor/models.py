"""The two optical models a calibration fits: colour change -> surface gradient, and its inverse.

Both are linear least-squares fits on polynomial features, chosen by measurement (docs/sensor.md): a cubic
in the colour change alone leaves held-out gradient errors about 1.7x larger than the same cubic plus
terms that let the colour-to-gradient gain vary with pixel position (the LEDs light the pad unevenly),
and a small MLP did no better than the cubic while taking minutes to train on this CPU.

Forward model (reconstruction, must be fast):
    g(c, x, y) = T(c) + sum_j c_j M_j(x, y)
with c the RGB colour change against the background, T a cubic in c without constant term (zero colour change is
flat gel: zero slope), M_j polynomials in pixel position (degree 2 to 4, chosen per calibration by held-out error
on its presses: ball_calibration). After fitting it is baked into a 3D lookup table for T's terms of degree 2 and 3
(indexed by the quantised colour change; cells no training colour came near take the value of the nearest cell
that one did, so the cubic never extrapolates) and per-pixel maps for M_j plus T's linear part, applied exactly
(a faint colour change is not read at its table cell's centre): inference is one table gather and three
multiply-adds per output. Calibrations written before (`anchored` False) also have a position bias b(x, y) and the
whole cubic, with its constant, in the table.

Inverse model (the optical simulator):
    c(g, x, y) = S(g) + sum_k m_k(g) N_k(x, y)
with S a quartic in the gradient (gx, gy) without constant term, m_k the gradient's monomials up to a gain
degree (1: gx, gy; 2: also their squares and product) and N_k polynomials in position (both chosen per
calibration by held-out error): a flat gel (zero gradient) renders exactly the background. Evaluated
directly (no table), gradients clamped to the magnitude range seen in calibration.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations_with_replacement

import numpy as np
from scipy import ndimage

# ---------------------------------------------------------------------------------------------------------
# Features


def monomial_exponents(num_vars: int, degree: int) -> np.ndarray:
    """(M, num_vars) exponents of every monomial of total degree 0..degree, constant first."""
    rows = [np.zeros(num_vars, dtype=np.int64)]
    for total in range(1, degree + 1):
        for combo in combinations_with_replacement(range(num_vars), total):
            exponent = np.zeros(num_vars, dtype=np.int64)
            for var in combo:
                exponent[var] += 1
            rows.append(exponent)
    return np.stack(rows)


def monomials(values: np.ndarray, exponents: np.ndarray) -> np.ndarray:
    """(N, M) monomials of (N, num_vars) values."""
    columns = np.ascontiguousarray(np.asarray(values, dtype=np.float64).T)
    out = np.ones((len(exponents), columns.shape[1]))  # monomial-major: each row written contiguously
    for m, exponent in enumerate(exponents):
        for var, power in enumerate(exponent):
            if power:
                out[m] *= columns[var] if power == 1 else columns[var] ** power
    return out.T


def normalised_xy(rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel positions scaled to [-1, 1] across the image, each (rows, cols) float64."""
    x = (np.arange(cols) - (cols - 1) / 2.0) / ((cols - 1) / 2.0)
    y = (np.arange(rows) - (rows - 1) / 2.0) / ((rows - 1) / 2.0)
    return np.meshgrid(x, y)


def _mixed_design(
    inputs: np.ndarray,
    xy: np.ndarray,
    input_scale: float,
    degree: int,
    position_degree: int,
    anchored: bool = False,
    gain_degree: int = 1,
) -> np.ndarray:
    """Design matrix [monomials(inputs) | pos | m_j(inputs) * pos], pos the non-constant position monomials and
    m_j the non-constant input monomials up to `gain_degree` (1: the inputs themselves).

    `anchored` drops the columns that do not vanish at zero input (the constant and `pos`), so the model
    predicts exactly zero for a zero input.
    """
    scaled = inputs / input_scale
    exponents = monomial_exponents(inputs.shape[1], degree)
    main = monomials(scaled, exponents)
    position = monomials(xy, monomial_exponents(2, position_degree))[:, 1:]
    gained = main[:, 1 : len(monomial_exponents(inputs.shape[1], gain_degree))]
    gains = [gained[:, [j]] * position for j in range(gained.shape[1])]
    if anchored:
        return np.hstack([main[:, 1:], *gains])
    return np.hstack([main, position, *gains])


def solve_ridge(design: np.ndarray, targets: np.ndarray, weights: np.ndarray, ridge: float) -> np.ndarray:
    """Weighted least squares with a Tikhonov weight `ridge` (relative to the sample count): the coefficients."""
    sqrt_w = np.sqrt(weights)[:, None]
    a = design * sqrt_w
    normal = a.T @ a
    normal[np.diag_indices_from(normal)] += ridge * len(design)
    return np.linalg.solve(normal, a.T @ (targets * sqrt_w))


# ---------------------------------------------------------------------------------------------------------
# Colour change as the models see it


def model_colour_change(image: np.ndarray, background_i16: np.ndarray, smooth: bool) -> np.ndarray:
    """int16 (rows, cols, 3) colour change, optionally smoothed by a 3x3 binomial filter (edges replicated).

    Integer arithmetic throughout so calibration and reconstruction see bit-identical inputs.
    """
    diff = image.astype(np.int16)
    diff -= background_i16
    if not smooth:
        return diff
    across = diff * 2
    across[:, 1:] += diff[:, :-1]
    across[:, :-1] += diff[:, 1:]
    across[:, 0] += diff[:, 0]
    across[:, -1] += diff[:, -1]
    out = across * 2
    out[1:] += across[:-1]
    out[:-1] += across[1:]
    out[0] += across[0]
    out[-1] += across[-1]
    out += 8
    out >>= 4
    return out


# ---------------------------------------------------------------------------------------------------------
# Colour change -> gradient


@dataclass(frozen=True)
class GradientModelConfig:
    """Shape of the colour -> gradient model."""

    colour_degree: int = 3  # degree of the polynomial in the colour change (3 chosen by held-out error)
    position_degree: int = 2  # degree of the position polynomials of the bias and per-channel gains
    colour_scale: float = 50.0  # colour change is divided by this before forming monomials (conditioning)
    lut_step: int = 4  # colour-change quantisation of the lookup table (RGB levels per cell; a power of two)
    lut_offset: int = 128  # colour change -lut_offset maps to cell 0; the table covers [-128, 128)
    occupied_radius: int = 2  # table cells within this many cells of a training colour count as seen
    ridge: float = 1e-6  # Tikhonov weight (relative to the sample count)
    anchored: bool = True  # no constant or position bias: zero colour change reads as zero slope (the background is
    # flat gel), and the linear part is applied exactly per pixel, the table holds only the rest (False: files
    # written before, with the whole cubic and a bias in the table)


@dataclass
class GradientModel:
    """Baked colour -> gradient model: a lookup table over the quantised colour change plus per-pixel maps."""

    lut: np.ndarray  # (2, Q^3) float32: T(c) for gx and gy, flat index (qr * Q + qg) * Q + qb
    bias: np.ndarray  # (2, rows, cols) float32: b(x, y) for gx and gy
    gains: np.ndarray  # (2, 3, rows, cols) float32: M_j(x, y) for gx, gy and channels r, g, b
    coefficients: np.ndarray  # (num_features, 2) float64: the fitted polynomial (kept for inspection)
    config: GradientModelConfig

    def __post_init__(self) -> None:
        if 256 % self.config.lut_step or self.config.lut_step & (self.config.lut_step - 1):
            raise ValueError(f"lut_step must be a power of two dividing 256, got {self.config.lut_step}")
        # (gx, gy) float32 pairs viewed as one 8-byte item: one gather fetches both.
        self._pairs = np.ascontiguousarray(self.lut.T, dtype=np.float32).view(np.float64).reshape(-1)

    @property
    def cells_per_channel(self) -> int:
        return 256 // self.config.lut_step

    def lut_index(self, diff: np.ndarray) -> np.ndarray:
        """Flat table index (qr * Q + qg) * Q + qb of each pixel of an int16 (rows, cols, 3) colour change."""
        shift = int(self.config.lut_step).bit_length() - 1
        bits = int(self.cells_per_channel).bit_length() - 1
        q = diff + np.int16(self.config.lut_offset)
        np.clip(q, 0, 255, out=q)
        q >>= shift
        index = np.left_shift(q[..., 0], 2 * bits, dtype=np.int32)
        index |= np.left_shift(q[..., 1], bits, dtype=np.int32)
        index |= q[..., 2]
        return index

    def predict(self, diff: np.ndarray, origin: tuple[int, int] = (0, 0)) -> tuple[np.ndarray, np.ndarray]:
        """Gradients (gx, gy), each (rows, cols) float32, of an int16 (rows, cols, 3) colour change.

        `diff` may be a window of the frame whose top-left pixel is `origin` (row, column).
        """
        rows, cols = diff.shape[:2]
        window = (slice(origin[0], origin[0] + rows), slice(origin[1], origin[1] + cols))
        pairs = self._pairs.take(self.lut_index(diff)).view(np.float32).reshape(rows, cols, 2)
        change = np.empty((3, rows, cols), dtype=np.float32)
        for j in range(3):
            change[j] = diff[..., j]
        scratch = np.empty((rows, cols), dtype=np.float32)
        out = []
        for k in range(2):
            g = pairs[..., k] + self.bias[k][window]
            for j in range(3):
                np.multiply(change[j], self.gains[k, j][window], out=scratch)
                g += scratch
            out.append(g)
        return out[0], out[1]

    def predict_reference(self, diff: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The fitted polynomial evaluated directly (slow, no table): the reference of the fast path."""
        rows, cols = diff.shape[:2]
        x, y = normalised_xy(rows, cols)
        design = gradient_design(
            diff.reshape(-1, 3).astype(np.float64), np.stack([x.ravel(), y.ravel()], 1), self.config
        )
        g = (design @ self.coefficients).reshape(rows, cols, 2)
        return g[..., 0], g[..., 1]

    def arrays(self, prefix: str) -> dict[str, np.ndarray]:
        """What a file stores: the table and the coefficients (the per-pixel maps are rebuilt on load)."""
        return {f"{prefix}lut": self.lut, f"{prefix}coefficients": self.coefficients}


def fit_gradient_model(
    diffs: np.ndarray,
    xy: np.ndarray,
    gradients: np.ndarray,
    weights: np.ndarray,
    image_shape: tuple[int, int],
    config: GradientModelConfig = GradientModelConfig(),
) -> GradientModel:
    """Fit colour change (N, 3) at normalised positions (N, 2) -> gradients (N, 2), then bake it.

    `weights` (N,) weight each sample in the least-squares fit.
    """
    if config.lut_step & (config.lut_step - 1):
        raise ValueError(f"lut_step must be a power of two, got {config.lut_step}")
    design = gradient_design(diffs, xy, config)
    coefficients = solve_ridge(design, gradients, weights, config.ridge)
    return bake_gradient_model(coefficients, diffs, image_shape, config)


def gradient_design(diffs: np.ndarray, xy: np.ndarray, config: GradientModelConfig) -> np.ndarray:
    """Design matrix of the colour -> gradient model for colour changes (N, 3) at normalised positions (N, 2)."""
    return _mixed_design(
        diffs, xy, config.colour_scale, config.colour_degree, config.position_degree, anchored=config.anchored
    )


def bake_gradient_model(
    coefficients: np.ndarray,
    seen_diffs: np.ndarray,
    image_shape: tuple[int, int],
    config: GradientModelConfig,
) -> GradientModel:
    """Turn fitted coefficients into the lookup table and per-pixel maps.

    Anchored models keep the linear part of T out of the table (the per-pixel gains apply it exactly): a faint
    colour change of a level or two is then not read at its table cell's centre, up to half a cell away.
    """
    colour_exps, c_colour = _colour_part(coefficients, config)

    # Table: T(c) at each cell's centre colour; cells far from any training colour copy the nearest seen cell.
    n = 256 // config.lut_step
    centres = np.arange(n) * config.lut_step - config.lut_offset + (config.lut_step - 1) / 2.0
    grid = np.stack(np.meshgrid(centres, centres, centres, indexing="ij"), axis=-1).reshape(-1, 3)
    if config.anchored:
        c_colour = c_colour.copy()
        c_colour[1:4] = 0.0  # the linear monomials (c_r, c_g, c_b) follow the constant: in the gain maps
    table = monomials(grid / config.colour_scale, colour_exps) @ c_colour  # (n^3, 2)
    seen = np.zeros((n, n, n), dtype=bool)
    cells = np.clip((np.round(seen_diffs).astype(np.int64) + config.lut_offset) // config.lut_step, 0, n - 1)
    seen[cells[:, 0], cells[:, 1], cells[:, 2]] = True
    if config.occupied_radius > 0:
        seen = ndimage.binary_dilation(seen, iterations=config.occupied_radius)
    _, nearest = ndimage.distance_transform_edt(~seen, return_indices=True)
    flat_nearest = np.ravel_multi_index(tuple(nearest.reshape(3, -1)), (n, n, n))
    table = table[flat_nearest]

    bias, gains = _position_maps(coefficients, image_shape, config)
    return GradientModel(np.ascontiguousarray(table.T, dtype=np.float32), bias, gains, coefficients, config)


def _position_maps(
    coefficients: np.ndarray, image_shape: tuple[int, int], config: GradientModelConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel bias b(x, y) (2, rows, cols) and gains M_j(x, y) (2, 3, rows, cols) of the raw change.

    An anchored model has no bias (zero maps), and its gains include T's linear part (see `bake_gradient_model`).
    """
    colour_exps, c_colour = _colour_part(coefficients, config)
    n_colour = len(colour_exps) - int(config.anchored)
    position_exps = monomial_exponents(2, config.position_degree)[1:]
    n_pos = len(position_exps)
    rows, cols = image_shape
    x, y = normalised_xy(rows, cols)
    pos = monomials(np.stack([x.ravel(), y.ravel()], 1), position_exps)  # (pixels, n_pos)
    if config.anchored:
        bias = np.zeros((2, rows, cols))
        c_gain = coefficients[n_colour:].reshape(3, n_pos, 2)
    else:
        bias = (pos @ coefficients[n_colour : n_colour + n_pos]).T.reshape(2, rows, cols)
        c_gain = coefficients[n_colour + n_pos :].reshape(3, n_pos, 2)
    gains = np.stack([(pos @ c_gain[j]).T.reshape(2, rows, cols) for j in range(3)], axis=1)
    if config.anchored:
        gains += c_colour[1:4].T[:, :, None, None]  # T's linear part (gx, gy by channel), the same at every pixel
    gains /= config.colour_scale
    return bias.astype(np.float32), np.ascontiguousarray(gains, dtype=np.float32)


def _colour_part(coefficients: np.ndarray, config: GradientModelConfig) -> tuple[np.ndarray, np.ndarray]:
    """Exponents of T's monomials (constant first) and their coefficients (an anchored model's constant is 0)."""
    colour_exps = monomial_exponents(3, config.colour_degree)
    if config.anchored:
        c_colour = np.vstack([np.zeros((1, coefficients.shape[1])), coefficients[: len(colour_exps) - 1]])
    else:
        c_colour = coefficients[: len(colour_exps)]
    return colour_exps, c_colour


def load_gradient_model(
    arrays: dict[str, np.ndarray], prefix: str, config: GradientModelConfig, image_shape: tuple[int, int]
) -> GradientModel:
    """Rebuild a baked model from its stored table and coefficients (the per-pixel maps are recomputed)."""
    coefficients = np.asarray(arrays[f"{prefix}coefficients"], dtype=np.float64)
    lut = np.ascontiguousarray(arrays[f"{prefix}lut"], dtype=np.float32)
    cells = (256 // config.lut_step) ** 3
    expected = _design_width(3, config.colour_degree, config.position_degree, config.anchored)
    if lut.shape != (2, cells) or coefficients.shape != (expected, 2):
        raise ValueError(
            f"model arrays have shapes {lut.shape} and {coefficients.shape}, expected (2, {cells}) and ({expected}, 2)"
        )
    bias, gains = _position_maps(coefficients, image_shape, config)
    return GradientModel(lut, bias, gains, coefficients, config)


def _design_width(num_inputs: int, degree: int, position_degree: int, anchored: bool) -> int:
    n_pos = len(monomial_exponents(2, position_degree)) - 1
    if anchored:
        return len(monomial_exponents(num_inputs, degree)) - 1 + n_pos * num_inputs
    return len(monomial_exponents(num_inputs, degree)) + n_pos * (1 + num_inputs)


# ---------------------------------------------------------------------------------------------------------
# Gradient -> colour change


@dataclass(frozen=True)
class ImageModelConfig:
    """Shape of the gradient -> colour model of the optical simulator."""

    gradient_degree: int = 4  # degree of the polynomial in (gx, gy)
    position_degree: int = 2  # degree of the position polynomials of the per-gradient gains
    gain_degree: int = 1  # the gains multiply the gradient's monomials up to this degree (1: gx and gy only)
    ridge: float = 1e-6  # Tikhonov weight (relative to the sample count)


@dataclass
class ImageModel:
    """Gradient (gx, gy) at a pixel -> RGB colour change against the background."""

    coefficients: np.ndarray  # (num_features, 3) float64
    max_gradient: float  # gradients are clamped to this magnitude (the largest seen in calibration)
    config: ImageModelConfig
    gain: np.ndarray | None = None  # (M,) polynomial of `config.position_degree` in the normalised pixel position
    # (constant first, `monomial_exponents` order) scaling the colour change so that the gradient model reads rendered
    # ball presses as it reads the real ones (`ball_calibration.round_trip_gain`); None: 1 (files written before it)

    def predict(self, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
        """(rows, cols, 3) float32 colour change of (rows, cols) gradient maps (exactly zero where the gel is flat,
        which is skipped)."""
        rows, cols = gx.shape
        magnitude = np.hypot(gx, gy)
        sloped = magnitude > 0
        scale = np.minimum(1.0, self.max_gradient / np.maximum(magnitude[sloped], 1e-12))
        g = np.stack([gx[sloped] * scale, gy[sloped] * scale], 1)
        x, y = normalised_xy(rows, cols)
        xy = np.stack([x[sloped], y[sloped]], 1)
        change = np.zeros((rows, cols, 3), dtype=np.float32)
        values = self._evaluate(g, xy)
        if self.gain is not None:
            values *= (monomials(xy, monomial_exponents(2, self.config.position_degree)) @ self.gain)[:, None]
        change[sloped] = values
        return change

    def _evaluate(self, gradients: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """`image_design(gradients, xy) @ coefficients` without forming the design: monomials times their
        coefficients plus, per gained monomial, its value times its position polynomial (N, 3)."""
        config = self.config
        main = monomials(gradients, monomial_exponents(2, config.gradient_degree))[:, 1:]
        position = monomials(xy, monomial_exponents(2, config.position_degree))[:, 1:]
        # einsum, not BLAS: a threaded matrix product of a tall thin matrix stalls on a busy machine.
        out = np.einsum("nk,kc->nc", main, self.coefficients[: main.shape[1]])
        gained = len(monomial_exponents(2, config.gain_degree)) - 1
        blocks = self.coefficients[main.shape[1] :].reshape(gained, position.shape[1], -1)
        gains = np.einsum("np,jpc->jnc", position, blocks)
        for j in range(gained):
            out += main[:, [j]] * gains[j]
        return out

    def arrays(self, prefix: str) -> dict[str, np.ndarray]:
        gain = {} if self.gain is None else {f"{prefix}gain": self.gain}
        return {f"{prefix}coefficients": self.coefficients, **gain}


def fit_image_model(
    gradients: np.ndarray,
    xy: np.ndarray,
    diffs: np.ndarray,
    weights: np.ndarray,
    config: ImageModelConfig = ImageModelConfig(),
) -> ImageModel:
    """Fit gradients (N, 2) at normalised positions (N, 2) -> colour change (N, 3)."""
    design = image_design(gradients, xy, config)
    coefficients = solve_ridge(design, diffs, weights, config.ridge)
    max_gradient = float(np.percentile(np.hypot(gradients[:, 0], gradients[:, 1]), 99.5))
    return ImageModel(coefficients, max_gradient, config)


def image_design(gradients: np.ndarray, xy: np.ndarray, config: ImageModelConfig) -> np.ndarray:
    """Design matrix of the gradient -> colour model for gradients (N, 2) at normalised positions (N, 2)."""
    return _mixed_design(
        gradients,
        xy,
        1.0,
        config.gradient_degree,
        config.position_degree,
        anchored=True,
        gain_degree=config.gain_degree,
    )
