"""The real rig (paper App. B, docs/rig.md): recordings in, calibrations and labelled contacts out.

- `yoto.rig.streams`: `read_pose_stream(path, topic_or_body)`, `read_point_stream`, `read_image_stream`,
  `open_recording` over ROS1/ROS2 bags (`yoto.rig.bags`, through `rosbags`), Motive CSV takes (`yoto.rig.motive`)
  and folders of time-stamped GelSight PNGs; `yoto.rig.timeline`: the stream types and matching in time.
- `yoto.rig.calibration`: the GelSight frame in a rig's rigid body (dual-ball procedure, CAD rotation, plate
  presses), `RigCalibration` and its file.
- `yoto.rig.beads`: the mesh frame in the object's rigid body (beads, SVD fit), `ObjectCalibration` and its file.
- `yoto.rig.labelling`: trials, ground-truth contact labels, contact-pair files of dual contacts.
- `yoto.rig.samples`: the labelled single-contact file `yoto train --real-pairs` reads.
- `yoto.rig.recording`: the recording simulator behind `yoto simulate recording`.
- `yoto.rig.bench`: `yoto rig bench`.

Nothing is imported here, so `yoto --help` stays fast; import the submodules.
"""
