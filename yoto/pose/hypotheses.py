"""Pose hypotheses: verified poses grouped into distinct ones, with probabilities (SPEC "Pose result").

A refined pose is scored by how well it explains both contacts: each tactile cloud's residual after its sensor
correction, and how large those corrections had to be under the calibration prior. The score is a
log-likelihood,

    log L = -1/2 [ sum over contacts of n_eff (rms / fit_noise)^2 + n_free (free / free_noise)^2
                   + correction Mahalanobis^2 ],

with `n_eff` the number of effectively independent points per contact (neighbouring tactile points share their
errors), `fit_noise` the residual of a right pose, and `free` how deep the object would reach into the gel where
the sensor felt nothing, or into its housing (a pose that puts the object there is impossible).

Poses closer than `distinct_translation_m` (at the object's centroid) and `distinct_rotation_rad`, modulo the
object's symmetries, are one hypothesis; each keeps its best pose. Probabilities are the normalised likelihoods,
tempered (log L / `temperature`: the model above counts the evidence of neighbouring points and of a calibration
error only roughly, and untempered it made the truth's probability too small where it was not the first), so
hypotheses that explain the contacts equally well (a flat face that lets the object slide, a body of revolution)
share the probability, and the pose is `ambiguous` when more than one keeps at least `ambiguous_probability`.

Where the contacts leave a continuous family of poses, the refined hypotheses land anywhere along it: the
neighbours of the most likely (`neighbour_poses`) are refined as well, so that the family is covered near them.
The reported pose is the likelihood-weighted mean of the refined poses near the most likely (`family_mean`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from yoto.geometry import (
    invert_transform,
    make_transform,
    mean_rotation,
    rotation_about_axis,
    se3_exp,
    skew,
    so3_exp,
)
from yoto.objects.symmetry import Symmetry
from yoto.pose.field import SurfaceField
from yoto.pose.kernels import SEARCH_KERNELS
from yoto.pose.refine import ContactPoints, Refined
from yoto.registration import transform_batch


@dataclass(frozen=True)
class HypothesisConfig:
    """How refined poses become distinct hypotheses with probabilities."""

    distinct_translation_m: float = 0.005  # poses further apart than this (object centroid) ...
    distinct_rotation_rad: float = float(np.radians(5.0))  # ... or this (modulo symmetry) are distinct hypotheses
    fit_noise_m: float = 3e-5  # residual RMS of a right pose (sensor noise, mesh error)
    effective_points: float = 4.0  # effectively independent points per contact (scales the fit's evidence)
    temperature: float = 2.5  # probabilities from log-likelihood / temperature: the value at which the truth's
    # probability is best predicted (its mean -log p least) on simulated pairs under 1 mm / 1 deg calibration error
    free_noise_m: float = 1e-4  # free space: RMS depth of the object inside the gel or housing that costs as much
    free_effective_points: float = 4.0  # ... and its effectively independent points per contact
    min_probability: float = 1e-3  # hypotheses below this probability are not reported
    max_hypotheses: int = 40  # reported hypotheses at most (the most probable)
    ambiguous_probability: float = 0.05  # ambiguous when a second hypothesis keeps at least this probability
    neighbours_of: int = 12  # the most likely hypotheses whose neighbours are refined as well (0: none) ...
    neighbour_rotation_rad: float = float(np.radians(7.0))  # ... turned by this about each object axis ...
    neighbour_translation_m: float = 0.006  # ... and slid by this along each (both beyond distinct_*)
    family_of: int = 4  # the most likely hypotheses whose weakest directions are sampled (0: none) ...
    family_directions: int = 2  # ... this many of the weakest directions of each ...
    family_reach: float = 36.0  # ... up to this far both ways (in distinct_* units) ...
    family_step: float = 1.0  # ... every this many units
    mean_reach: float = 2.0  # the reported pose is the mean of the refined poses within this many distinct_* units
    # of the most likely, refined again (`family_mean`; 0: the most likely pose itself) ...
    mean_temperature: float = 1.0  # ... each weighted by its likelihood tempered by this (2.5, the probabilities'
    # temperature, moved a held-out cow pose 3.0 mm / 2.9 deg off to 4.7 mm / 5.5 deg)


@dataclass
class Hypotheses:
    """Distinct poses, most probable first (arrays over H)."""

    T_world_object: np.ndarray  # (H, 4, 4)
    probability: np.ndarray  # (H,) normalised over the hypotheses found (before `min_probability` is applied)
    log_likelihood: np.ndarray  # (H,)
    member: np.ndarray  # (H,) index of each hypothesis's pose in the refined set
    support: np.ndarray  # (H,) how many refined poses fell into each hypothesis

    def __len__(self) -> int:
        return len(self.probability)


GROUPING_PRODUCT_SIZE = 2_000_000  # grouping compares founders with every pose in parts of at most this many
# entries per symmetry (many poses, or a large symmetry group, stay small in memory)


def log_likelihoods(refined: Refined, config: HypothesisConfig) -> np.ndarray:
    """(K,) log-likelihood of each refined pose (see the module docstring)."""
    fit = config.effective_points * np.sum((refined.fit_rms_m / config.fit_noise_m) ** 2, axis=1)
    free = config.free_effective_points * np.sum((refined.free_rms_m / config.free_noise_m) ** 2, axis=1)
    return -0.5 * (fit + free + refined.correction_cost)


def pose_distances(T_a: np.ndarray, T_b: np.ndarray, symmetry: Symmetry) -> tuple[np.ndarray, np.ndarray]:
    """Translation (of the object's centroid, the canonical frame's origin; metres) and rotation (radians, modulo
    symmetry) between each of the (K, 4, 4) poses `T_a` and the single pose or (K, 4, 4) poses `T_b`."""
    T_b = np.broadcast_to(T_b, T_a.shape)
    return np.linalg.norm(T_a[:, :3, 3] - T_b[:, :3, 3], axis=1), symmetry.rotation_errors_rad(T_a, T_b)


def group_hypotheses(refined: Refined, symmetry: Symmetry, config: HypothesisConfig) -> Hypotheses:
    """Group refined poses into distinct hypotheses (best first) with probabilities: in order of likelihood, each
    pose not yet taken founds a hypothesis and takes every untaken pose within the distinct distances of it
    (compiled where numba is installed, `kernels.group_founders`; else `_close_pairs` for every pair at once)."""
    score = log_likelihoods(refined, config)
    order = np.argsort(-score, kind="stable")
    poses = refined.T_world_object
    if SEARCH_KERNELS is not None:
        best, support = _compiled_groups(order, poses, symmetry, config)
    else:
        close = _close_pairs(poses, symmetry, config)
        unassigned = np.ones(len(order), dtype=bool)
        members, supports = [], []
        for k in order:
            if not unassigned[k]:
                continue
            joining = unassigned & close[k]  # k among them
            unassigned &= ~joining
            members.append(k)
            supports.append(int(np.count_nonzero(joining)))
        best, support = np.array(members, dtype=np.int64), np.array(supports, dtype=np.int64)
    log_l = score[best]
    weights = np.exp((log_l - log_l.max()) / config.temperature) if len(best) else np.empty(0)
    probability = weights / weights.sum() if len(best) else weights
    return Hypotheses(poses[best], probability, log_l, best, support)


def _close_pairs(poses: np.ndarray, symmetry: Symmetry, config: HypothesisConfig) -> np.ndarray:
    """(K, K) whether each pose (row, a founder) and each other (column) of K poses (K, 4, 4) are one hypothesis:
    within `distinct_translation_m` (the centroid's distance) and `distinct_rotation_rad` modulo the symmetries
    (`Symmetry.rotation_errors_rad(other, founder)`'s angle, compared through its cosine: every pair at once by small
    matrix products, instead of a loop over founders)."""
    count, group = len(poses), len(symmetry.rotations)
    position = poses[:, :3, 3]
    moved, others = _rotation_rows(poses, symmetry)
    close = np.empty((count, count), dtype=bool)
    best = np.empty((count, count))
    rows = max(1, GROUPING_PRODUCT_SIZE // (group * count))  # founders at a time
    for first in range(0, count, rows):
        gap = position[first : first + rows, None, :] - position[None, :, :]
        close[first : first + rows] = np.sqrt(np.add.reduce(gap * gap, axis=2)) <= config.distinct_translation_m
        inner = moved[first * group : (first + rows) * group] @ others.T
        best[first : first + rows] = inner.reshape(-1, group, count).max(axis=1)
    if symmetry.spherical:
        return close
    cosine = (best - 1.0) / 2.0 if symmetry.axis_object is None else best
    least = np.cos(config.distinct_rotation_rad)
    # Pairs within rounding of the limit (poses a family step placed exactly one unit apart, which the refinement
    # left where they were) get `rotation_errors_rad`'s own angle, so the grouping is the one pose by pose.
    near = np.argwhere(close & (np.abs(cosine - least) <= 1e-9))
    close &= cosine >= least
    if len(near):
        founder, other = near.T
        angle = symmetry.rotation_errors_rad(poses[other], poses[founder])
        close[founder, other] = angle <= config.distinct_rotation_rad
    np.fill_diagonal(close, True)
    return close


def _rotation_rows(poses: np.ndarray, symmetry: Symmetry) -> tuple[np.ndarray, np.ndarray]:
    """(K G, 9) and (K, 9) rows (without an axis; (K G, 3) and (K, 3) with one) whose products give the rotation
    cosines of K poses (K, 4, 4) modulo the G symmetries: row k G + g of the first with row j of the second,
    largest over g, is founder k's and pose j's trace of R_j^T R_k S_g (the cosine is (trace - 1) / 2), or with a
    continuous axis u the swing's cosine (R_k S_g u) . (R_j u) (any twist about u is free)."""
    count, group = len(poses), len(symmetry.rotations)
    rotation = np.ascontiguousarray(poses[:, :3, :3])
    if symmetry.axis_object is None:
        # trace(R_other^T R_founder S) = <R_founder S, R_other> (entrywise)
        moved = np.einsum("kij,gjl->kgil", rotation, symmetry.rotations).reshape(count * group, 9)
        return moved, rotation.reshape(count, 9)
    u = symmetry.axis_object
    return np.einsum("kij,gj->kgi", rotation, symmetry.rotations @ u).reshape(count * group, 3), rotation @ u


def _compiled_groups(
    order: np.ndarray, poses: np.ndarray, symmetry: Symmetry, config: HypothesisConfig
) -> tuple[np.ndarray, np.ndarray]:
    """`group_hypotheses`'s founders and supports by `kernels.group_founders`: only the founders' rows, the
    cosines within rounding of the limit decided by `rotation_errors_rad`'s own angle, as `_close_pairs` does."""
    count = len(poses)
    moved, others = _rotation_rows(poses, symmetry)
    position = np.ascontiguousarray(poses[:, :3, 3])
    unassigned = np.ones(count, dtype=bool)
    row = np.empty(count, dtype=np.int8)
    state = np.zeros(3, dtype=np.int64)
    out = np.empty((2, count), dtype=np.int64)
    group = 0 if symmetry.spherical else len(symmetry.rotations)
    while True:
        founder = SEARCH_KERNELS.group_founders(  # type: ignore[union-attr]
            order,
            position,
            moved,
            others,
            group,
            config.distinct_translation_m,
            np.cos(config.distinct_rotation_rad),
            symmetry.axis_object is None,
            unassigned,
            row,
            state,
            out,
        )
        if founder < 0:
            return out[0, : state[2]].copy(), out[1, : state[2]].copy()
        near = np.flatnonzero(row == 2)
        angle = symmetry.rotation_errors_rad(poses[near], poses[np.full(len(near), founder)])
        row[near] = angle <= config.distinct_rotation_rad


def neighbour_poses(T_world_object: np.ndarray, config: HypothesisConfig) -> np.ndarray:
    """(12 H, 4, 4) the neighbours of H poses: each turned both ways about each axis of the object frame (through
    its origin, the centroid) and slid both ways along it. Where two contacts leave a continuous family of poses
    (a body of revolution that a handle breaks, a flat face), refined hypotheses land anywhere along it, further
    apart than a hypothesis reaches; refining the best ones' neighbours fills the family near them, while the
    refinement pulls every neighbour back onto the contacts in the directions they fix."""
    steps = []
    for axis in np.eye(3):
        for sign in (-1.0, 1.0):
            steps.append(make_transform(rotation_about_axis(axis, sign * config.neighbour_rotation_rad), np.zeros(3)))
            steps.append(make_transform(np.eye(3), sign * config.neighbour_translation_m * axis))
    return np.einsum("hij,sjk->hsik", np.asarray(T_world_object).reshape(-1, 4, 4), np.array(steps)).reshape(-1, 4, 4)


def weak_directions(
    field: SurfaceField,
    contacts: list[ContactPoints],
    T_world_object: np.ndarray,
    config: HypothesisConfig,
    capture_m: float,
) -> np.ndarray:
    """(H, 6, 6) for each of H poses (H, 4, 4) the object-frame twists (rotation vector, translation; one per row)
    along which the two clouds constrain the pose least first: eigenvectors of the clouds' point-to-surface
    information (Gauss-Newton, unit weights), in units of (distinct_rotation_rad, distinct_translation_m), each
    scaled so that its larger part (rotation or translation) is one unit. Points further than `capture_m` from the
    surface count nothing (the refinement's capture range)."""
    unit = np.array([config.distinct_rotation_rad] * 3 + [config.distinct_translation_m] * 3)
    information = np.zeros((len(T_world_object), 6, 6))
    T_object_world = invert_transform(T_world_object)
    for contact in contacts:
        q = transform_batch(T_object_world @ contact.T_world_sensor, contact.points_sensor)
        r, n = field.distance(q)
        assert n is not None
        # A point's row (n x q, -n), as the refinement's; points off the surface (beyond its capture) count nothing.
        rows = np.concatenate([np.cross(n, q), -n], axis=2) * (np.abs(r) < capture_m)[..., None]
        information += np.einsum("hpi,hpj->hij", rows, rows)
    information *= unit[None, :, None] * unit[None, None, :]
    _, vectors = np.linalg.eigh(information)
    directions = np.swapaxes(vectors, 1, 2)  # rows, weakest first
    size = np.maximum(np.linalg.norm(directions[..., :3], axis=2), np.linalg.norm(directions[..., 3:], axis=2))
    return directions / np.maximum(size, 1e-12)[..., None] * unit


def family_poses(
    field: SurfaceField,
    contacts: list[ContactPoints],
    hypotheses: Hypotheses,
    config: HypothesisConfig,
    capture_m: float,
) -> np.ndarray:
    """(F, 4, 4) poses along the weakest directions of the most likely hypotheses (`weak_directions`), both ways,
    every `family_step` units up to `family_reach`. Where two contacts leave a family of poses (a body of revolution
    turned about its axis, a box slid along its faces), the weakest direction is the family's, and the screw motion
    along it follows the family far beyond where a linear step would: the truth there, however far from the
    hypotheses found, lies near one of these."""
    count = min(len(hypotheses), config.family_of)
    if count == 0:
        return np.empty((0, 4, 4))
    T = hypotheses.T_world_object[:count]
    directions = weak_directions(field, contacts, T, config, capture_m)[:, : config.family_directions]  # (H, D, 6)
    steps = np.arange(config.family_step, config.family_reach + 1e-9, config.family_step)
    steps = np.concatenate([-steps[::-1], steps])
    twists = directions[:, :, None, :] * steps[None, None, :, None]  # (H, D, S, 6)
    moves = se3_exp(twists.reshape(count, -1, 6))
    return np.einsum("hij,hsjk->hsik", T, moves).reshape(-1, 4, 4)


def family_mean(refined: Refined, hypotheses: Hypotheses, symmetry: Symmetry, config: HypothesisConfig) -> np.ndarray:
    """(4, 4) the estimate within the first hypothesis's family: the mean of the refined poses within `mean_reach`
    units (`distinct_*`, the larger ratio, modulo symmetry) of its pose, each weighted by its likelihood tempered by
    `mean_temperature`. Where the contacts leave the pose free along a family (a rounded contact rolls, a flat
    face slides), the most likely pose is one draw from it; were the likelihoods the posterior, the weighted mean
    (rotations: the chordal mean, after mapping each pose by the symmetry nearest the first) would have the smaller
    expected error."""
    first = int(hypotheses.member[0])
    poses = refined.T_world_object
    translation, rotation = pose_distances(poses, poses[first], symmetry)
    units = np.maximum(translation / config.distinct_translation_m, rotation / config.distinct_rotation_rad)
    near = np.flatnonzero(units <= config.mean_reach)
    score = log_likelihoods(refined.subset(near), config)
    weights = np.exp((score - score.max()) / config.mean_temperature)
    mean = np.eye(4)
    mean[:3, 3] = weights @ poses[near, :3, 3] / weights.sum()
    mean[:3, :3] = (
        poses[first, :3, :3]
        if symmetry.spherical
        else mean_rotation(_nearest_equivalent(poses[first, :3, :3], poses[near, :3, :3], symmetry), weights)
    )
    return mean


def _nearest_equivalent(rotation: np.ndarray, rotations: np.ndarray, symmetry: Symmetry) -> np.ndarray:
    """(K, 3, 3) each of `rotations` composed with the symmetry (discrete, and a twist about the continuous axis)
    that brings it nearest (chordally) to `rotation`."""
    composed = np.einsum("kij,gjl->kgil", rotations, symmetry.rotations)  # (K, G, 3, 3)
    relative = np.einsum("ji,kgjl->kgil", rotation, composed)  # R^T R_k S
    if symmetry.axis_object is None:
        best = np.trace(relative, axis1=-2, axis2=-1).argmax(axis=1)
        return composed[np.arange(len(rotations)), best]
    # trace(M Rot(u, a)) = c cos a + s sin a + u.M u, with c = trace M - u.M u and s = trace(M [u]x)
    u = symmetry.axis_object
    along = np.einsum("i,kgij,j->kg", u, relative, u)
    c = np.trace(relative, axis1=-2, axis2=-1) - along
    s = np.einsum("kgij,ji->kg", relative, skew(u))
    best = (np.hypot(c, s) + along).argmax(axis=1)
    pick = np.arange(len(rotations))
    return composed[pick, best] @ so3_exp(np.arctan2(s[pick, best], c[pick, best])[:, None] * u)


def spread(hypotheses: Hypotheses, symmetry: Symmetry, scale_m: float, scale_rad: float, cap: float) -> float:
    """How far the probability reaches from the first hypothesis: the probability-weighted distance of every
    hypothesis from the first (modulo symmetry: poses a symmetry maps onto each other are one pose for a robot), in
    units of (`scale_m`, `scale_rad`) (the larger of the two ratios), each capped at `cap` (a hypothesis far off is
    simply elsewhere). Near 0 when the other hypotheses are close neighbours of the first along a family of poses
    (a rotation of a few degrees about a rounded contact), large when they are poses elsewhere on the object."""
    if len(hypotheses) < 2:
        return 0.0
    translation, rotation = pose_distances(hypotheses.T_world_object, hypotheses.T_world_object[0], symmetry)
    distance = np.minimum(np.maximum(translation / scale_m, rotation / scale_rad), cap)
    weights = hypotheses.probability / hypotheses.probability.sum()
    return float(np.sum(weights * distance))


def reported(hypotheses: Hypotheses, config: HypothesisConfig) -> Hypotheses:
    """The hypotheses worth reporting: at least `min_probability`, at most `max_hypotheses` (the first is kept)."""
    keep = np.flatnonzero(hypotheses.probability >= config.min_probability)[: config.max_hypotheses]
    if len(keep) == 0 and len(hypotheses):
        keep = np.array([0])
    return Hypotheses(*(getattr(hypotheses, name)[keep] for name in hypotheses.__dataclass_fields__))


def is_ambiguous(hypotheses: Hypotheses, config: HypothesisConfig) -> bool:
    """More than one hypothesis keeps a meaningful share of the probability."""
    return bool(len(hypotheses) > 1 and hypotheses.probability[1] >= config.ambiguous_probability)
