"""The truth's own key through GelSight images: does the joint search's key test reject the true pose?

The joint search (`yoto.pose.search`) keeps the location pairs whose key (separation, angles (d, nL), (d, nR),
(nL, nR)) fits the measured one and whose local shape (principal curvatures) fits each contact's. For the
benchmark's pairs (seed 7) through clean clouds and through images (`--renderer`: a calibration file's optical model
or `shading[:SEED]`), this prints what each measurement gets wrong against the truth (key, contact normals and
centres in the object frame) and how the truth fares in each test:
- curvature test: how many of the 3 surface samples nearest each true contact location pass it;
- key test: of the location pairs near the truth (the 6 nearest left x 6 nearest right locations, after the
  search's thinning), the best one's mismatch in tolerances (pass <= 1) and its parts: (nL, nR), separation,
  (d, nL), (d, nR);
- the search's matches: the closed-form pose nearest the truth, and how many lie within 5 mm and 5 deg.

    python benchmarks/image_truth_key.py --renderer CAL.npz --objects ../shared/data/meshes/mug/mug.ply -n 40 \\
        --pairs 8 11 21 28
"""

from __future__ import annotations

import argparse

import numpy as np


def location_pair_mismatch(left, right, i, j, separation, angles, config) -> np.ndarray:
    """The key-test parts (in tolerances) of location pair (i, j) against a measured key, as `key_matches` computes
    them: (nL, nR), separation, (d, nL), (d, nR)."""
    from yoto.geometry import normalize
    from yoto.pose.solver import direction_angles

    n_left, n_right = normalize(left.n_object[i]), normalize(right.n_object[j])
    offset = right.p_object[j] - left.p_object[i]
    distance = float(np.linalg.norm(offset))
    blur = left.blur_m[i] + right.blur_m[j]
    key = direction_angles(offset, n_left, n_right)
    turn_left, turn_right = left.normal_blur_rad(config)[i], right.normal_blur_rad(config)[j]
    variance = config.angle_tolerance_rad**2
    turn2 = (blur / max(separation, 1e-3)) ** 2
    return np.array(
        [
            abs(key[2] - angles[2]) / np.sqrt(variance + turn_left**2 + turn_right**2),
            abs(distance - separation) / np.hypot(config.distance_tolerance_m, blur),
            abs(key[0] - angles[0]) / np.sqrt(variance + turn_left**2 + turn2),
            abs(key[1] - angles[1]) / np.sqrt(variance + turn_right**2 + turn2),
        ]
    )


def truth_key_report(model, pair, candidates, T_world_object, p_true, config) -> list[str]:
    """Lines describing how one measured pair's key and shapes compare with the truth's, and how the search's tests
    treat the truth."""
    from yoto.contacts import SIDES, contact_in_world
    from yoto.pose.hypotheses import pose_distances
    from yoto.pose.search import contact_locations, contact_shape, search_poses, surface_samples, thin
    from yoto.pose.solver import direction_angles

    surface = surface_samples(model, config.samples)
    rotation, translation = T_world_object[:3, :3], T_world_object[:3, 3]
    n_true = {side: model.aggregated_normal(p_true[side]) for side in SIDES}
    true_offset = p_true["right"] - p_true["left"]
    true_separation = float(np.linalg.norm(true_offset))
    true_angles = direction_angles(true_offset, n_true["left"], n_true["right"])
    world = {side: contact_in_world(pair.contact(side)) for side in SIDES}
    offset = world["right"].p_world - world["left"].p_world
    separation = float(np.linalg.norm(offset))
    angles = direction_angles(offset, world["left"].n_world, world["right"].n_world)
    lines = [
        f"key: separation {separation * 1e3:.2f} mm ({(separation - true_separation) * 1e3:+.2f}), angle errors "
        f"(d,nL) (d,nR) (nL,nR) {np.array2string(np.degrees(angles - true_angles), precision=1)} deg"
    ]
    locations = {}
    for side in SIDES:
        n_object = rotation.T @ world[side].n_world
        p_object = rotation.T @ (world[side].p_world - translation)
        shape = contact_shape(
            pair.contact(side).points_sensor, world[side].p_sensor, world[side].n_sensor, config.samples
        )
        tolerance = (config.curvature_floor + np.abs(shape.curvatures[0]).max()) * (
            config.curvature_share + min(float(shape.rms_m[0]), 1e-3) / config.curvature_residual_scale_m
        )
        near = np.argsort(np.linalg.norm(surface.points_object - p_true[side], axis=1))[:3]
        curvatures = surface.shapes.curvatures[near]
        passing = (np.abs(curvatures - shape.curvatures[0]) <= tolerance).all(axis=1)
        angle = np.degrees(np.arccos(np.clip(n_object @ n_true[side], -1.0, 1.0)))
        lines.append(
            f"{side}: normal {angle:.1f} deg off, centre {np.linalg.norm(p_object - p_true[side]) * 1e3:.2f} mm off; "
            f"curvatures {np.array2string(shape.curvatures[0], precision=1)} 1/m (fit {shape.rms_m[0] * 1e6:.0f} um, "
            f"tolerance {tolerance:.1f}); the 3 samples nearest the truth: {int(passing.sum())} pass"
        )
        locations[side] = contact_locations(surface, shape, candidates[side], config)
    left, right = locations["left"], locations["right"]
    spacing = surface.spacing_m
    while len(left.p_object) * len(right.p_object) > config.pair_budget:  # the search's own thinning
        spacing *= 1.5
        if len(left.p_object) >= len(right.p_object):
            left = thin(left, spacing)
        else:
            right = thin(right, spacing)
    nearest_left = np.argsort(np.linalg.norm(left.p_object - p_true["left"], axis=1))[:6]
    nearest_right = np.argsort(np.linalg.norm(right.p_object - p_true["right"], axis=1))[:6]
    parts = min(
        (
            location_pair_mismatch(left, right, i, j, separation, angles, config)
            for i in nearest_left
            for j in nearest_right
        ),
        key=lambda p: float(p.max()),
    )
    lines.append(
        f"key test at the truth (thinned to {spacing * 1e3:.1f} mm): mismatch {parts.max():.2f} "
        f"(nL,nR) {parts[0]:.2f} separation {parts[1]:.2f} (d,nL) {parts[2]:.2f} (d,nR) {parts[3]:.2f}"
    )
    shapes = {
        side: contact_shape(
            pair.contact(side).points_sensor, world[side].p_sensor, world[side].n_sensor, config.samples
        )
        for side in SIDES
    }
    matches = search_poses(model, world, shapes, candidates, config)
    distance, angle = pose_distances(matches.T_world_object, T_world_object, model.symmetry)
    best = int(np.argmin(distance / 0.005 + np.degrees(angle) / 5.0))
    within = int(np.count_nonzero((distance < 0.005) & (np.degrees(angle) < 5.0)))
    lines.append(
        f"search: {len(matches)} matches, nearest the truth {distance[best] * 1e3:.1f} mm / "
        f"{np.degrees(angle[best]):.1f} deg, {within} within 5 mm and 5 deg"
    )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--renderer", required=True, help="calibration file (its optical model) or shading[:SEED]")
    parser.add_argument("--objects", nargs="+", required=True)
    parser.add_argument("-n", type=int, default=40, help="pairs per object (the benchmark's, seed 7)")
    parser.add_argument("--pairs", type=int, nargs="*", help="only these pair indices")
    args = parser.parse_args()

    from yoto.contacts import SIDES
    from yoto.evaluation.bench import BenchConfig, pairs_via_images, resolve_object, simulate_benchmark_pairs
    from yoto.localize import make_localizer
    from yoto.pose.pipeline import localize_contacts

    bench = BenchConfig(num_pairs=args.n, image_calibration=args.renderer)
    search_config = bench.pose_config("full").search_config
    localizer = make_localizer("match")
    for name in args.objects:
        model = resolve_object(name, None)
        simulated = [s for s in simulate_benchmark_pairs(model, bench) if not args.pairs or s.index in args.pairs]
        for clean, image in zip(simulated, pairs_via_images(simulated, bench)):
            T_world_object = clean.pair.T_world_mesh_true @ model.T_mesh_object
            p_true = {side: np.asarray(clean.contacts[side].p_object) for side in SIDES}
            print(f"## {model.name} pair {clean.index}")
            for label, pair in (("clean", clean.pair), ("image", image.pair)):
                if any(len(pair.contact(side).points_sensor) == 0 for side in SIDES):
                    print(f"  {label}: no contact in a frame")
                    continue
                candidates = localize_contacts(pair, model, localizer)[0]
                for line in truth_key_report(model, pair, candidates, T_world_object, p_true, search_config):
                    print(f"  {label} {line}")


if __name__ == "__main__":
    main()
