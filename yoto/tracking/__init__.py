"""Tracking after one touch: the object pose from the live sensor poses (open loop, paper Sec. 4.3), corrected by
the tactile frames during motion (closed loop). See docs/tracking.md.

- `yoto.tracking.track`: `track` (the driver: open loop, then each tactile instant), `TrackResult`, the pairing of
  frames into instants; re-exports the public names of the parts below.
- `yoto.tracking.config`: `TrackConfig` and the closed loop's `CorrectionConfig`.
- `yoto.tracking.touch`: `Touch`, `touch_from_pair`, the touch's time matched to the streams.
- `yoto.tracking.correction`: the closed loop's filter (`ClosedLoop`, its `Correction` per instant).
- `yoto.tracking.frame_registration`: a tactile frame's samples, its registration's settings and information.
- `yoto.tracking.release`: a release, one gel letting go, a new touch after a release (`NewTouchSearch`, `Regrasp`).
- `yoto.tracking.pinning`: how well contacts pin each direction (`Pinning`), where to touch again (`retouch`).
- `yoto.tracking.pad_error`: each pad's own reconstruction error, learnt and removed.
- `yoto.tracking.fusion`: two sensor streams -> one object pose (interpolation, jitter, weighted averaging), from the
  sides that hold it (`fuse_holding`).
- `yoto.tracking.streams`: sensor pose streams and tactile frames from files (TUM, frame folders, rig recordings).
- `yoto.tracking.evaluate`: errors against ground truth (Table 3, Fig. 4).
- `yoto.tracking.bench`: the tracking benchmark on simulated trajectories.

Nothing is imported here, so `yoto --help` stays fast; import the submodules.
"""
