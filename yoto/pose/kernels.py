"""Compiled loops for the pose stage's hottest work (numba, the `fast` extra), with numpy as the fallback.

`KERNELS` is None where numba is missing (or `YOTO_NO_NUMBA=1` is set); callers then take their numpy path.
The loops repeat the numpy paths' arithmetic in their precision (no fastmath) without their temporaries: the
field read (`field.SurfaceField.distance`) in the same order, bitwise the same numbers; the refinement's
Gauss-Newton system (`refine._add_normal_equations`) summed point by point, equal to ~1e-12 relative; the whole
iteration loop of `refine.refine_hypotheses` (the system, its solve by Cholesky, the SE(3) updates, the same
stopping rule), its final fit (`refine.evaluate_fit`) and the seeds' cheap score (`refine.evaluate_offsets`), pose
by pose. Compiled through `yoto.jit` (cached on disk: only the first process after an install pays the compile,
~12 s of CPU)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from yoto.jit import ENABLED as _ENABLED
from yoto.jit import jit as _jit


@_jit
def field_read(flat, nx, ny, nz, origin, inverse_cell, band, points, distance, normal, with_gradient):
    """Trilinear signed distance (and outward unit normal) of a (nx, ny, nz) float32 grid, flattened, at
    (N, 3) points; the float32 operations of `SurfaceField.distance`'s numpy path, in its order."""
    sx, sy = ny * nz, nz
    tiny = np.float32(1e-12)
    for p in range(points.shape[0]):
        gxf = np.float32((points[p, 0] - origin[0]) * inverse_cell)
        gyf = np.float32((points[p, 1] - origin[1]) * inverse_cell)
        gzf = np.float32((points[p, 2] - origin[2]) * inverse_cell)
        bx, by, bz = np.floor(gxf), np.floor(gyf), np.floor(gzf)
        fx, fy, fz = gxf - bx, gyf - by, gzf - bz
        # outside the grid's cells (NaN fails every test too): never a match
        if not (bx >= 0 and by >= 0 and bz >= 0 and bx <= nx - 2 and by <= ny - 2 and bz <= nz - 2):
            distance[p] = band
            if with_gradient:
                normal[p, 0] = 0.0
                normal[p, 1] = 0.0
                normal[p, 2] = 0.0
            continue
        base = int(bx) * sx + int(by) * sy + int(bz)
        c000, c001 = flat[base], flat[base + 1]
        c010, c011 = flat[base + sy], flat[base + sy + 1]
        c100, c101 = flat[base + sx], flat[base + sx + 1]
        c110, c111 = flat[base + sx + sy], flat[base + sx + sy + 1]
        s00, s01, s10, s11 = c001 - c000, c011 - c010, c101 - c100, c111 - c110
        z00, z01, z10, z11 = c000 + fz * s00, c010 + fz * s01, c100 + fz * s10, c110 + fz * s11
        y0, y1 = z01 - z00, z11 - z10
        a0, a1 = z00 + fy * y0, z10 + fy * y1
        gx = a1 - a0
        distance[p] = np.float64(a0 + fx * gx)
        if with_gradient:
            gy = y0 + fx * (y1 - y0)
            d0, d1 = s00 + fy * (s01 - s00), s10 + fy * (s11 - s10)
            gz = d0 + fx * (d1 - d0)
            norm = np.sqrt(gx * gx + gy * gy + gz * gz)
            scale = np.float32(1.0) / max(norm, tiny) if norm > tiny else np.float32(0.0)
            normal[p, 0] = np.float64(gx * scale)
            normal[p, 1] = np.float64(gy * scale)
            normal[p, 2] = np.float64(gz * scale)


@_jit
def select(values, count, rank):
    """The `rank`-th smallest of values[:count] (0: the least), by Hoare's quickselect in place: afterwards
    values[:rank] hold the smaller ones (in no order)."""
    low, high = 0, count - 1
    while low < high:
        pivot = values[(low + high) // 2]
        i, j = low, high
        while i <= j:
            while values[i] < pivot:
                i += 1
            while values[j] > pivot:
                j -= 1
            if i <= j:
                values[i], values[j] = values[j], values[i]
                i += 1
                j -= 1
        if rank <= j:
            high = j
        elif rank >= i:
            low = i
        else:
            break
    return values[rank]


@_jit
def add_normal_equations(
    flat,
    nx,
    ny,
    nz,
    origin,
    inverse_cell,
    band,
    A,
    points,
    z_scale,
    max_distance,
    noise,
    weight_scale,
    side,
    scale_row,
    hessian,
    gradient,
):
    """Add one contact's robustly weighted point-to-surface normal equations under K poses A (K, 4, 4) (object
    <- sensor) of its (M, 3) sensor-frame points, heights scaled by z_scale (K,), into hessian (K, S, S) and
    gradient (K, S): the object pose's rows 0-5, its sensor's correction's rows side..side + 5, its log depth
    scale's row scale_row (< 0: none). `refine._add_normal_equations` in one pass (its numpy path explains
    the algebra)."""
    count = points.shape[0]
    q = np.empty((count, 3))
    r = np.empty(count)
    n = np.empty((count, 3))
    used = np.empty(count)
    jacobian = np.empty((count, 8))  # each used point's row a (n x q, -n), its residual, its d r / d log s
    weight = np.empty(count)
    sums = np.empty((7, 8))  # rows 0-5: a^T W a, a^T W r, a^T W j; row 6: W j^2, W j r
    adjoint = np.zeros((6, 6))  # M = [[-R^T, R^T [t]x], [0, -R^T]]
    coupled = np.empty((6, 8))  # M [B, g, a^T W j]
    for k in range(A.shape[0]):
        for m in range(count):
            x, y, z = points[m, 0], points[m, 1], points[m, 2] * z_scale[k]
            for i in range(3):
                q[m, i] = x * A[k, i, 0] + y * A[k, i, 1] + z * A[k, i, 2] + A[k, i, 3]
        field_read(flat, nx, ny, nz, origin, inverse_cell, band, q, r, n, True)
        kept = 0
        for m in range(count):
            if abs(r[m]) < max_distance:
                used[kept] = abs(r[m])
                kept += 1
        median = 0.0
        if kept > 0:  # the middle one or two of the kept magnitudes (selected in place, not sorted: the same values)
            half = kept // 2
            upper = select(used, kept, half)
            median = upper if kept % 2 else 0.5 * (used[:half].max() + upper)
        scale = max(noise, 1.4826 * median)
        rows = 0
        for m in range(count):
            magnitude = abs(r[m])
            if not magnitude < max_distance:
                continue
            w = min(1.0, scale / max(magnitude, 1e-12)) * weight_scale
            a = jacobian[rows]
            a[0] = n[m, 1] * q[m, 2] - n[m, 2] * q[m, 1]
            a[1] = n[m, 2] * q[m, 0] - n[m, 0] * q[m, 2]
            a[2] = n[m, 0] * q[m, 1] - n[m, 1] * q[m, 0]
            a[3], a[4], a[5] = -n[m, 0], -n[m, 1], -n[m, 2]
            a[6] = r[m]
            height = points[m, 2] * z_scale[k]
            a[7] = (n[m, 0] * A[k, 0, 2] + n[m, 1] * A[k, 1, 2] + n[m, 2] * A[k, 2, 2]) * height
            weight[rows] = w
            rows += 1
        for i in range(6):  # row by row, its 8 sums in registers (each summed in the points' order)
            s0, s1, s2, s3, s4, s5, s6, s7 = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
            for m in range(rows):
                a = jacobian[m]
                wi = a[i] * weight[m]
                s0 += wi * a[0]
                s1 += wi * a[1]
                s2 += wi * a[2]
                s3 += wi * a[3]
                s4 += wi * a[4]
                s5 += wi * a[5]
                s6 += wi * a[6]
                s7 += wi * a[7]
            sums[i, 0], sums[i, 1], sums[i, 2], sums[i, 3] = s0, s1, s2, s3
            sums[i, 4], sums[i, 5], sums[i, 6], sums[i, 7] = s4, s5, s6, s7
        s0, s1 = 0.0, 0.0
        for m in range(rows):
            a = jacobian[m]
            s0 += weight[m] * a[7] * a[7]
            s1 += weight[m] * a[7] * a[6]
        sums[6, 0], sums[6, 1] = s0, s1
        tx, ty, tz = A[k, 0, 3], A[k, 1, 3], A[k, 2, 3]
        for i in range(3):
            for j in range(3):
                adjoint[i, j] = adjoint[3 + i, 3 + j] = -A[k, j, i]
            adjoint[i, 3] = A[k, 1, i] * tz - A[k, 2, i] * ty  # (R^T [t]x)[i, :]
            adjoint[i, 4] = A[k, 2, i] * tx - A[k, 0, i] * tz
            adjoint[i, 5] = A[k, 0, i] * ty - A[k, 1, i] * tx
        for i in range(6):
            for j in range(8):
                total = 0.0
                for m in range(6):
                    total += adjoint[i, m] * sums[m, j]
                coupled[i, j] = total
        for i in range(6):
            gradient[k, i] += sums[i, 6]
            gradient[k, side + i] += coupled[i, 6]
            for j in range(6):
                hessian[k, i, j] += sums[i, j]
                hessian[k, i, side + j] += coupled[j, i]
                hessian[k, side + i, j] += coupled[i, j]
                total = 0.0
                for m in range(6):
                    total += coupled[i, m] * adjoint[j, m]
                hessian[k, side + i, side + j] += total
        if scale_row >= 0:
            for i in range(6):
                hessian[k, i, scale_row] += sums[i, 7]
                hessian[k, scale_row, i] += sums[i, 7]
                hessian[k, side + i, scale_row] += coupled[i, 7]
                hessian[k, scale_row, side + i] += coupled[i, 7]
            hessian[k, scale_row, scale_row] += sums[6, 0]
            gradient[k, scale_row] += sums[6, 1]


@_jit
def se3_exp_into(xi, out):
    """out (4, 4) = exp(xi) for one twist xi (6,) = (omega, rho): `geometry.se3_exp`'s arithmetic, per element."""
    w0, w1, w2 = xi[0], xi[1], xi[2]
    angle = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    unit = max(angle, 1e-300)
    x, y, z = w0 / unit, w1 / unit, w2 / unit
    cos_angle, sin_angle = np.cos(angle), np.sin(angle)
    c = 1.0 - cos_angle
    out[0, 0], out[0, 1], out[0, 2] = c * x * x + cos_angle, c * x * y - sin_angle * z, c * x * z + sin_angle * y
    out[1, 0], out[1, 1], out[1, 2] = c * y * x + sin_angle * z, c * y * y + cos_angle, c * y * z - sin_angle * x
    out[2, 0], out[2, 1], out[2, 2] = c * z * x - sin_angle * y, c * z * y + sin_angle * x, c * z * z + cos_angle
    if angle < 1e-2:  # the series where the differences cancel
        square = angle * angle
        a = 0.5 - square / 24.0 + square * square / 720.0
        b = 1.0 / 6.0 - square / 120.0 + square * square / 5040.0
    else:
        a = (1.0 - cos_angle) / angle**2
        b = (angle - sin_angle) / angle**3
    r0, r1, r2 = xi[3], xi[4], xi[5]
    u0, u1, u2 = w1 * r2 - w2 * r1, w2 * r0 - w0 * r2, w0 * r1 - w1 * r0  # omega x rho
    v0, v1, v2 = w1 * u2 - w2 * u1, w2 * u0 - w0 * u2, w0 * u1 - w1 * u0  # omega x (omega x rho)
    out[0, 3], out[1, 3], out[2, 3] = r0 + a * u0 + b * v0, r1 + a * u1 + b * v1, r2 + a * u2 + b * v2
    out[3, 0], out[3, 1], out[3, 2], out[3, 3] = 0.0, 0.0, 0.0, 1.0


@_jit
def compose_into(first, second, out):
    """out (4, 4) = first @ second for rigid 4 x 4 poses (out may be neither)."""
    for i in range(3):
        for j in range(4):
            out[i, j] = first[i, 0] * second[0, j] + first[i, 1] * second[1, j] + first[i, 2] * second[2, j]
        out[i, 3] += first[i, 3]
    out[3, 0], out[3, 1], out[3, 2], out[3, 3] = 0.0, 0.0, 0.0, 1.0


@_jit
def sensor_poses(poses, T_world_sensor, corrections, depth_scale, scaled, A, z_scale):
    """A (K, 4, 4) = poses^-1 T_world_sensor corrections (object <- sensor, as numpy's inverse and two products
    compute it) of K poses (K, 4, 4) and one sensor's corrections (K, 4, 4); z_scale (K,) = depth_scale (K,) where
    the contact's heights are `scaled`, else 1."""
    T_object_world = np.empty((4, 4))
    T_object_sensor = np.empty((4, 4))
    for k in range(poses.shape[0]):
        for i in range(3):  # the inverse pose [R^T | -R^T t]
            for j in range(3):
                T_object_world[i, j] = poses[k, j, i]
        for i in range(3):
            T_object_world[i, 3] = -(
                T_object_world[i, 0] * poses[k, 0, 3]
                + T_object_world[i, 1] * poses[k, 1, 3]
                + T_object_world[i, 2] * poses[k, 2, 3]
            )
        compose_into(T_object_world, T_world_sensor, T_object_sensor)
        compose_into(T_object_sensor, corrections[k], A[k])
        z_scale[k] = depth_scale[k] if scaled else 1.0


@_jit
def solve_into(matrix, rhs, out, work):
    """out = matrix^-1 rhs for one symmetric (S, S) system (matrix left alone; work (S, S)): by Cholesky where
    the matrix is positive definite, else by Gaussian elimination with partial pivoting (what LAPACK's LU, numpy's
    solve, does there). False where the matrix is singular (an exact zero pivot)."""
    size = matrix.shape[0]
    work[:] = matrix
    positive = True
    for j in range(size):  # the lower triangle becomes L (matrix = L L^T)
        total = work[j, j]
        for m in range(j):
            total -= work[j, m] * work[j, m]
        if not total > 0.0:
            positive = False
            break
        diagonal = np.sqrt(total)
        work[j, j] = diagonal
        for i in range(j + 1, size):
            total = work[i, j]
            for m in range(j):
                total -= work[i, m] * work[j, m]
            work[i, j] = total / diagonal
    if positive:
        for i in range(size):  # L y = rhs, then L^T out = y
            total = rhs[i]
            for m in range(i):
                total -= work[i, m] * out[m]
            out[i] = total / work[i, i]
        for i in range(size - 1, -1, -1):
            total = out[i]
            for m in range(i + 1, size):
                total -= work[m, i] * out[m]
            out[i] = total / work[i, i]
        return True
    work[:] = matrix
    out[:] = rhs
    for j in range(size):
        pivot = j
        for i in range(j + 1, size):
            if abs(work[i, j]) > abs(work[pivot, j]):
                pivot = i
        if work[pivot, j] == 0.0:
            return False
        if pivot != j:
            for m in range(size):
                work[j, m], work[pivot, m] = work[pivot, m], work[j, m]
            out[j], out[pivot] = out[pivot], out[j]
        for i in range(j + 1, size):
            factor = work[i, j] / work[j, j]
            for m in range(j, size):
                work[i, m] -= factor * work[j, m]
            out[i] -= factor * out[j]
    for i in range(size - 1, -1, -1):
        total = out[i]
        for m in range(i + 1, size):
            total -= work[i, m] * out[m]
        out[i] = total / work[i, i]
    return True


@_jit
def refine_loop(
    flat,
    nx,
    ny,
    nz,
    origin,
    inverse_cell,
    band,
    points,
    starts,
    T_world_sensor,
    sensor,
    scale_row,
    information,
    poses,
    corrections,
    deviation,
    log_scale,
    iterations,
    tolerance,
    max_distance,
    noise,
    weight_scale,
):
    """`refine.refine_hypotheses`' Gauss-Newton iterations for K poses (K, 4, 4) and their sensors' corrections
    (K, 2, 4, 4), updated in place with the accumulated twists `deviation` (K, S) and each contact's log depth
    scale (K, C): per iteration the clouds' normal equations (`add_normal_equations`) over the prior
    `information` (S, S), each pose's damped system solved (`solve_into`), its step applied through the SE(3)
    exponential; stops after the first iteration whose every step is below `tolerance`. Contact c holds
    points[starts[c]:starts[c + 1]] (sensor frame), seen by sensor[c] at T_world_sensor[c], its log depth scale's
    row scale_row[c] (< 0: its heights exact). Returns the iterations run, or -1 where a system was singular."""
    count, size = poses.shape[0], information.shape[0]
    hessian = np.empty((count, size, size))
    gradient = np.empty((count, size))
    A = np.empty((count, 4, 4))
    z_scale = np.empty(count)
    step = np.empty(size)
    rhs = np.empty(size)
    work = np.empty((size, size))
    update = np.empty((4, 4))
    moved = np.empty((4, 4))
    for iteration in range(iterations):
        for k in range(count):
            hessian[k] = information
            for j in range(size):
                total = 0.0
                for i in range(size):
                    total += deviation[k, i] * information[i, j]
                gradient[k, j] = total
        for c in range(T_world_sensor.shape[0]):
            s = sensor[c]
            depth_scale = np.exp(log_scale[:, c])
            sensor_poses(poses, T_world_sensor[c], corrections[:, s], depth_scale, scale_row[c] >= 0, A, z_scale)
            add_normal_equations(
                flat,
                nx,
                ny,
                nz,
                origin,
                inverse_cell,
                band,
                A,
                points[starts[c] : starts[c + 1]],
                z_scale,
                max_distance,
                noise,
                weight_scale,
                6 + 6 * s,
                scale_row[c],
                hessian,
                gradient,
            )
        largest = 0.0
        for k in range(count):
            for i in range(size):
                rhs[i] = -gradient[k, i]
            if not solve_into(hessian[k], rhs, step, work):
                return -1
            for i in range(size):
                deviation[k, i] += step[i]
                largest = max(largest, abs(step[i]))  # NaN steps never stop the iterations (as numpy's max)
                if step[i] != step[i]:
                    largest = np.inf
            se3_exp_into(step[0:6], update)
            compose_into(poses[k], update, moved)
            poses[k] = moved
            for side in range(2):
                se3_exp_into(step[6 + 6 * side : 12 + 6 * side], update)
                compose_into(corrections[k, side], update, moved)
                corrections[k, side] = moved
            for c in range(T_world_sensor.shape[0]):
                if scale_row[c] >= 0:
                    log_scale[k, c] += step[scale_row[c]]
        if largest < tolerance:
            return iteration + 1
    return iterations


@_jit
def fit_scores(
    flat, nx, ny, nz, origin, inverse_cell, band, A, points, z_scale, free, tau, inlier, free_tau, skirt_tau, out
):
    """`refine.evaluate_fit` for one contact under K poses A (K, 4, 4) (object <- sensor, its correction
    included): out (K, 3) = truncated RMS residual, inlier fraction and free-space RMS depth of its (M, 3) points,
    heights scaled by z_scale (K,), and its (F, 3) free-space points (as they are). skirt_tau >= 0: a point outside
    the object, no deeper than the deepest point touching it (within `inlier`), whose pad-plane foot (its x, y at
    height 0) lies more than skirt_tau outside too counts at most skirt_tau (the gel's skirt,
    `RefineConfig.skirt_tau_m`)."""
    count, spare = points.shape[0], free.shape[0]
    q = np.empty((count + spare, 3))
    distance = np.empty(count + spare)
    normal = np.empty((0, 3))
    outside = np.empty(count, dtype=np.int64)
    foot = np.empty((count, 3))
    foot_distance = np.empty(count)
    limit = np.empty(count)  # each point's truncation
    for k in range(A.shape[0]):
        for m in range(count + spare):
            if m < count:
                x, y, z = points[m, 0], points[m, 1], points[m, 2] * z_scale[k]
            else:
                x, y, z = free[m - count, 0], free[m - count, 1], free[m - count, 2]
            for i in range(3):
                q[m, i] = x * A[k, i, 0] + y * A[k, i, 1] + z * A[k, i, 2] + A[k, i, 3]
        field_read(flat, nx, ny, nz, origin, inverse_cell, band, q, distance, normal, False)
        feet = 0
        if skirt_tau >= 0.0:
            deepest = -np.inf  # the deepest point touching the object (height z: below the pad plane, negative)
            for m in range(count):
                if abs(distance[m]) < inlier:
                    deepest = max(deepest, -points[m, 2] * z_scale[k])
            for m in range(count):
                if distance[m] > 0.0 and -points[m, 2] * z_scale[k] <= deepest:
                    for i in range(3):
                        foot[feet, i] = points[m, 0] * A[k, i, 0] + points[m, 1] * A[k, i, 1] + A[k, i, 3]
                    outside[feet] = m
                    feet += 1
            field_read(flat, nx, ny, nz, origin, inverse_cell, band, foot[:feet], foot_distance, normal, False)
        limit[:] = tau
        for f in range(feet):
            if foot_distance[f] > skirt_tau:
                limit[outside[f]] = skirt_tau
        squares, inside = 0.0, 0
        for m in range(count):
            magnitude = abs(distance[m])
            squares += min(magnitude, limit[m]) ** 2
            inside += magnitude < inlier
        out[k, 0] = np.sqrt(squares / count) if count else np.nan  # numpy's mean of nothing
        out[k, 1] = inside / count if count else np.nan
        squares = 0.0
        for m in range(count, count + spare):
            squares += min(max(-distance[m], 0.0), free_tau) ** 2
        out[k, 2] = np.sqrt(squares / spare) if spare else 0.0


@_jit
def fit_all(
    flat,
    nx,
    ny,
    nz,
    origin,
    inverse_cell,
    band,
    points,
    starts,
    free,
    free_starts,
    T_world_sensor,
    sensor,
    poses,
    corrections,
    depth_scale,
    scaled,
    tau,
    inlier,
    free_tau,
    skirt_tau,
    out,
):
    """`fit_scores` of every contact (packed as for `refine_loop`, its free-space points free[free_starts[c]:
    free_starts[c + 1]]) under K poses (K, 4, 4) and their sensors' corrections (K, 2, 4, 4), each contact's
    heights scaled by depth_scale[:, c] where scaled[c]: out (C, K, 3)."""
    count = poses.shape[0]
    A = np.empty((count, 4, 4))
    z_scale = np.empty(count)
    for c in range(T_world_sensor.shape[0]):
        sensor_poses(poses, T_world_sensor[c], corrections[:, sensor[c]], depth_scale[:, c], scaled[c], A, z_scale)
        fit_scores(
            flat,
            nx,
            ny,
            nz,
            origin,
            inverse_cell,
            band,
            A,
            points[starts[c] : starts[c + 1]],
            z_scale,
            free[free_starts[c] : free_starts[c + 1]],
            tau,
            inlier,
            free_tau,
            skirt_tau,
            out[c],
        )


@_jit
def offset_scores(
    flat,
    nx,
    ny,
    nz,
    origin,
    inverse_cell,
    band,
    A,
    points,
    free,
    design,
    fitter,
    tau,
    max_distance,
    truncated,
    noise,
    offset_std,
    tilt_std,
    free_noise,
    free_tau,
    score,
):
    """Subtract one contact's share of `refine.evaluate_offsets`' score from score (K,) under K poses A (K, 4, 4)
    (object <- sensor): its (V, 3) points' signed distances less the plane fitted to them (`design` (V, 3): the
    plane's design [1, x - mean x, y - mean y], `fitter` (3, V): its pseudo-inverse), the plane's offset and tilt
    under their priors, and its (F, 3) free-space points' depth inside the object beyond the plane's offset."""
    count, spare = points.shape[0], free.shape[0]
    q = np.empty((count + spare, 3))
    distance = np.empty(count + spare)
    normal = np.empty((0, 3))
    for k in range(A.shape[0]):
        for m in range(count + spare):
            source = points[m] if m < count else free[m - count]
            for i in range(3):
                q[m, i] = source[0] * A[k, i, 0] + source[1] * A[k, i, 1] + source[2] * A[k, i, 2] + A[k, i, 3]
        field_read(flat, nx, ny, nz, origin, inverse_cell, band, q, distance, normal, False)
        offset, tilt_x, tilt_y = 0.0, 0.0, 0.0
        for m in range(count):
            offset += distance[m] * fitter[0, m]
            tilt_x += distance[m] * fitter[1, m]
            tilt_y += distance[m] * fitter[2, m]
        squares = 0.0
        for m in range(count):
            plane = offset * design[m, 0] + tilt_x * design[m, 1] + tilt_y * design[m, 2]
            residual = min(abs(distance[m] - plane), tau)
            if truncated and abs(distance[m]) >= max_distance:
                residual = tau
            squares += residual * residual
        spread = np.sqrt(squares / count)
        score[k] -= 0.5 * ((spread / noise) ** 2 + (offset / offset_std) ** 2 + (tilt_x**2 + tilt_y**2) / tilt_std**2)
        if spare:
            squares = 0.0
            for m in range(count, count + spare):
                depth = min(max(offset - distance[m], 0.0), free_tau)
                squares += depth * depth
            score[k] -= 0.5 * (squares / spare) / free_noise**2


KERNELS = (
    SimpleNamespace(
        field_read=field_read,
        select=select,
        add_normal_equations=add_normal_equations,
        se3_exp_into=se3_exp_into,
        solve_into=solve_into,
        refine_loop=refine_loop,
        fit_all=fit_all,
        offset_scores=offset_scores,
    )
    if _ENABLED
    else None
)


# The joint search's key test (`search.key_matches`): appended after the pose stage's kernels above.

KEY_SLACK = 1e-6  # the compiled key test keeps pairs within (1 + this) tolerances, tested without an arccos: numpy's
# exact test (`search.key_matches`) then decides on what it keeps


@_jit
def _angle_may_fit(cosine, cosine_key, sine_key, variance):
    """Whether an angle arccos(`cosine`) may lie within (1 + KEY_SLACK) sqrt(`variance`) of the key angle (its
    cosine and sine given): cos(angle - key) >= cos(tolerance) >= 1 - tolerance^2 / 2, a test that never rejects an
    angle that fits (by 1e-9 of rounding), without an arccos."""
    reach2 = variance * (1.0 + KEY_SLACK) ** 2
    if reach2 >= np.pi * np.pi:
        return True
    cosine = min(max(cosine, -1.0), 1.0)
    turned = cosine * cosine_key + np.sqrt(max(1.0 - cosine * cosine, 0.0)) * sine_key
    return turned >= 1.0 - 0.5 * reach2 - 1e-9


@_jit
def key_candidates(
    partial,
    low,
    high,
    squared_left,
    p_left,
    p_right,
    n_left,
    n_right,
    own_left,
    own_right,
    left_variance,
    right_turn2,
    left_blur,
    right_blur,
    angles,
    separation,
    distance_tolerance,
    right_angle_variance,
    min_separation,
    first_row,
    found,
):
    """The flat indices into `partial` ((rows, R): [pL, 1] . [-2 pR, |pR|^2] of left locations `first_row` on, as
    `search.key_matches` forms it) of the pairs in the separation shell [low, high] whose key may fit (within
    1 + KEY_SLACK tolerances), in row order, written to `found`; returns how many. The same terms as
    `key_matches`'s numpy path (per left and right location: blurs, the left's angle variance, the right's turn;
    the right contact's angle variance), each test a superset of numpy's: numpy's exact test runs on what it keeps."""
    rows, columns = partial.shape
    slack2 = (1.0 + KEY_SLACK) ** 2
    least = max(separation, 1e-3)
    cosines, sines = np.cos(angles), np.sin(angles)
    tolerance2 = distance_tolerance * distance_tolerance
    shell = np.empty(columns, dtype=np.int64)
    count = 0
    for r in range(rows):
        i = first_row + r
        lo, hi = low[i], high[i]
        within = 0
        for j in range(columns):  # the row's pairs in the shell, without a branch per pair
            value = partial[r, j]
            shell[within] = j
            within += (value >= lo) & (value <= hi)
        for k in range(within):
            j = shell[k]
            value = partial[r, j]
            # (nL, nR)
            cosine = n_left[0, i] * n_right[0, j] + n_left[1, i] * n_right[1, j] + n_left[2, i] * n_right[2, j]
            if not _angle_may_fit(cosine, cosines[2], sines[2], left_variance[i] + right_turn2[j]):
                continue
            # separation
            distance = np.sqrt(max(value + squared_left[i], 0.0))
            blur = left_blur[i] + right_blur[j]
            gap = distance - separation
            if distance < min_separation or gap * gap > slack2 * (tolerance2 + blur * blur):
                continue
            turn = blur / least
            turn2 = turn * turn
            length = max(distance, 1e-12)
            # (d, nL) and (d, nR)
            dot = p_right[0, j] * n_left[0, i] + p_right[1, j] * n_left[1, i] + p_right[2, j] * n_left[2, i]
            if not _angle_may_fit((dot - own_left[i]) / length, cosines[0], sines[0], left_variance[i] + turn2):
                continue
            dot = p_left[0, i] * n_right[0, j] + p_left[1, i] * n_right[1, j] + p_left[2, i] * n_right[2, j]
            variance = right_angle_variance + right_turn2[j] + turn2
            if not _angle_may_fit((own_right[j] - dot) / length, cosines[1], sines[1], variance):
                continue
            found[count] = r * columns + j
            count += 1
    return count


@_jit
def group_founders(
    order, position, moved, others, group, translation_limit, least_cosine, trace_cosine, unassigned, row, state, out
):
    """The greedy grouping of K poses into hypotheses (`hypotheses.group_hypotheses`): in `order`, each pose still
    `unassigned` founds a hypothesis and takes every unassigned pose within `translation_limit` of its `position`
    (K, 3) whose rotation's cosine to it (modulo symmetry, the largest over the founder's `group` rows of `moved`
    dotted with the other's row of `others`; a trace's (t - 1) / 2 where `trace_cosine`, no rotation test where
    `group` is 0) is at least `least_cosine`. Only founders' rows are computed, and only against unassigned poses.
    A founder whose row holds a cosine within 1e-9 of the limit stops the loop: it returns that founder with `row`
    (K,) marking 1 (joins), 0 (not), 2 (to decide by the angle itself); the caller writes 0 or 1 there and calls
    again, and the loop takes that row as it is. `state`: [position in `order`, a decided row waiting, founders
    so far]; `out` (2, K): each founder and how many poses it took. Returns -1 when all are grouped."""
    count, width = others.shape
    while state[0] < count:
        k = order[state[0]]
        if not unassigned[k]:
            state[0] += 1
            continue
        if state[1] == 0:
            undecided = False
            for j in range(count):
                code = 0
                if j == k:
                    code = 1
                elif unassigned[j]:
                    gx = position[k, 0] - position[j, 0]
                    gy = position[k, 1] - position[j, 1]
                    gz = position[k, 2] - position[j, 2]
                    if np.sqrt(gx * gx + gy * gy + gz * gz) <= translation_limit:
                        code = 1
                        if group:
                            best = -np.inf
                            for g in range(k * group, (k + 1) * group):
                                inner = 0.0
                                for c in range(width):
                                    inner += moved[g, c] * others[j, c]
                                best = max(best, inner)
                            cosine = (best - 1.0) / 2.0 if trace_cosine else best
                            if abs(cosine - least_cosine) <= 1e-9:
                                code = 2
                                undecided = True
                            elif cosine < least_cosine:
                                code = 0
                row[j] = code
            if undecided:
                state[1] = 1
                return k
        taken = 0
        for j in range(count):
            if row[j] == 1 and unassigned[j]:
                unassigned[j] = False
                taken += 1
        out[0, state[2]] = k
        out[1, state[2]] = taken
        state[1] = 0
        state[2] += 1
        state[0] += 1
    return -1


SEARCH_KERNELS = (  # the search's key test and the grouping of its refined poses
    SimpleNamespace(key_candidates=key_candidates, group_founders=group_founders) if _ENABLED else None
)
