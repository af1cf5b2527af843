"""How the track is set: `TrackConfig` (the open loop's fusion, the touch's checks, the re-touch advice), its
closed loop's `CorrectionConfig` (frame sampling, registration, the filter, the pads' errors, the divergence guard)
and `ReleaseConfig` (a release, one gel letting go, a new touch after a release).

Lengths in metres, angles in radians; directions are the canonical `object` frame's (origin at the centroid).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from yoto.tracking.fusion import FusionConfig
from yoto.tracking.pad_error import PadErrorConfig


@dataclass(frozen=True)
class CorrectionConfig:
    """How tactile frames during motion correct the tracked pose (closed loop)."""

    points_per_contact: int = 250  # tactile points registered per contact, after voxel down-sampling
    voxel_m: float = 0.0004  # side of the square bins over the pad (sensor x, y) whose means are those points
    min_depth_fraction: float = 0.4  # only points pressed at least this share of the frame's deepest point count:
    # the rim, where the gel barely touches and sinks in beside the object, is where reconstructions are off
    sync_tolerance_s: float = 0.02  # a left and a right frame this close in time are registered together; or
    # closer than half the slower gel's frame period where that is longer (`instant_window_s`)
    iterations: int = 10  # Gauss-Newton iterations at most ...
    step_tolerance_m: float = 1e-6  # ... stopping when a step moves less than this ...
    step_tolerance_rad: float = 1e-5  # ... and turns less than this (far below what a frame can tell)
    max_distance_m: float = 0.002  # correspondences further than this are ignored (the capture range per frame)
    surface_noise_m: float = 3e-5  # 1-sigma of a tactile point's distance from the surface (robust scale floor)
    registration_prior_rotation_rad: float = float(np.radians(3.0))  # weak prior on the prediction inside the
    registration_prior_translation_m: float = 0.003  # registration (keeps free directions put)
    pixel_noise_m: float = 4e-5  # 1-sigma error of a tactile point that is new in every frame (camera noise, and
    # what registering a frame adds: its mask edge, its sampling)
    bias_points: float = 3.0  # the error a contact's points share from frame to frame (calibration, lighting,
    bias_noise_m: float = 3e-5  # integration drift) is smooth over the patch: as if this many points had this error
    bias_travel_m: float = 1.0  # that shared error is fixed on the pad (calibration, lighting) and changes only as
    # the contact slides over it, millimetres along a path: fully over this much travel of the sensors
    inlier_distance_m: float = 0.0003  # a registered point this close to the surface lies on it
    min_inlier_fraction: float = 0.5  # a frame with fewer of its points on the surface after registration is unusable
    observable_max_contacts: int = 1  # instants with at most this many contacts (1: a lone contact; 2: all; 0: none)
    # correct only the directions they pin, where a reconstruction's smooth error (`bias_noise_m` over
    # `bias_points`) moves the fit by less than this turn and this shift (in those units, one unit); along the
    # others (a lone contact's spin and lever, the line through two flat contacts) the prediction stands
    observable_rotation_rad: float = float(np.radians(2.0))  # that turn ...
    observable_translation_m: float = 0.002  # ... and that shift
    innovation_bound: float = 12.6  # a registration whose normalized innovation squared exceeds this (chi-square,
    # 6 degrees of freedom, 95%) has its information scaled down by bound / NIS
    max_correction_m: float = 0.003  # a frame asking for a larger jump than this is unusable (a wrong fit) ...
    max_correction_rad: float = float(np.radians(3.0))  # ... or a larger turn than this
    touch_translation_m: float = 0.001  # 1-sigma uncertainty of the touch's pose: how far the first frames may
    touch_rotation_rad: float = float(np.radians(2.0))  # move it
    slip_rate_translation: float = 0.03  # 1-sigma prior of the slip rate: metres of slip per metre of travel ...
    slip_rate_rotation: float = float(np.radians(20.0))  # ... and radians per metre (paper: 1-3 mm, 1-2 deg / 100 mm)
    slip_travel_m: float = 0.1  # over this much travel the slip rate may change by its prior, and the slip may
    slip_wander_translation_m: float = 0.001  # leave its rate by this (elastic, inertial slip) ...
    slip_wander_rotation_rad: float = float(np.radians(1.0))  # ... and this
    turn_radius_m: float = 0.05  # the sensors turning by one radian count as this much travel
    creep_translation_m: float = 1e-5  # 1-sigma slip per second at rest (per square root of a second) ...
    creep_rotation_rad: float = float(np.radians(0.01))  # ... and its rotation
    pad_error: PadErrorConfig = PadErrorConfig()  # each pad's fixed reconstruction error, learnt at rest, removed
    bias_follows_pads: bool = True  # where a pad's map, learning on, changes what it removes under the contact at
    # rest (where the filter learnt the registrations' bias), the bias moves by the registration shift that change
    # makes there: the map's later knowledge revises the bias instead of reading as slip
    guard_bound: float = 22.46  # divergence guard: when the tracked slip leaves what the slip model allows over the
    # travel so far (its squared Mahalanobis distance above this: chi-square, 6 degrees of freedom, 99.9%), the
    # instant's frames are registered from the open-loop pose as well ...
    guard_fit_margin: float = 1.1  # ... and where they fit there within this factor of the closed loop's RMS (and
    # its inlier share), the frames never asked for the departure: the loop re-anchors on that fit
    guard_support_fraction: float = 0.5  # ... and stay there: the fit moves the pose less than this share of the
    # departure (observable units); frames that see a real pivot lead it away from the open loop
    guard_every_s: float = 0.24  # while the slip stays beyond the bound, such checks at least this long apart ...
    guard_every: int = 1  # ... and at least this many applied instants between them (0.24 s: 6 instants at 25 fps,
    # what 5 instants between checks gave there; at other frame rates the same time between checks, not a frame count)
    guard_block_bound: float = 17.73  # ... it checks as well when the slip's turn or its shift alone leaves the
    # model (3 degrees of freedom each, 99.95%: both at 99.9% together): a spin beyond it is not diluted by a quiet
    # shift (0: off) ...
    guard_rate: bool = True  # ... or the filter's slip rate's turn or shift leaves its prior by as much (seed 23's
    # mug: a spin the scanned mesh's planes claim to pin, rate 6 sigma out, its slip only 3.7)
    guard_weak_spread: float = 1.0  # along the directions the two-contact instants pin more weakly than this (their
    # mean shared error moves the fit by more, observable units; `weak_pinning_warning`; 0: off) ...
    guard_weak_sigmas: float = 1.0  # ... the tracked slip is held within this many sigma of the slip model: the frames
    # cannot tell slip there (seed 37's cracker box: a face's slide carried 6.6 mm by the slip rate, the slip 4.0;
    # held at 0 sigma seed 11's fruit, figurine, tool lose what the loop corrects there: 47 -> 32 of 53 meet)
    secant_directions: int = 3  # an instant's information (both contacts; a lone contact's own rule is above) is
    # checked along its this many weakest directions (observable units): its points re-matched to the surface at
    # +-`secant_step` there, the cost's actual rise against the planes' prediction; where the surface rises less (a
    # scanned mesh's tilted planes claim a spin its surface of revolution leaves free), the information there is
    # scaled down to what re-matching shows (0: off)
    secant_step: float = 0.5  # that step, in observable units (`observable_rotation_rad`, `observable_translation_m`)
    shallow_read_fraction: float = 0.5  # a frame reading its press shallower than this share of what it should is
    # left out (0: off): in motion, of what its pad read at rest (median) while the sensors stand no further apart
    # than then (within `shallow_gap_m`): the reconstruction lost part of the contact, and would read as a slide ...
    misread_fraction: float = 0.25  # ... at rest, of the press the touch's pose puts on its pad; a pad whose rest
    # frames read that shallow (median) is left out of the motion too: it misreads this contact's shape (0.5 also
    # drops the cracker box's left pad through `shading:3`, 0.42 of its press, whose track met the target)
    shallow_gap_m: float = 0.001  # (the reported sensor poses put the sensors' distance a few tenths off)
    image_contact_tilt_rad: float = 0.001  # frames the tracker reconstructs from GelSight images: each contact may
    # turn about its own centre in its pad plane by about this much (1-sigma, two angles a contact, estimated in the
    # registration beside the correction and left out of its information: `frame_registration.register_contacts`);
    # the reconstruction reads a contact's plane a few mrad off, changing as it slides over the pad (0: off) ...
    cloud_contact_tilt_rad: float = 0.001  # ... and clouds given as clouds, which a lab's reconstruction made too
    # (seeds 11 / 23 / 37's PLY frames: 111 -> 115 of 130 meet, growth +0.090 -> +0.063 deg per 100 mm; the
    # figurine #2s and the mug seed 23 #0 worse, journal stop 20)
    # (stop 21) the tilt combinations that would move the registration's landing far, not estimated:
    contact_tilt_move_units: float = 0.0  # > 0: the registration estimates only the contacts' tilt combinations of
    # which a tilt of its sigma moves the correction by at most this many observable units (along a spin two flat
    # contacts pin only through their planes, 1 mrad of tilt is the object turning by degrees); 0.15 measured: seed
    # 11's PLY frames gain (figurine #2s), the held-out seeds lose (avocado seed 37 #0), so off
    # (`frame_registration.tilts_leaving_the_landing`; 0: every tilt estimated, stop 20)
    # (stop 22) a reconstruction's depth scale error, taken out of each frame's shape before its registration:
    image_depth_scale: float = 0.3  # frames the tracker reconstructs from GelSight images: the share by which a frame
    # reads its depths (about their mean) off, 1-sigma prior of its estimate at the predicted pose jointly with a rigid
    # motion, narrowed as if the patch's shape told it through `bias_points` points only
    # (`frame_registration.without_depth_scale`; 0: off). Such frames read a press 5-15% shallow, by a share that
    # changes as the contact slides (seed 11's figurine #0 at the truth: the frames' own turn 2.9 -> 0.9 deg); 0.1 /
    # 0.2 / 0.3 measured, 0.3 kept (image frames 16 -> 20 of 38 meet; clouds given as clouds: not measured, not used)


@dataclass(frozen=True)
class ReleaseConfig:
    """When the object is let go (a release, one gel letting go), and when a new touch follows (`release.py`)."""

    release_s: float = 0.2  # the object is released (let go) when, after contact, both sensors' frames show no
    # contact (too few points) for at least this long each (from each side's first such frame to its latest) ...
    release_frames: int = 3  # ... in at least this many frames each (a floor for slow cameras; 0: off): the track
    # ends there (a lift-off of one side, or both for a moment, keeps the prediction). One side alone without contact
    # as long, the other touching, let go: the other carries the object alone. A duration, not a frame count: at
    # 25 fps 0.2 s takes 6 frames, at 15 fps 4, at 60 fps 13
    lifted_apart_m: float = 0.002  # a side whose frame shows no contact and whose grasp puts the object this far
    # from where the other side's puts it (position plus 50 mm per radian) predicts nothing until it touches again:
    # its sensor is leaving the object (a lift-off in place, the sides agreeing, keeps both)
    regrasp_s: float = 0.08  # after a release, both gels touching in every instant over this long (the first such
    # instant to the latest) ...
    regrasp_frames: int = 2  # ... and in at least this many instants make a new touch (its pose estimated from the
    # latest pair: the press has settled), when `track` is given a `NewTouchEstimator` (0.08 s: 3 instants at 25 fps)
    regrasp_attempts: int = 3  # new touches whose estimate was refused before the track stops looking until the end


@dataclass(frozen=True)
class TrackConfig:
    """How `track` follows the object after the touch."""

    fusion: FusionConfig = FusionConfig()
    correction: CorrectionConfig = CorrectionConfig()
    release: ReleaseConfig = ReleaseConfig()
    touch_mismatch_warning_m: float = 0.005  # warn when the streams never come this close to the pair's sensor poses
    min_touch_confidence: float = 0.5  # warn when the touch's pose is less likely than this to be right
    weak_pinning_warning: float = 1.0  # warn when the two contacts pin a direction of the pose only this loosely
    # (`Pinning.spread`, observable units: 1 is 2 deg / 2 mm): slip along it is not observable from the contacts
    retouch_above: float = 0.25  # beyond this spread of the weakest direction (the drift target, 0.5 deg / 0.5 mm),
    # `yoto track` says where on the object a contact would see it (`retouch`)
