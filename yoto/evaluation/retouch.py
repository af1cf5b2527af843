"""Simulating the suggested re-touch: one sensor moves where `next_touch` says, presses, the other stays.

The robot only knows the object's pose through the first estimate, so the moving sensor goes to the world pose
planned under the most probable hypothesis (`NextTouch.T_world_sensor`) and presses along its own z into the
object where it truly is, with the contact simulator that made the pair (same gel, noise and reachability rules).
Its reported pose carries the same calibration error as its first contact: the error belongs to the sensor.
A press the simulator rejects (nothing under the pad, the housing would collide, ...) is a failed re-touch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from yoto.contacts import TactileContact
from yoto.geometry import invert_transform
from yoto.pose.next_touch import NextTouch
from yoto.simulate.press import SimulatedContact, finish_contact
from yoto.simulate.scenarios import PairSimulator, SimulatedPair

RETOUCH_STREAM = 7  # the re-touch's random stream, beside the pair's own (pose, contacts, noise, calibration)


@dataclass
class Retouch:
    """The outcome of a simulated re-touch."""

    touch: TactileContact | None  # the new contact (reported sensor pose), None if the press failed
    rejection: str | None  # why the press failed (a key of the simulator's rejection reasons)


def simulate_retouch(
    simulator: PairSimulator, simulated: SimulatedPair, suggestion: NextTouch, number: int = 0
) -> Retouch:
    """Press the suggested sensor at the suggested place into the true object (see the module docstring); `number`
    counts the re-touches of one pair (each draws its own press depth and noise)."""
    stream = [simulated.seed, simulated.index, RETOUCH_STREAM] + ([number] if number else [])
    rng = np.random.default_rng(np.random.SeedSequence(stream))
    depth = float(rng.uniform(*simulator.config.press.depth_range_m))
    T_object_sensor_start = invert_transform(simulated.T_world_object) @ suggestion.T_world_sensor
    press = simulator.presses.press(T_object_sensor_start, depth)
    contact = SimulatedContact(
        target_object=T_object_sensor_start[:3, 3], approach={"depth_mm": depth * 1e3}, press=press
    )
    if press.accepted:
        finish_contact(simulator.presses, contact, rng, simulator.reconstruct)
    if not contact.accepted or contact.points_sensor is None:
        return Retouch(None, contact.rejection or "reconstruction_failed")
    side = suggestion.sensor
    reported_first = simulated.pair.contact(side).T_world_sensor
    error = invert_transform(simulated.T_world_sensor_true[side]) @ reported_first  # reported = true @ error
    T_world_sensor_true = simulated.T_world_object @ press.T_object_sensor
    return Retouch(TactileContact(contact.points_sensor, T_world_sensor_true @ error), None)
