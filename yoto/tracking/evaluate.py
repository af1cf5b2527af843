"""Tracking errors against ground truth, as the paper reports them (Table 3, Fig. 4).

Per frame: the translation error of the object's centroid and the rotation error of `E = T_true^-1 @ T_estimate`
(object frame). Summaries:
- `touch`: the error of the touch's own pose estimate;
- `motion_mean`, `motion_peak`: mean and largest error while the sensors move (Table 3's figure, and the peaks of
  Fig. 4); the motion is found from the sensor streams (speed over a short window), not from the truth;
- `settled`: mean error after the motion (Fig. 4's shaded tail);
- `settled_drift`: how much the motion changed the error, `E(before)^-1 @ E(t)` averaged over the settled tail, with
  `before` the last frame before the motion. Open loop this is the slip (the error the touch left stays as it was);
  closed loop it leaves out how the tracker settled on the touch while the sensors rested. Each frame's size is
  averaged, so the output's frame-to-frame jitter (the arms' smoothed pose noise) adds to it, and the single frame
  `before` carries its own jitter into every frame of the tail;
- `final_drift`: the change of the mean error, `mean(E at rest)^-1 @ mean(E settled)`, the means over the last
  `MotionConfig.window_s` before the motion and over the settled tail (twists averaged): the offset the motion left,
  without the output's jitter on either side.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from yoto.contacts import SIDES
from yoto.errors import InputError
from yoto.geometry import invert_transform, pose_from_twist, so3_log, twist_of_pose
from yoto.io import write_bytes_atomic
from yoto.trajectory import PoseStream


@dataclass(frozen=True)
class MotionConfig:
    """When the sensors count as moving."""

    speed_m_per_s: float = 0.002  # moving: the sensors' mean speed exceeds this ...
    turn_rad_per_s: float = float(np.radians(1.0))  # ... or their mean turn rate this
    window_s: float = 0.2  # speeds compare the mean pose over one window with the one before (jitter averages out)


def _window_means(stream: PoseStream, ends_s: np.ndarray, window_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean position and rotation vector (relative to the first sample) of the samples in (t - window, t], and
    whether there were any, for each end time t."""
    first = stream.T_world_frame[0, :3, :3]
    values = np.hstack(
        [stream.T_world_frame[:, :3, 3], so3_log(np.einsum("ji,njk->nik", first, stream.T_world_frame[:, :3, :3]))]
    )
    sums = np.vstack([np.zeros(6), np.cumsum(values, axis=0)])
    upper = np.searchsorted(stream.timestamps_s, ends_s, side="right")
    lower = np.searchsorted(stream.timestamps_s, ends_s - window_s, side="right")
    count = upper - lower
    means = (sums[upper] - sums[lower]) / np.maximum(count, 1)[:, None]
    return means, count > 0


def motion_interval(
    streams: dict[str, PoseStream], timestamps_s: np.ndarray, config: MotionConfig = MotionConfig()
) -> tuple[float, float] | None:
    """(first, last) time the sensors move, among `timestamps_s`, or None if they never do.

    The mean sensor pose over a window is compared with the one over the window before: a speed that jitter
    barely reaches (its mean over a window of samples is small) and smooth motion does.
    """
    times = np.asarray(timestamps_s, dtype=np.float64)
    speed, turn, counted = np.zeros(len(times)), np.zeros(len(times)), np.zeros(len(times))
    for side in SIDES:
        now, seen_now = _window_means(streams[side], times, config.window_s)
        before, seen_before = _window_means(streams[side], times - config.window_s, config.window_s)
        both = seen_now & seen_before & (times - 2 * config.window_s >= streams[side].start_s)
        speed += both * np.linalg.norm(now[:, :3] - before[:, :3], axis=1) / config.window_s
        turn += both * np.linalg.norm(now[:, 3:] - before[:, 3:], axis=1) / config.window_s
        counted += both
    counted = np.maximum(counted, 1)
    moving = (speed / counted > config.speed_m_per_s) | (turn / counted > config.turn_rad_per_s)
    if not moving.any():
        return None
    indices = np.flatnonzero(moving)
    # The two windows' means are a window apart: their difference is the speed a window before t.
    return float(times[indices[0]] - config.window_s), float(times[indices[-1]] - config.window_s)


@dataclass
class TrackingErrors:
    """Per-frame errors of tracked poses against the truth."""

    timestamps_s: np.ndarray  # (M,)
    errors: np.ndarray  # (M, 4, 4) E = T_true^-1 @ T_estimate, object frame (centroid origin)
    touch_error: np.ndarray  # (4, 4) the same for the touch's own estimate

    @property
    def translation_m(self) -> np.ndarray:
        return np.linalg.norm(self.errors[:, :3, 3], axis=1)

    @property
    def rotation_rad(self) -> np.ndarray:
        return np.linalg.norm(so3_log(self.errors[:, :3, :3]), axis=1)

    def drift(self, reference: int) -> tuple[np.ndarray, np.ndarray]:
        """How much the error changed since frame `reference`: (M,) translation (m) and rotation (rad)."""
        change = invert_transform(self.errors[reference]) @ self.errors
        return np.linalg.norm(change[:, :3, 3], axis=1), np.linalg.norm(so3_log(change[:, :3, :3]), axis=1)


def tracking_errors(
    timestamps_s: np.ndarray,
    T_world_object_estimate: np.ndarray,
    T_world_object_true: np.ndarray,
    T_world_object_touch: np.ndarray,
    T_world_object_true_touch: np.ndarray,
) -> TrackingErrors:
    """Errors of (M, 4, 4) estimates against the truth at the same times, and of the touch's estimate against the
    truth then; poses of YOTO's canonical frame (origin at the centroid)."""
    return TrackingErrors(
        np.asarray(timestamps_s, dtype=np.float64),
        invert_transform(T_world_object_true) @ T_world_object_estimate,
        invert_transform(T_world_object_true_touch) @ T_world_object_touch,
    )


def truth_at(truth_mesh: PoseStream, timestamps_s: np.ndarray, T_mesh_object: np.ndarray, max_gap_s: float = 0.1):
    """The true T_world_object (canonical frame) at the given times from a `T_world_mesh` stream; refuses times the
    truth does not cover."""
    poses, covered = truth_mesh.interpolate(timestamps_s, truth_mesh.dropout_gap_s(max_gap_s))
    if len(timestamps_s) and not covered.any():
        raise InputError(
            f"the ground truth ({truth_mesh.start_s:.3f} - {truth_mesh.end_s:.3f} s) does not cover the tracked times "
            f"({timestamps_s[0]:.3f} - {timestamps_s[-1]:.3f} s)",
            truth_mesh.source,
        )
    return poses @ T_mesh_object, covered


def final_drift_twist(
    errors: TrackingErrors, motion: tuple[float, float] | None, window_s: float = MotionConfig().window_s
) -> np.ndarray:
    """(6,) the final drift as a twist (rotation vector in rad, then translation in m; object frame): the mean error
    over the settled tail against the mean error over the last `window_s` before the motion (the frame before it
    where none is that close). NaN without a motion or a settled tail."""
    times = errors.timestamps_s
    if motion is None or not (times > motion[1]).any():
        return np.full(6, np.nan)
    resting = (times < motion[0]) & (times >= motion[0] - window_s)
    if not resting.any():
        resting = np.arange(len(times)) == max(int(np.searchsorted(times, motion[0])) - 1, 0)
    mean_rest = pose_from_twist(twist_of_pose(errors.errors[resting]).mean(axis=0))
    mean_settled = pose_from_twist(twist_of_pose(errors.errors[times > motion[1]]).mean(axis=0))
    return twist_of_pose(invert_transform(mean_rest) @ mean_settled)


def summarize_errors(errors: TrackingErrors, motion: tuple[float, float] | None) -> dict[str, Any]:
    """Table-3 figures of one tracked trajectory, in millimetres and degrees (see the module docstring)."""
    times = errors.timestamps_s
    if motion is None:
        during, after = np.ones(len(times), bool), np.zeros(len(times), bool)
    else:
        during = (times >= motion[0]) & (times <= motion[1])
        after = times > motion[1]
    # Drift is counted from the last frame before the motion: what the motion did, not how the tracker settled
    # on the touch while the sensors rested.
    reference = max(int(np.searchsorted(times, motion[0])) - 1, 0) if motion is not None else 0
    translation, rotation = errors.translation_m, errors.rotation_rad
    drift_translation, drift_rotation = errors.drift(reference)
    change = final_drift_twist(errors, motion)
    final = {"mm": 1e3 * float(np.linalg.norm(change[3:])), "deg": float(np.degrees(np.linalg.norm(change[:3])))}
    touch_translation = float(np.linalg.norm(errors.touch_error[:3, 3]))
    touch_rotation = float(np.linalg.norm(so3_log(errors.touch_error[:3, :3])))

    def pair(t: np.ndarray, r: np.ndarray, mask: np.ndarray, reduce=np.mean) -> dict[str, float]:
        if not mask.any():
            return {"mm": float("nan"), "deg": float("nan")}
        return {"mm": 1e3 * float(reduce(t[mask])), "deg": float(np.degrees(reduce(r[mask])))}

    return {
        "touch": {"mm": 1e3 * touch_translation, "deg": float(np.degrees(touch_rotation))},
        "motion_mean": pair(translation, rotation, during),
        "motion_peak": pair(translation, rotation, during, np.max),
        "settled": pair(translation, rotation, after),
        "settled_drift": pair(drift_translation, drift_rotation, after),
        "final_drift": final,
        "frames": int(len(times)),
        "motion_s": None if motion is None else [float(motion[0]), float(motion[1])],  # clock times
    }


@dataclass
class ErrorCurve:
    """One line of the Fig. 4-style plot."""

    label: str
    times_s: np.ndarray  # relative to the touch
    translation_mm: np.ndarray
    rotation_deg: np.ndarray
    motion_mean: tuple[float, float] | None = None  # (mm, deg) dashed reference line


def plot_tracking(
    panels: list[tuple[str, list[ErrorCurve], tuple[float, float] | None]], path: str | Path, title: str = ""
) -> Path:
    """Per-frame tracking error, one column per panel (top: translation, bottom: rotation), like the paper's
    Fig. 4: each panel a title, its curves, and the motion interval (relative times) whose tail is shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    columns = max(len(panels), 1)
    figure, axes = plt.subplots(2, columns, figsize=(3.6 * columns, 5.0), dpi=90, squeeze=False, sharex="col")
    colours = ["tab:red", "tab:blue", "tab:green", "tab:purple"]
    for column, (name, curves, motion) in enumerate(panels):
        for row, (key, unit) in enumerate((("translation_mm", "mm"), ("rotation_deg", "deg"))):
            axis = axes[row, column]
            for colour, curve in zip(colours, curves, strict=False):
                axis.plot(curve.times_s, getattr(curve, key), color=colour, lw=1.2, label=curve.label)
                if curve.motion_mean is not None:
                    value = curve.motion_mean[row]
                    axis.axhline(value, color=colour, ls="--", lw=0.8)
                    axis.annotate(
                        f"{value:.2f}",
                        (0.99, value),
                        xycoords=("axes fraction", "data"),
                        ha="right",
                        va="bottom",
                        fontsize=7,
                        color=colour,
                    )
            if motion is not None and curves:
                axis.axvspan(motion[1], float(curves[0].times_s[-1]), color="0.85", zorder=0, lw=0)
            axis.set_ylabel(f"{'translation' if row == 0 else 'rotation'} error ({unit})", fontsize=8)
            axis.tick_params(labelsize=7)
            axis.set_ylim(bottom=0)
            if row == 0:
                axis.set_title(name, fontsize=9)
            else:
                axis.set_xlabel("time since the touch (s)", fontsize=8)
        if curves:
            axes[0, column].legend(fontsize=7, loc="upper left")
    if title:
        figure.suptitle(title, fontsize=9)
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    plt.close(figure)
    return write_bytes_atomic(Path(path), buffer.getvalue())
