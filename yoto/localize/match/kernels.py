"""Compiled loops of the matched filter (numba, the `fast` extra, through `yoto.jit`), numpy as the fallback.

`KERNELS` is None where numba is missing (or `YOTO_NO_NUMBA=1` is set); callers then take their numpy paths.

- The candidate ICP (`localizer.candidate_icp`, `registration.point_to_plane_gauss_newton` for its one use here: a
  pivot, one facing normal, every pose iterating until it stops): per iteration one pass transforms the active
  poses' points for the nearest-point lookups (pykdtree or SciPy, called between the passes), and one pass per pose
  gathers its matches, takes the robust scale (the same median), sums its 6 x 6 system point by point, solves it by
  Cholesky and moves the pose, with none of the numpy path's (K, M, ...) temporaries. The residual fits and the
  free-space violation likewise. Their sums and the solve run in another order than numpy's BLAS and LAPACK:
  poses and residuals agree to ~1e-13 (docs/journal/localization.md, "Compiled kernels").
- The filter's per-cell work (the contact's maps at every roll, the plane costs past their matrix products with
  each anchor's best roll, the free-space penalty's squared depths): numpy's float32 operations in numpy's order,
  bitwise its results.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from yoto.jit import ENABLED, jit


@jit
def transform_active(poses, active, points, out):
    """out[k] = the (M, 3) points under pose active[k] (out: (len(active), M, 3))."""
    for k in range(active.shape[0]):
        pose = poses[active[k]]
        for m in range(points.shape[0]):
            x, y, z = points[m, 0], points[m, 1], points[m, 2]
            for i in range(3):
                out[k, m, i] = pose[i, 0] * x + pose[i, 1] * y + pose[i, 2] * z + pose[i, 3]


@jit
def _rotation_log(r, out):
    """`geometry.so3_log` of one 3 x 3 rotation into out (3,): the same formulas, the branch near pi included."""
    a0, a1, a2 = r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]
    cos_angle = min(max((r[0, 0] + r[1, 1] + r[2, 2] - 1.0) / 2.0, -1.0), 1.0)
    angle = np.arctan2(np.sqrt(a0 * a0 + a1 * a1 + a2 * a2) / 2.0, cos_angle)
    factor = 0.5 if angle < 1e-9 else angle / (2.0 * np.sin(max(angle, 1e-9)))
    out[0], out[1], out[2] = a0 * factor, a1 * factor, a2 * factor
    if angle > np.pi - 0.1:  # the axis from the symmetric part, its sign from the antisymmetric part
        best, column = -np.inf, 0
        for j in range(3):
            value = (r[j, j] - cos_angle) / (1.0 - cos_angle)
            if value > best:
                best, column = value, j
        axis = np.empty(3)
        for i in range(3):
            axis[i] = ((r[i, column] + r[column, i]) / 2.0 - (cos_angle if i == column else 0.0)) / (1.0 - cos_angle)
        norm = max(np.sqrt(axis[0] ** 2 + axis[1] ** 2 + axis[2] ** 2), 1e-12)
        sign = -1.0 if axis[0] * a0 + axis[1] * a1 + axis[2] * a2 < 0.0 else 1.0
        for i in range(3):
            out[i] = sign * axis[i] / norm * angle


@jit
def _rotation_exp(omega, out):
    """`geometry.so3_exp` of one rotation vector (3,) into out (3, 3): (1 - cos) a a^T + cos I + sin [a]_x."""
    angle = np.sqrt(omega[0] ** 2 + omega[1] ** 2 + omega[2] ** 2)
    scale = max(angle, 1e-300)
    a0, a1, a2 = omega[0] / scale, omega[1] / scale, omega[2] / scale
    c, s = np.cos(angle), np.sin(angle)
    one = 1.0 - c
    out[0, 0], out[0, 1], out[0, 2] = one * a0 * a0 + c, one * a0 * a1 - s * a2, one * a0 * a2 + s * a1
    out[1, 0], out[1, 1], out[1, 2] = one * a1 * a0 + s * a2, one * a1 * a1 + c, one * a1 * a2 - s * a0
    out[2, 0], out[2, 1], out[2, 2] = one * a2 * a0 - s * a1, one * a2 * a1 + s * a0, one * a2 * a2 + c


@jit
def _cholesky_solve(a, b, size, out):
    """out[:size] = a[:size, :size]^-1 b[:size] for a symmetric positive definite a (overwritten)."""
    for j in range(size):
        diagonal = a[j, j]
        for k in range(j):
            diagonal -= a[j, k] * a[j, k]
        a[j, j] = np.sqrt(diagonal)
        for i in range(j + 1, size):
            value = a[i, j]
            for k in range(j):
                value -= a[i, k] * a[j, k]
            a[i, j] = value / a[j, j]
    for i in range(size):  # L y = b
        value = b[i]
        for k in range(i):
            value -= a[i, k] * out[k]
        out[i] = value / a[i, i]
    for i in range(size - 1, -1, -1):  # L^T x = y
        value = out[i]
        for k in range(i + 1, size):
            value -= a[k, i] * out[k]
        out[i] = value / a[i, i]


@jit
def gauss_newton_step(
    poses,
    active,
    points,
    gaps,
    index,
    surface_points,
    surface_normals,
    facing_source,
    pivot_source,
    start_rotations,
    anchor_start,
    prior,
    noise,
    first,
    translation_only,
    step_tolerance_m,
    step_tolerance_rad,
    moving,
):
    """One damped point-to-plane Gauss-Newton step of each active pose, in place (`registration.
    point_to_plane_gauss_newton` with a pivot and one facing normal): `points` (len(active), M, 3) are its
    transformed source points, `gaps` and `index` their nearest surface points (inf gap: none within reach);
    `prior` (6,) the prior's diagonal. moving[k]: whether pose active[k] still moves (its step above tolerance)."""
    count, size = points.shape[0], points.shape[1]
    noise_squared = noise * noise
    residual = np.empty(size)
    magnitude = np.empty(size)
    used = np.empty(size, dtype=np.bool_)
    sorted_magnitudes = np.empty(size)
    jacobian = np.empty(6)
    hessian = np.empty((6, 6))
    gradient = np.empty(6)
    step = np.zeros(6)
    deviation = np.empty(6)
    relative = np.empty((3, 3))
    delta = np.empty((3, 3))
    rotation = np.empty((3, 3))
    for k in range(count):
        pose = poses[active[k]]
        facing = np.empty(3)
        centre = np.empty(3)
        for i in range(3):
            facing[i] = pose[i, 0] * facing_source[0] + pose[i, 1] * facing_source[1] + pose[i, 2] * facing_source[2]
            centre[i] = (
                pose[i, 0] * pivot_source[0] + pose[i, 1] * pivot_source[1] + pose[i, 2] * pivot_source[2] + pose[i, 3]
            )
        matched = 0
        for m in range(size):
            flat = k * size + m
            use = np.isfinite(gaps[flat])
            r = 0.0
            if use:
                j = index[flat]
                n0, n1, n2 = surface_normals[j, 0], surface_normals[j, 1], surface_normals[j, 2]
                use = n0 * facing[0] + n1 * facing[1] + n2 * facing[2] > 0.5
                if use:
                    q = surface_points[j]
                    r = (points[k, m, 0] - q[0]) * n0 + (points[k, m, 1] - q[1]) * n1 + (points[k, m, 2] - q[2]) * n2
                    sorted_magnitudes[matched] = abs(r)
                    matched += 1
            residual[m], magnitude[m], used[m] = r, abs(r), use
        median = 0.0
        if matched > 0:
            ordered = np.sort(sorted_magnitudes[:matched])
            median = 0.5 * (ordered[(matched - 1) // 2] + ordered[matched // 2])
        scale = max(noise, 1.4826 * median)
        for i in range(6):
            gradient[i] = 0.0
            for j in range(6):
                hessian[i, j] = 0.0
        for m in range(size):
            if not used[m]:
                continue
            weight = min(1.0, scale / max(magnitude[m], 1e-12)) / noise_squared
            j = index[k * size + m]
            n0, n1, n2 = surface_normals[j, 0], surface_normals[j, 1], surface_normals[j, 2]
            l0, l1, l2 = points[k, m, 0] - centre[0], points[k, m, 1] - centre[1], points[k, m, 2] - centre[2]
            jacobian[0], jacobian[1], jacobian[2] = l1 * n2 - l2 * n1, l2 * n0 - l0 * n2, l0 * n1 - l1 * n0
            jacobian[3], jacobian[4], jacobian[5] = n0, n1, n2
            for i in range(6):
                weighted = weight * jacobian[i]
                gradient[i] += weighted * residual[m]
                for j2 in range(i + 1):
                    hessian[i, j2] += weighted * jacobian[j2]
        if first:
            for i in range(6):
                deviation[i] = 0.0
        else:
            start = start_rotations[active[k]]
            for i in range(3):
                for j in range(3):
                    relative[i, j] = pose[i, 0] * start[j, 0] + pose[i, 1] * start[j, 1] + pose[i, 2] * start[j, 2]
            _rotation_log(relative, deviation[:3])
            for i in range(3):
                deviation[3 + i] = centre[i] - anchor_start[active[k], i]
        for i in range(6):
            hessian[i, i] += prior[i]
            gradient[i] = -(gradient[i] + deviation[i] * prior[i])
            for j in range(i):
                hessian[j, i] = hessian[i, j]
        for i in range(6):
            step[i] = 0.0
        if translation_only:
            _cholesky_solve(hessian[3:, 3:], gradient[3:], 3, step[3:])
        else:
            _cholesky_solve(hessian, gradient, 6, step)
        _rotation_exp(step[:3], delta)
        for i in range(3):
            for j in range(3):
                rotation[i, j] = pose[i, j]
        lever0, lever1, lever2 = pose[0, 3] - centre[0], pose[1, 3] - centre[1], pose[2, 3] - centre[2]
        for i in range(3):
            pose[i, 3] = delta[i, 0] * lever0 + delta[i, 1] * lever1 + delta[i, 2] * lever2 + centre[i] + step[3 + i]
            for j in range(3):
                pose[i, j] = delta[i, 0] * rotation[0, j] + delta[i, 1] * rotation[1, j] + delta[i, 2] * rotation[2, j]
        moving[k] = (step[3] ** 2 + step[4] ** 2 + step[5] ** 2 >= step_tolerance_m**2) or (
            step[0] ** 2 + step[1] ** 2 + step[2] ** 2 >= step_tolerance_rad**2
        )


@jit
def truncated_rms(poses, points, gaps, index, surface_points, surface_normals, facing_source, tau, out):
    """out[k]: `registration.truncated_plane_fit(...).rms_m` of the (K, M, 3) points under pose k (their nearest
    surface points `gaps`, `index`), correspondences facing the pose's `facing_source` normal."""
    count, size = points.shape[0], points.shape[1]
    for k in range(count):
        pose = poses[k]
        f0 = pose[0, 0] * facing_source[0] + pose[0, 1] * facing_source[1] + pose[0, 2] * facing_source[2]
        f1 = pose[1, 0] * facing_source[0] + pose[1, 1] * facing_source[1] + pose[1, 2] * facing_source[2]
        f2 = pose[2, 0] * facing_source[0] + pose[2, 1] * facing_source[1] + pose[2, 2] * facing_source[2]
        total = 0.0
        for m in range(size):
            flat = k * size + m
            residual = tau
            if np.isfinite(gaps[flat]):
                j = index[flat]
                n0, n1, n2 = surface_normals[j, 0], surface_normals[j, 1], surface_normals[j, 2]
                if n0 * f0 + n1 * f1 + n2 * f2 > 0.5:
                    q = surface_points[j]
                    distance = (
                        (points[k, m, 0] - q[0]) * n0 + (points[k, m, 1] - q[1]) * n1 + (points[k, m, 2] - q[2]) * n2
                    )
                    residual = min(abs(distance), tau)
            total += residual * residual
        out[k] = np.sqrt(total / size)


@jit
def free_space_depths(
    anchor_points, poses, reach, pad_x, pad_y, margin, centre, basis, half, pixel, untouched, tau, out
):
    """out[k]: `scores.free_space_violation`'s sum for pose k (T_object_sensor) before its area scaling: over the
    anchors within `reach` of the sensor, over the pad, deeper than `margin` past the gel plane and on no pixel of
    the contact image's `untouched` mask's complement, the squared depth capped at tau."""
    side = untouched.shape[0]
    reach_squared = reach * reach
    for k in range(poses.shape[0]):
        pose = poses[k]
        t0, t1, t2 = pose[0, 3], pose[1, 3], pose[2, 3]
        total = 0.0
        for a in range(anchor_points.shape[0]):
            d0, d1, d2 = anchor_points[a, 0] - t0, anchor_points[a, 1] - t1, anchor_points[a, 2] - t2
            if d0 * d0 + d1 * d1 + d2 * d2 > reach_squared:
                continue
            s0 = d0 * pose[0, 0] + d1 * pose[1, 0] + d2 * pose[2, 0]
            s1 = d0 * pose[0, 1] + d1 * pose[1, 1] + d2 * pose[2, 1]
            s2 = d0 * pose[0, 2] + d1 * pose[1, 2] + d2 * pose[2, 2]
            depth = -s2 - margin
            if not (abs(s0) <= pad_x and abs(s1) <= pad_y and depth > 0):
                continue
            e0, e1, e2 = s0 - centre[0], s1 - centre[1], s2 - centre[2]
            x = e0 * basis[0, 0] + e1 * basis[1, 0] + e2 * basis[2, 0]
            y = e0 * basis[0, 1] + e1 * basis[1, 1] + e2 * basis[2, 1]
            i = min(max(int(np.floor((x + half) / pixel - 0.5)), 0), side - 2)
            j = min(max(int(np.floor((y + half) / pixel - 0.5)), 0), side - 2)
            if untouched[i, j] and untouched[i + 1, j] and untouched[i, j + 1] and untouched[i + 1, j + 1]:
                capped = min(depth, tau)
                total += capped * capped
        out[k] = total


@jit
def sample_rolls(
    image_heights, image_mask, untouched, half, pixel, cos, sin, centres, centre, basis, pad_x, pad_y, heights, mask,
    free, gel,
):  # fmt: skip
    """`contact.contact_maps`' per-cell values at every roll (R, C), bitwise: the image's bilinear height where all
    four pixels lie in its mask (else 0), that coverage, whether the cell lies on the pad with all four pixels
    untouched, and the gel plane's height there."""
    side = image_heights.shape[0]
    for r in range(cos.shape[0]):
        for c in range(centres.shape[0]):
            x = cos[r] * centres[c, 0] + sin[r] * centres[c, 1]
            y = -sin[r] * centres[c, 0] + cos[r] * centres[c, 1]
            fx = (x + half) / pixel - 0.5
            fy = (y + half) / pixel - 0.5
            i = min(max(int(np.floor(fx)), 0), side - 2)
            j = min(max(int(np.floor(fy)), 0), side - 2)
            wx = min(max(fx - i, 0.0), 1.0)
            wy = min(max(fy - j, 0.0), 1.0)
            covered = image_mask[i, j] and image_mask[i + 1, j] and image_mask[i, j + 1] and image_mask[i + 1, j + 1]
            value = 0.0
            value += image_heights[i, j] * ((1 - wx) * (1 - wy))
            value += image_heights[i + 1, j] * (wx * (1 - wy))
            value += image_heights[i, j + 1] * ((1 - wx) * wy)
            value += image_heights[i + 1, j + 1] * (wx * wy)
            heights[r, c] = np.float32(value) if covered else np.float32(0.0)
            mask[r, c] = np.float32(1.0) if covered else np.float32(0.0)
            near = untouched[i, j] and untouched[i + 1, j] and untouched[i, j + 1] and untouched[i + 1, j + 1]
            pad0 = centre[0] + basis[0, 0] * x + basis[0, 1] * y
            pad1 = centre[1] + basis[1, 0] * x + basis[1, 1] * y
            free[r, c] = abs(pad0) <= pad_x and abs(pad1) <= pad_y and near
            gel[r, c] = np.float32(-(centre[2] + basis[2, 0] * x + basis[2, 1] * y) / basis[2, 2])


@jit
def free_space_squares(anchor_heights, anchor_valid, anchor_index, roll_index, beta, x, y, gel, free, margin, cap):
    """(K, C) float32: `scores.free_space_penalty`'s squared depths, bitwise (its float32 operations in its order)."""
    out = np.zeros((anchor_index.shape[0], x.shape[0]), dtype=np.float32)
    zero = np.float32(0.0)
    for k in range(anchor_index.shape[0]):
        a, r = anchor_index[k], roll_index[k]
        for c in range(x.shape[0]):
            if not (free[r, c] and anchor_valid[a, c] > 0):
                continue
            surface = anchor_heights[a, c] + beta[0, k] + beta[1, k] * x[c] + beta[2, k] * y[c]
            depth = max(min(gel[r, c] - margin - surface, cap), zero)
            out[k, c] = depth * depth
    return out


@jit
def best_plane_costs(sums, height_sums, squared_sums, total, air_squared):
    """Per anchor, `scores.plane_costs` (with tilt) at its best roll, bitwise: its float32 arithmetic on the products
    it forms (`sums` (10 R, A): the mask's moments and the contact's height sums against the anchors' validity,
    `height_sums` (4 R, A) against their heights, `squared_sums` (R, A) against their squares; `total` (R,) each
    roll's covered cells). Returns the first best roll (R,) as `np.argmin`, its cost and plane (3, A)."""
    rolls, count = squared_sums.shape
    best_roll = np.zeros(count, dtype=np.int64)
    best_cost = np.empty(count, dtype=np.float32)
    best_beta = np.empty((3, count), dtype=np.float32)
    one, zero, two = np.float32(1.0), np.float32(0.0), np.float32(2.0)
    for a in range(count):
        for r in range(rolls):
            n, sx, sy = sums[r, a], sums[rolls + r, a], sums[2 * rolls + r, a]
            sxx, sxy, syy = sums[3 * rolls + r, a], sums[4 * rolls + r, a], sums[5 * rolls + r, a]
            st, stx, sty, stt = (
                sums[6 * rolls + r, a],
                sums[7 * rolls + r, a],
                sums[8 * rolls + r, a],
                sums[9 * rolls + r, a],
            )
            sh, shx, shy = height_sums[r, a], height_sums[rolls + r, a], height_sums[2 * rolls + r, a]
            sth = height_sums[3 * rolls + r, a]
            b0, b1, b2 = st - sh, stx - shx, sty - shy
            sdd = stt - two * sth + squared_sums[r, a]
            c00, c01, c02 = sxx * syy - sxy * sxy, sy * sxy - sx * syy, sx * sxy - sy * sxx
            c11, c12, c22 = n * syy - sy * sy, sx * sy - n * sxy, n * sxx - sx * sx
            det = n * c00 + sx * c01 + sy * c02
            spread = sxx + syy
            solvable = n >= 6 and det > np.float32(1e-2) * n * spread * spread / np.float32(4.0)
            inv = one / det if solvable else zero
            beta0 = (c00 * b0 + c01 * b1 + c02 * b2) * inv
            beta1 = (c01 * b0 + c11 * b1 + c12 * b2) * inv
            beta2 = (c02 * b0 + c12 * b1 + c22 * b2) * inv
            safe_n = max(n, one)
            if solvable:
                sse = sdd - (beta0 * b0 + beta1 * b1 + beta2 * b2)
            else:
                sse = sdd - b0 * b0 / safe_n
                beta0 = b0 / safe_n
            cost = (max(sse, zero) + air_squared * (total[r] - n)) / max(total[r], one)
            if r == 0 or cost < best_cost[a]:
                best_roll[a], best_cost[a] = r, cost
                best_beta[0, a], best_beta[1, a], best_beta[2, a] = beta0, beta1, beta2
    return best_roll, best_cost, best_beta


KERNELS = (
    SimpleNamespace(
        transform_active=transform_active,
        gauss_newton_step=gauss_newton_step,
        truncated_rms=truncated_rms,
        free_space_depths=free_space_depths,
        sample_rolls=sample_rolls,
        free_space_squares=free_space_squares,
        best_plane_costs=best_plane_costs,
    )
    if ENABLED
    else None
)
