"""Tactile clouds whose CONTENT another SPEC-following simulator makes differently from YOTO's (stop 15): contact
points alone whose noisy rim puts a few points above the gel plane, and clouds randomly decimated to a few thousand
points. The clouds are written here from SPEC ("Dual contact": PLY, sensor frame, metres, z <= 0 where pressed) by a
writer of the test's own, never YOTO's; `benchmarks/foreign_contacts.py` measures what such clouds cost in poses.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from yoto.contacts import read_tactile_cloud
from yoto.tactile_image import tactile_height_image, tactile_spacing_m

PITCH_M = 0.0634e-3  # SPEC: the Mini's 320 x 240 pixels


def _ply(path: Path, points: np.ndarray) -> Path:
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
    header += "property float x\nproperty float y\nproperty float z\nend_header\n"
    path.write_bytes(header.encode() + points.astype("<f4").tobytes())
    return path


def _sphere_press(
    rng: np.random.Generator, noise_m: float, whole_pad: bool = False, radius_m: float = 0.02, depth_m: float = 0.001
) -> np.ndarray:
    """A rigid pad pressed 1 mm into a 20 mm-radius sphere: every pixel where the sphere penetrates the pad plane
    (or, `whole_pad`, every pixel), heights with white noise."""
    x, y = np.meshgrid((np.arange(320) - 159.5) * PITCH_M, (np.arange(240) - 119.5) * PITCH_M)
    penetration = np.maximum(depth_m - (x**2 + y**2) / (2.0 * radius_m), 0.0)
    keep = np.ones_like(x, dtype=bool) if whole_pad else penetration > 0
    z = -penetration + rng.normal(0.0, noise_m, x.shape)
    return np.column_stack([x[keep], y[keep], z[keep]])


def test_a_contact_only_cloud_with_a_noisy_rim_keeps_its_rim(tmp_path, rng):
    """A simulator that writes the contact's pixels with noisy heights puts its shallow rim partly above z = 0 (here
    0.2% of the points). Such a cloud was taken for one of the whole pad and every point shallower than the 0.05 mm
    floor dropped (here 8% of the contact: its outline moved in); since whole-pad clouds are also cut at a tenth of
    their depth, it would lose 0.1 mm of its rim. Now it is read as it is; a cloud of the whole pad of the same press
    is still read as its contact (docs/journal/formats.md, stop 15)."""
    contact = _sphere_press(rng, 2e-5)
    above = int((contact[:, 2] >= 0).sum())
    assert 20 <= above < 0.01 * len(contact)  # more than the old test's 20 points, a small share
    read = read_tactile_cloud(_ply(tmp_path / "contact.ply", contact))
    assert len(read) == len(contact)
    assert read[:, 2].max() > 0.0  # the rim's points above the plane are the contact's, not untouched gel

    whole = _sphere_press(np.random.default_rng(3), 2e-5, whole_pad=True)
    read_whole = read_tactile_cloud(_ply(tmp_path / "whole.ply", whole))
    assert len(read_whole) < 0.9 * len(contact)  # the untouched gel (and the rim within its noise) left out
    assert read_whole[:, 2].max() <= -5e-5


@pytest.mark.parametrize("keep", [3000, 1500])
def test_a_randomly_decimated_cloud_keeps_its_contact_area(rng, keep):
    """A cloud decimated at random (Open3D's `random_down_sample`, a few thousand points) has neighbours at about half
    its spacing; the height image's pixel was 1.5 x that distance, so most pixels stayed empty, the rim erosion widened
    the holes, and the trusted mask lost 10-75% of the contact (3000 / 1500 of ~30000 points). The spacing is now read
    off the density: the mask covers the full cloud's within 15%, and a grid's spacing is still its pitch."""
    full = _sphere_press(rng, 0.0, radius_m=0.015)
    decimated = full[np.sort(rng.choice(len(full), keep, replace=False))]

    def area_mm2(points: np.ndarray) -> float:
        image = tactile_height_image(points, 0.0105, 0.0002, 1)
        return float(image.mask.sum() * image.pixel_m**2 * 1e6)

    assert area_mm2(decimated) == pytest.approx(area_mm2(full), rel=0.15)
    density_spacing = np.sqrt(np.pi * 0.015 * 2 * 0.001 / keep)  # the contact disc's area per point
    assert tactile_spacing_m(decimated) == pytest.approx(density_spacing, rel=0.1)
    assert tactile_spacing_m(full) == pytest.approx(PITCH_M, rel=0.02)
    column, row = np.rint(full[:, 0] / PITCH_M + 159.5), np.rint(full[:, 1] / PITCH_M + 119.5)
    coarse = full[(column % 2 == 0) & (row % 2 == 0)]  # every other pixel: a 0.127 mm grid
    assert tactile_spacing_m(coarse) == pytest.approx(2 * PITCH_M, rel=0.02)


def test_a_whole_pad_cloud_is_read_without_the_gels_sink_in_ring(tmp_path, rng):
    """A simulator with a soft gel (here the penetration spread by an exponential kernel of 0.5 mm, not YOTO's
    Gaussian) writes the whole pad: around the contact the gel sinks in without touching the object, 0.1-0.3 mm deep
    at a 1 mm press. The old floor (0.05 mm, or 5 sigma of the noise) kept that ring out to 1.0 mm beyond the contact
    (35% more points than the contact); a floor at a tenth of the contact's depth keeps 0.6 mm of it. On the
    benchmark's whole-pad clouds: poses right 30 -> 34 of 40 (contact-only clouds of the same presses: 35)."""
    from scipy import signal

    x, y = np.meshgrid((np.arange(320) - 159.5) * PITCH_M, (np.arange(240) - 119.5) * PITCH_M)
    penetration = np.maximum(0.001 - (x**2 + y**2) / (2.0 * 0.02), 0.0)
    offsets = np.arange(-32, 33) * PITCH_M
    kernel = np.exp(-np.hypot(*np.meshgrid(offsets, offsets)) / 0.0005)
    spread = signal.fftconvolve(np.pad(penetration, 32, mode="edge"), kernel / kernel.sum(), mode="valid")
    gel = np.maximum(penetration, spread)
    touching = (gel - penetration < 1e-7) & (penetration > 0)
    z = -gel + rng.normal(0.0, 5e-6, x.shape)
    read = read_tactile_cloud(_ply(tmp_path / "whole.ply", np.column_stack([x.ravel(), y.ravel(), z.ravel()])))
    contact_radius = np.hypot(x[touching], y[touching]).max()
    assert np.hypot(read[:, 0], read[:, 1]).max() < contact_radius + 0.0007
    assert len(read) < 1.25 * touching.sum()
    deep = touching & (penetration > 0.0002)
    assert len(read) > deep.sum()  # the contact's deeper part is all there


def test_a_whole_pad_whose_gel_lies_below_z_0_is_still_read_as_its_contact(tmp_path):
    """A reconstruction whose zero level is off by 30 um (its untouched gel at z = -0.03 mm, 10 um of noise) puts only
    its noise's tail above z = 0 (0.1% of the points): fewer than a whole pad's share, but the cloud spans the pad, so
    it is still read as its contact, not as 76 800 points of flat gel."""
    from yoto.contacts import MINI_PAD_M
    from yoto.sensor.spec import GELSIGHT_MINI

    assert MINI_PAD_M == pytest.approx(GELSIGHT_MINI.pad_size_m)  # the core module's copy of SPEC's pad
    whole = _sphere_press(np.random.default_rng(4), 1e-5, whole_pad=True)
    whole[:, 2] -= 3e-5
    assert 20 <= int((whole[:, 2] >= 0).sum()) < 0.01 * len(whole)
    read = read_tactile_cloud(_ply(tmp_path / "offset.ply", whole))
    contact = _sphere_press(np.random.default_rng(4), 0.0)
    assert len(read) < len(contact)
    assert read[:, 2].max() <= -1e-4  # the floor: a tenth of the 1 mm contact's depth


def test_a_whole_pad_tracking_frame_pressed_nowhere_holds_no_contact(tmp_path, rng):
    """Tracking frames of the whole pad (`benchmarks/foreign_frames.py`): where the gel lost contact, the frame is the
    flat gel (10 um of noise, 76 800 points; 5000 of them, decimated) and holds no contact, so the closed loop leaves it
    out as empty; before, the flat gel was registered as a contact (refused only when it fitted badly). A pressed whole
    pad with NaN pixels (an organised cloud) still gives its contact. A shallow noisy frame of contact points alone (30
    um deep, not pressed beyond its noise floor) was kept as it is (stop 15) and is now no contact either: the object
    only kisses the gel (stop 16, `GelReading.kiss`)."""
    from yoto.tracking.streams import read_tactile_folder

    folder = tmp_path / "left_tactile"
    folder.mkdir()
    flat = _sphere_press(rng, 1e-5, whole_pad=True, depth_m=0.0)
    pressed = _sphere_press(rng, 1e-5, whole_pad=True)
    pressed[::50] = np.nan
    shallow = _sphere_press(rng, 1e-5, depth_m=3e-5)
    frames = [flat, flat[rng.choice(len(flat), 5000, replace=False)], pressed, shallow]
    for k, cloud in enumerate(frames):
        _ply(folder / f"{1700000000 + k}.ply", cloud)
    stream = read_tactile_folder(folder)
    assert len(stream.load(0)) == 0
    assert len(stream.load(1)) == 0
    contact = stream.load(2)
    assert np.isfinite(contact).all()
    assert 0.5 * (_sphere_press(rng, 0.0)[:, 2] < -1e-4).sum() < len(contact) < len(_sphere_press(rng, 0.0))
    assert len(shallow) > 900 and len(stream.load(3)) == 0


def test_a_16_bit_grey_and_alpha_png_is_refused_as_greyscale(tmp_path):
    """A 16-bit grey + alpha PNG (a depth camera's frame with a mask) is opened by Pillow as colour, so it was refused
    as "another sensor, or the lighting changed" after a reconstruction's worth of checks; the PNG header says it is
    grey. Written here byte by byte from the PNG specification (colour type 4, bit depth 16), never by Pillow: as a
    file, and as a bag's CompressedImage message."""
    import struct
    import zlib
    from types import SimpleNamespace

    from yoto.errors import InputError
    from yoto.rig.streams import decode_image_message
    from yoto.sensor.presses import load_image
    from yoto.sensor.spec import GELSIGHT_MINI

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    grey_alpha = np.zeros((240, 320, 2), dtype=">u2")
    grey_alpha[..., 0], grey_alpha[..., 1] = 30000, 65535
    rows = b"".join(b"\x00" + row.tobytes() for row in grey_alpha)
    header = struct.pack(">IIBBBBB", 320, 240, 16, 4, 0, 0, 0)
    chunks = chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b"")
    png = b"\x89PNG\r\n\x1a\n" + chunks
    path = tmp_path / "depth_with_mask.png"
    path.write_bytes(png)
    with pytest.raises(InputError, match="depth_with_mask.png: expected an 8-bit colour image, got a greyscale PNG"):
        load_image(path)
    message = SimpleNamespace(format="png", data=np.frombuffer(png, dtype=np.uint8))
    with pytest.raises(
        InputError, match=r"topic '/gel': a compressed frame \(png\) is not a colour image \(a greyscale PNG\)"
    ):
        decode_image_message(message, "sensor_msgs/msg/CompressedImage", GELSIGHT_MINI, "topic '/gel'", tmp_path / "b")


def test_track_job_refuses_one_source_for_both_sensors(tmp_path):
    """`run_track_job` (what `yoto track` runs, and a program calling it) refuses one tactile folder or recording
    topic, or one pose file, for both sensors, before it reads anything (here the touch does not even exist); the CLI
    alone checked it before, and a program building its `TrackJob` had the left frames registered as the right's."""
    from yoto.errors import InputError
    from yoto.tracking.job import Source, TrackJob, run_track_job

    (tmp_path / "frames").mkdir()
    sensors = {"left": Source(tmp_path / "l.tum"), "right": Source(tmp_path / "r.tum")}
    job = TrackJob(tmp_path / "touch.json", sensors, tmp_path / "object.tum")
    cases = {
        "tactile frames are the same source, .*frames: give each sensor its own folder or topic": {
            "tactile": {"left": Source(tmp_path / "frames"), "right": Source(tmp_path / "." / "frames")}
        },
        r"tactile frames are the same source, .*rec.bag \(topic /gel\): give each sensor its own topic": {
            "tactile": {"left": Source(tmp_path / "rec.bag", "/gel"), "right": Source(tmp_path / "rec.bag", "/gel")}
        },
        "pose streams are the same source, .*l.tum: give each sensor its own file": {
            "sensors": {"left": Source(tmp_path / "l.tum"), "right": Source(tmp_path / "x" / ".." / "l.tum")}
        },
    }
    for message, change in cases.items():
        with pytest.raises(InputError, match=message):
            run_track_job(dataclasses.replace(job, **change))
    other = {"left": Source(tmp_path / "rec.bag", "/gel_left"), "right": Source(tmp_path / "rec.bag", "/gel_right")}
    with pytest.raises(InputError, match="touch.json"):  # two topics of one recording are two sources: read on
        run_track_job(dataclasses.replace(job, tactile=other))


def _lifted_off(points_sensor: np.ndarray, kind: int, rng: np.random.Generator) -> np.ndarray:
    """A frame of the object leaving the gel, as another simulator writes it from the frame's own surface: 0, the
    whole pad's flat gel (10 um noise; the object 0-50 um behind it); 1, the whole pad with the object's front kissing
    the gel 40-90 um deep; 2, that kiss's pixels alone (contact points deeper than 20 um, noisy)."""
    x, y = np.meshgrid((np.arange(320) - 159.5) * PITCH_M, (np.arange(240) - 119.5) * PITCH_M)
    pad = np.column_stack([x.ravel(), y.ravel(), rng.normal(0.0, 1e-5, x.size)])
    kiss = points_sensor.copy()
    kiss[:, 2] -= kiss[:, 2].min() + rng.uniform(4e-5, 9e-5)  # the front moved to 40-90 um behind the gel plane
    kiss = kiss[kiss[:, 2] < -2e-5]
    kiss[:, 2] += rng.normal(0.0, 1e-5, len(kiss))
    return [pad, np.vstack([pad, kiss]), kiss][kind]


def test_lift_off_frames_are_no_contact_and_the_closed_loop_keeps_its_prediction(builtin_models, tmp_path):
    """Where the object leaves the gel (the grip slackens on the right sensor for four frames, both sensors' last three
    frames end the motion), the frames show flat gel or a kiss of 40-90 um (hundreds of pixels here, pressed beyond
    the 50 um noise floor). The kisses were registered as contacts (the flat pads already held none): at this grasp
    the frame says the object is a millimetre off the pad. Now every lifted frame is no contact ("too few points
    (0)") and the closed loop keeps its prediction: its poses are exactly those of the same frames with the lifted
    ones empty. On foreign_frames' lifted trajectories (docs/journal/formats.md, stop 16) registering kisses cost
    drift."""
    from test_tracking_closed_loop import SHORT

    from yoto.contacts import SIDES
    from yoto.simulate.trajectory import TrajectorySimulator
    from yoto.tracking.streams import TactileStream, read_tactile_folder
    from yoto.tracking.track import touch_from_pair, track
    from yoto.trajectory import tactile_frame_name

    model = builtin_models["fruit"]
    trajectory = TrajectorySimulator(model, SHORT).trajectory(3, 1)
    rng = np.random.default_rng(7)
    streams, reference, kisses = {}, {}, []
    for side in SIDES:
        frames = trajectory.tactile[side]
        lifted = set(range(len(frames) - 3, len(frames))) | (set(range(5, 9)) if side == "right" else set())
        folder = tmp_path / f"{side}_tactile"
        folder.mkdir()
        for k, frame in enumerate(frames):
            points = frame.points_sensor
            if k in lifted:
                points = _lifted_off(points, k % 3, rng)
                kisses += [len(points)] if k % 3 == 2 else []
            _ply(folder / tactile_frame_name(frame.timestamp_s), points)
        streams[side] = stream = read_tactile_folder(folder)
        reference[side] = TactileStream(
            stream.timestamps_s, lambda i, s=stream, out=lifted: np.empty((0, 3)) if i in out else s.load(i)
        )
    assert sorted(kisses)[1] >= 100  # contact points enough to register (30), had they been read as a contact
    touch = touch_from_pair(trajectory.touch.pair, trajectory.touch.T_world_object, trajectory.touch_time_s)
    result = track(touch, trajectory.streams, model, streams)
    assert result.correction_summary()["unusable"] == {"too few points": 3 + 3 + 4}
    assert result.released_s is None  # three frames of both, 0.16 s from the first to the last at 12.5 Hz: no release
    expected = track(touch, trajectory.streams, model, reference)
    assert np.array_equal(result.T_world_object, expected.T_world_object)
