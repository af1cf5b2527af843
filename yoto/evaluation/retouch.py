"""Simulating the suggested re-touch: one sensor moves where `next_touch` says, presses, the other stays.

The robot only knows the object's pose through the first estimate, so the moving sensor goes to the world pose
planned under the most probable hypothesis (`NextTouch.T_world_sensor`) and presses along its own z into the
object where it truly is, with the contact simulator that made the pair (same gel, noise and reachability rules).
Its reported pose carries the same calibration error as its first contact: the error belongs to the sensor.
A press the simulator rejects (nothing under the pad, the housing would collide, ...) is a failed re-touch.
Where the pair's contacts came through GelSight images (the benchmark's rows via images), so does the re-touch: its
gel height map is rendered and reconstructed by the same `ImagePath`, and the contact carries the reconstruction's
depth-scale prior.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from yoto.contacts import MIN_TACTILE_POINTS, TactileContact
from yoto.geometry import invert_transform
from yoto.pose.next_touch import NextTouch
from yoto.simulate.press import SimulatedContact, finish_contact
from yoto.simulate.scenarios import PairSimulator, SimulatedPair

if TYPE_CHECKING:
    from yoto.sensor.optical import ImagePath

RETOUCH_STREAM = 7  # the re-touch's random stream, beside the pair's own (pose, contacts, noise, calibration)


@dataclass
class Retouch:
    """The outcome of a simulated re-touch."""

    touch: TactileContact | None  # the new contact (reported sensor pose), None if the press failed
    rejection: str | None  # why the press failed (a key of the simulator's rejection reasons)


def simulate_retouch(
    simulator: PairSimulator,
    simulated: SimulatedPair,
    suggestion: NextTouch,
    number: int = 0,
    image_path: ImagePath | None = None,
) -> Retouch:
    """Press the suggested sensor at the suggested place into the true object (see the module docstring); `number`
    counts the re-touches of one pair (each draws its own press depth and noise); `image_path`: the contact comes
    through its GelSight image and reconstruction instead of the simulator's noise model."""
    stream = [simulated.seed, simulated.index, RETOUCH_STREAM] + ([number] if number else [])
    rng = np.random.default_rng(np.random.SeedSequence(stream))
    depth = float(rng.uniform(*simulator.config.press.depth_range_m))
    T_object_sensor_start = invert_transform(simulated.T_world_object) @ suggestion.T_world_sensor
    press = simulator.presses.press(T_object_sensor_start, depth)
    if not press.accepted:
        return Retouch(None, press.rejection or "reconstruction_failed")
    if image_path is None:
        contact = SimulatedContact(
            target_object=T_object_sensor_start[:3, 3], approach={"depth_mm": depth * 1e3}, press=press
        )
        finish_contact(simulator.presses, contact, rng, simulator.reconstruct)
        points_sensor, depth_scale_sigma = (contact.points_sensor if contact.accepted else None), 0.0
    else:
        reconstruction = image_path.reconstruction(press.height_map_m)
        points_sensor = None if reconstruction is None else reconstruction.points_sensor
        depth_scale_sigma = 0.0 if reconstruction is None else reconstruction.depth_scale_sigma
    if points_sensor is None or len(points_sensor) < MIN_TACTILE_POINTS:
        return Retouch(None, "reconstruction_failed")
    side = suggestion.sensor
    reported_first = simulated.pair.contact(side).T_world_sensor
    error = invert_transform(simulated.T_world_sensor_true[side]) @ reported_first  # reported = true @ error
    T_world_sensor_true = simulated.T_world_object @ press.T_object_sensor
    touch = TactileContact(points_sensor, T_world_sensor_true @ error, depth_scale_sigma=depth_scale_sigma)
    return Retouch(touch, None)
