"""Simulated GelSight contacts, dual-contact scenarios and simulated phone scans (docs/simulation.md).

- `yoto.simulate.gelsight`: `PressSimulator` (press a GelSight Mini into a mesh), `simulate_contact`,
  `reconstruct_points` (reconstruction noise), the configs `PressConfig`, `GelModel`, `ReconstructionNoise`,
  `SensorBody`.
- `yoto.simulate.scenarios`: `PairSimulator`, `simulate_pairs` (in-memory pairs), `write_pairs` (pair files),
  `ScenarioConfig`.
- `yoto.simulate.scan`: `degrade_mesh`, `ScanConfig`.

Nothing is imported here, so `yoto --help` stays fast; import the submodules.
"""
