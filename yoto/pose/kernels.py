"""Compiled loops for the pose stage's hottest work (numba, the `fast` extra), with numpy as the fallback.

`KERNELS` is None where numba is missing (or `YOTO_NO_NUMBA=1` is set); callers then take their numpy path.
The loops repeat the numpy paths' arithmetic in their precision (no fastmath) without their temporaries: the
field read (`field.SurfaceField.distance`) in the same order, bitwise the same numbers; the refinement's
Gauss-Newton system (`refine._add_normal_equations`) summed point by point, equal to ~1e-12 relative. Compiled
code is cached on disk (`cache=True`: next to this module, or under NUMBA_CACHE_DIR / the user's cache folder where
the package is read-only), so only the first process after an install pays the compile (~6 s of CPU).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np

_jit: Callable[[Any], Any] | None = None  # numba's njit where it is installed and not switched off
if os.environ.get("YOTO_NO_NUMBA", "") in ("", "0"):
    try:
        import numba

        _jit = numba.njit(cache=True, nogil=True)  # module-level functions: the on-disk cache finds them again
    except ImportError:  # the numpy paths
        pass
_ENABLED = _jit is not None
if _jit is None:
    _jit = lambda function: function  # noqa: E731 (plain Python, never called: callers take their numpy paths)


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
    a = np.empty(8)
    sums = np.empty((7, 8))  # rows 0-5: a^T W a, a^T W r, a^T W j; row 6: W j^2, W j r
    adjoint = np.zeros((6, 6))  # M = [[-R^T, R^T [t]x], [0, -R^T]]
    coupled = np.empty((6, 8))  # M [B, g, a^T W j]
    for k in range(A.shape[0]):
        sums[:] = 0.0
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
        for m in range(count):
            magnitude = abs(r[m])
            if not magnitude < max_distance:
                continue
            w = min(1.0, scale / max(magnitude, 1e-12)) * weight_scale
            a[0] = n[m, 1] * q[m, 2] - n[m, 2] * q[m, 1]
            a[1] = n[m, 2] * q[m, 0] - n[m, 0] * q[m, 2]
            a[2] = n[m, 0] * q[m, 1] - n[m, 1] * q[m, 0]
            a[3], a[4], a[5] = -n[m, 0], -n[m, 1], -n[m, 2]
            a[6] = r[m]
            height = points[m, 2] * z_scale[k]
            a[7] = (n[m, 0] * A[k, 0, 2] + n[m, 1] * A[k, 1, 2] + n[m, 2] * A[k, 2, 2]) * height
            for i in range(6):
                wi = a[i] * w
                for j in range(8):
                    sums[i, j] += wi * a[j]
            sums[6, 0] += w * a[7] * a[7]
            sums[6, 1] += w * a[7] * a[6]
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


KERNELS = (
    SimpleNamespace(field_read=field_read, select=select, add_normal_equations=add_normal_equations)
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
