"""Scores of a contact against the anchors: plane-corrected height differences and the free-space test."""

from __future__ import annotations

import itertools

import numpy as np

from yoto.localize.match.anchors import AnchorMaps
from yoto.localize.match.config import MatchConfig
from yoto.localize.match.contact import ContactImage, ContactMaps
from yoto.localize.match.kernels import KERNELS


def plane_costs(
    mt: np.ndarray,
    t: np.ndarray,
    ma: np.ndarray,
    h: np.ndarray,
    hh: np.ndarray,
    centres: np.ndarray,
    remove_tilt: bool,
    air_penalty_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Cost (R, A) of every (roll, anchor) and the fitted plane beta = (offset, slope x, slope y), (3, R, A).

    Inputs: the contact's mask and heights (R, C) at the cell centres (C, 2) for each roll, and the anchors'
    validity, heights and squared heights as (C, A) columns (heights 0 where invalid). With d = t - h over the
    cells both cover, cost = (min_beta sum (d - beta . (1, x, y))^2 + air_penalty^2 * contact cells where the
    anchor has no surface) / contact cells; without `remove_tilt` beta is the offset alone. Every sum over
    cells is one matrix product of (rolls x cells) contact terms with (cells x anchors) anchor terms.
    """
    mtt = mt * t
    total = mt.sum(axis=1, keepdims=True)
    if remove_tilt:
        sums, height_sums, squared_sums = _tilt_products(mt, t, ma, h, hh, centres)
        n, sx, sy, sxx, sxy, syy, st, stx, sty, stt = np.split(sums, 10)
        sh, shx, shy, sth = np.split(height_sums, 4)
        b0, b1, b2 = st - sh, stx - shx, sty - shy
        sdd = stt - 2.0 * sth + squared_sums
        # Normal equations G beta = b, G = [[n, sx, sy], [sx, sxx, sxy], [sy, sxy, syy]], solved by cofactors.
        c00, c01, c02 = sxx * syy - sxy * sxy, sy * sxy - sx * syy, sx * sxy - sy * sxx
        c11, c12, c22 = n * syy - sy * sy, sx * sy - n * sxy, n * sxx - sx * sx
        det = n * c00 + sx * c01 + sy * c02
        spread = sxx + syy
        # A plane needs cells spread in two directions: det is ~ n * (second moments)^2 when it is well posed.
        solvable = (n >= 6) & (det > 1e-2 * n * spread * spread / 4.0)
        inv = np.where(solvable, 1.0 / np.where(solvable, det, 1.0), 0.0)
        beta = np.stack(
            [
                (c00 * b0 + c01 * b1 + c02 * b2) * inv,
                (c01 * b0 + c11 * b1 + c12 * b2) * inv,
                (c02 * b0 + c12 * b1 + c22 * b2) * inv,
            ]
        )
        safe_n = np.maximum(n, 1.0)
        sse = np.where(solvable, sdd - (beta[0] * b0 + beta[1] * b1 + beta[2] * b2), sdd - b0 * b0 / safe_n)
        beta[0] = np.where(solvable, beta[0], b0 / safe_n)
    else:
        n, st, stt = np.split(np.concatenate([mt, mtt, mtt * t]) @ ma, 3)
        sh, sth = np.split(np.concatenate([mt, mtt]) @ h, 2)
        safe_n = np.maximum(n, 1.0)
        sse = stt - 2.0 * sth + mt @ hh - (st - sh) ** 2 / safe_n
        beta = np.zeros((3,) + n.shape, dtype=np.float32)
        beta[0] = (st - sh) / safe_n
    cost = (np.maximum(sse, 0.0) + air_penalty_m**2 * (total - n)) / np.maximum(total, 1.0)
    return cost, beta


def _tilt_products(
    mt: np.ndarray, t: np.ndarray, ma: np.ndarray, h: np.ndarray, hh: np.ndarray, centres: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The matrix products of `plane_costs` with tilt: the contact's mask moments and height sums (10 R rows) against
    the anchors' validity, (mask, its x and y moments, heights) (4 R rows) against their heights, the mask against
    their squared heights (R rows)."""
    x, y = centres.T.astype(np.float32)
    mtt = mt * t
    first = np.concatenate([mt, mt * x, mt * y, mt * x * x, mt * x * y, mt * y * y, mtt, mtt * x, mtt * y, mtt * t])
    return first @ ma, np.concatenate([mt, mt * x, mt * y, mtt]) @ h, mt @ hh


def best_plane_costs(
    mt: np.ndarray,
    t: np.ndarray,
    ma: np.ndarray,
    h: np.ndarray,
    hh: np.ndarray,
    centres: np.ndarray,
    remove_tilt: bool,
    air_penalty_m: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`plane_costs` at each anchor's best roll: the roll (A,) (the first of equal costs), its cost (A,) float64 and
    its plane (3, A); compiled past the products where numba is, the same numbers."""
    if KERNELS is not None and remove_tilt:
        total = mt.sum(axis=1)
        roll, cost, beta = KERNELS.best_plane_costs(
            *_tilt_products(mt, t, ma, h, hh, centres), total, np.float32(air_penalty_m**2)
        )
        return roll, cost.astype(np.float64), beta
    costs, betas = plane_costs(mt, t, ma, h, hh, centres, remove_tilt, air_penalty_m)
    roll = np.argmin(costs, axis=0)
    columns = np.arange(costs.shape[1])
    return roll, costs[roll, columns].astype(np.float64), betas[:, roll, columns]


def free_space_penalty(
    contact: ContactMaps,
    anchors: AnchorMaps,
    anchor_index: np.ndarray,
    roll_index: np.ndarray,
    beta: np.ndarray,
    config: MatchConfig,
) -> np.ndarray:
    """(K,) sum over free pad cells of the squared depth by which the anchor's surface would push into the gel.

    Under a hypothesis the contact-frame height of the anchor's surface at a cell is h + beta . (1, x, y); the
    gel plane lies at `gel_heights`. Surface nearer the sensor than the plane (less a margin) on a cell where
    the sensor saw no contact contradicts the hypothesis.
    """
    x, y = anchors.grid.centres.T.astype(np.float32)
    if KERNELS is not None:
        squared = KERNELS.free_space_squares(
            anchors.heights, anchors.valid, anchor_index, roll_index, np.ascontiguousarray(beta), x, y,
            contact.gel_heights, contact.free, np.float32(contact.image.free_margin_m),
            np.float32(config.anchors.ray_start_m),
        )  # fmt: skip
        return np.asarray(squared.sum(axis=1, dtype=np.float64))
    surface = anchors.heights[anchor_index] + beta[0][:, None] + beta[1][:, None] * x + beta[2][:, None] * y
    depth = np.minimum(
        contact.gel_heights[roll_index] - np.float32(contact.image.free_margin_m) - surface,
        np.float32(config.anchors.ray_start_m),
    )
    judged = contact.free[roll_index] & (anchors.valid[anchor_index] > 0)
    squared = np.square(np.maximum(depth, 0.0), where=judged, out=np.zeros_like(depth))
    return np.asarray(squared.sum(axis=1, dtype=np.float64))


def free_space_violation(
    anchors: AnchorMaps, image: ContactImage, T_object_sensor: np.ndarray, config: MatchConfig
) -> np.ndarray:
    """(K,) mean squared depth (capped at tau) by which the object would push into the gel unseen, per tactile sample.

    Anchors near the sensor (a sample of the surface every `anchor_spacing_m`) are mapped into the sensor frame;
    those over the pad, beyond the gel plane by more than the margin, and not near the observed contact, each
    contribute their depth squared, weighted by the area they represent relative to a tactile sample's.
    """
    pad = np.asarray(config.pad_size_m) / 2.0
    reach = float(np.hypot(*pad)) + 0.002
    tactile_samples = max(int(image.mask.sum()), 1)
    sample_area = image.pixel_m**2
    if KERNELS is not None:
        sums = np.empty(len(T_object_sensor))
        KERNELS.free_space_depths(
            anchors.points_object, np.ascontiguousarray(T_object_sensor, dtype=np.float64), reach, pad[0], pad[1],
            image.free_margin_m, np.ascontiguousarray(image.centre_sensor, dtype=np.float64), image.basis_sensor,
            image.half_m, image.pixel_m, ~image.touched, config.residual_tau_m, sums,
        )  # fmt: skip
        return sums * anchors.area_m2 / sample_area / tactile_samples
    members = anchors.kdtree.query_ball_point(T_object_sensor[:, :3, 3], reach)
    counts = np.array([len(m) for m in members])
    if counts.sum() == 0:
        return np.zeros(len(T_object_sensor))
    owner = np.repeat(np.arange(len(T_object_sensor)), counts)
    index = np.fromiter(itertools.chain.from_iterable(members), dtype=np.int64, count=int(counts.sum()))
    p_object = anchors.points_object.take(index, axis=0)
    # Each pose's anchors into its sensor frame: one small product per pose (the members lie in pose order).
    p_sensor = np.empty_like(p_object)
    ends = np.cumsum(counts)
    for k, (start, end) in enumerate(zip(ends - counts, ends, strict=True)):
        p_sensor[start:end] = (p_object[start:end] - T_object_sensor[k, :3, 3]) @ T_object_sensor[k, :3, :3]
    depth = -p_sensor[:, 2] - image.free_margin_m
    over = (np.abs(p_sensor[:, 0]) <= pad[0]) & (np.abs(p_sensor[:, 1]) <= pad[1]) & (depth > 0)
    local = (p_sensor[over] - image.centre_sensor) @ image.basis_sensor
    away = image.covered(local[:, 0], local[:, 1], ~image.touched)
    depth = np.minimum(depth[over][away], config.residual_tau_m)
    violation = np.bincount(owner[over][away], weights=depth**2, minlength=len(T_object_sensor))
    return violation * anchors.area_m2 / sample_area / tactile_samples
