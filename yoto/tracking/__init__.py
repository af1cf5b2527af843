"""Tracking after one touch: the object pose from the live sensor poses (open loop, paper Sec. 4.3), corrected by
the tactile frames during motion (closed loop). See docs/tracking.md.

- `yoto.tracking.track`: `track`, `Touch`, `touch_from_pair`, `TrackConfig`, `TrackResult`.
- `yoto.tracking.fusion`: two sensor streams -> one object pose (interpolation, jitter, weighted averaging).
- `yoto.tracking.streams`: sensor pose streams and tactile frames from files (TUM, frame folders, rig recordings).
- `yoto.tracking.evaluate`: errors against ground truth (Table 3, Fig. 4).
- `yoto.tracking.bench`: the tracking benchmark on simulated trajectories.

Nothing is imported here, so `yoto --help` stays fast; import the submodules.
"""
