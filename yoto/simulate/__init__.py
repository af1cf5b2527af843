"""Simulated GelSight contacts, dual-contact scenarios and simulated phone scans (docs/simulation.md).

- `yoto.simulate.press`: `PressSimulator` (press a GelSight Mini into a mesh), `simulate_contact`, `PressConfig`.
- `yoto.simulate.gel`: the gel model `GelModel` (`gel_surface`) and the reconstruction noise `ReconstructionNoise`
  (`reconstruct_points`).
- `yoto.simulate.body`: the sensor's rigid body `SensorBody` and its collision sweep `BodySweep`.
- `yoto.simulate.scenarios`: `PairSimulator`, `simulate_pairs` (in-memory pairs), `write_pairs` (pair files),
  `ScenarioConfig`.
- `yoto.simulate.scan`: `degrade_mesh`, `ScanConfig`.

Nothing is imported here, so `yoto --help` stays fast; import the submodules.
"""
