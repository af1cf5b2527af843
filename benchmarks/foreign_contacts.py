"""Contact pairs made by another program: do they localize and pose as well as YOTO's own simulator's?

Every other benchmark feeds the pose stage contacts from YOTO's simulator (`yoto.simulate.press` + `gel`). This one
writes SPEC contact-pair files (JSON + PLY, "Dual contact") with a generator of its own, written from SPEC alone
and deliberately unlike YOTO's: it does not import `yoto.simulate`. Per pair: a random object pose; two contacts at
surface points drawn by area, the approach along the reversed face normal tilted up to 8 deg, the pad centred up to
1.5 mm off the point, a random roll; a grid of rays cast through the pad plane into the mesh (Open3D, `yoto.raycast`);
the sensor moved along its z until the object's deepest point lies the indentation behind the gel plane. What the
pad reads is the raw penetration (a rigid pad: a sharp rim) or, with `gel_m`, the penetration spread by an
exponential kernel (not YOTO's Gaussian). A contact is refused when the target is not in it, when it covers less
than 1.5 mm^2, crosses the pad from border to border, or when a mesh vertex lies inside a box behind the pad (the
sensor body); the two approaches must not be coaxial. Ground truth (SPEC): the object surface point nearest the
centroid of the noise-free contact patch. The reported sensor poses carry a calibration error (1 mm / 1 deg mean, as
`yoto bench`) and are written as float32 (not exactly orthonormal). Settings (`SETTINGS`, `--settings`) vary the
pitch and grid (320x240 at 0.0634 mm; 640x480 at half of it; a 0.1 mm grid), the gel, white or correlated noise,
whole-pad clouds (every pixel, the untouched gel at z = 0 + noise) or contact points only (the noise-free contact's
pixels with noisy heights, so some lie above z = 0), random decimation (to 3000 or 1500 points), indentation, ascii
or binary PLY. Results: docs/journal/formats.md, "Stop 15".

Each pair is written to a folder and read back with `yoto.contacts.read_contact_pair`, then posed by
`estimate_pose` with the matched filter (`match`) and the default pose stage, as `yoto pose` would. The same
objects' pairs from YOTO's own simulator (as `yoto bench` simulates them: its default scenario, the same calibration
error), written and read the same way, are the first row of each object (`yoto`). Default objects: fruit, figurine,
tool and ../shared/data/meshes/{mug,cracker_box,banana}; lemon, bunny and drill were held out of every choice.

Prints one table: per object and setting, poses right (5 mm / 5 deg) of N, the localization error of the
matched filter's first candidate (median and p90 over both contacts, mm), the median pose error (mm / deg), pose
stage failures, and the median number of points per cloud as read (a whole pad's: its contact); then the same
pooled over the objects, and the process's CPU time; `--json` writes the per-pair figures.

    python benchmarks/foreign_contacts.py                       # the default objects and settings, 10 pairs each
    python benchmarks/foreign_contacts.py --settings all        # every setting (about 11 CPU minutes)
    python benchmarks/foreign_contacts.py --objects $M/lemon/lemon.ply $M/bunny/bunny.ply $M/drill/drill.ply
    python benchmarks/foreign_contacts.py --settings rigid whole_pad --objects fruit -n 20 --keep DIR
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage, signal

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's yoto, not an installed one

M = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "meshes"
DEFAULT_OBJECTS = ["fruit", "figurine", "tool", str(M / "mug/mug.ply"), str(M / "cracker_box/cracker_box.ply"),
                   str(M / "banana/banana.ply")]  # fmt: skip
HELD_OUT = [str(M / "lemon/lemon.ply"), str(M / "bunny/bunny.ply"), str(M / "drill/drill.ply")]


@dataclass(frozen=True)
class Setting:
    """How the foreign generator makes and writes a tactile cloud."""

    columns: int = 320
    rows: int = 240
    pitch_m: float = 6.34e-5  # grid spacing on the pad
    gel_m: float = 0.0  # exponential sink-in length of the gel around the contact (0: a rigid pad, raw penetration)
    noise_m: float = 0.0  # height noise, standard deviation
    noise_length_m: float = 0.0  # its correlation length (0: white per point)
    whole_pad: bool = False  # every grid point (the untouched gel at z = 0 + noise), else the contact's only
    keep: int = 0  # a random subset of this many points (0: all)
    depth_m: tuple[float, float] = (0.0005, 0.0015)  # indentation, uniform
    contact_m: float = 2e-5  # contact-only clouds: grid points whose noise-free penetration exceeds this
    ply: str = "binary"  # "binary" (float32 little endian) or "ascii"


SETTINGS = {
    "rigid": Setting(),
    "rigid_noisy": Setting(noise_m=2e-5),
    "gel": Setting(gel_m=0.0005, noise_m=1e-5),
    "noisy30": Setting(gel_m=0.0005, noise_m=3e-5),
    "correlated": Setting(gel_m=0.0005, noise_m=2e-5, noise_length_m=0.001),
    "whole_pad": Setting(gel_m=0.0005, noise_m=1e-5, whole_pad=True),
    "whole_pad_clean": Setting(whole_pad=True, ply="ascii"),
    "whole_pad_corr": Setting(gel_m=0.0005, noise_m=3e-5, noise_length_m=0.001, whole_pad=True),
    "half_pitch": Setting(columns=640, rows=480, pitch_m=3.17e-5, gel_m=0.0005, noise_m=1e-5),
    "grid_0.1mm": Setting(columns=203, rows=152, pitch_m=1e-4, gel_m=0.0005, noise_m=1e-5),
    "decimated": Setting(gel_m=0.0005, noise_m=1e-5, keep=3000),
    "decimated_1500": Setting(gel_m=0.0005, noise_m=1e-5, keep=1500),
    "whole_decimated": Setting(gel_m=0.0005, noise_m=1e-5, whole_pad=True, keep=5000),
    "shallow": Setting(gel_m=0.0005, noise_m=1e-5, depth_m=(0.0003, 0.0005)),
    "deep": Setting(depth_m=(0.0015, 0.002)),
}
# The default run (about 5 minutes on one quiet core); `--settings all` runs every setting.
DEFAULT_SETTINGS = ["rigid_noisy", "gel", "correlated", "whole_pad", "grid_0.1mm", "decimated"]

BODY_HALF_M = (0.016, 0.014)  # the sensor body's box behind the pad, half its x and y size ...
BODY_DEPTH_M = 0.04  # ... and its depth behind the gel plane
MIN_AREA_M2 = 1.5e-6
MAX_TILT_DEG = 8.0
MAX_OFFSET_M = 0.0015
CALIBRATION_MM, CALIBRATION_DEG = 1.0, 1.0


def _rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random rotation (a unit quaternion from four normals)."""
    x, y, z, w = rng.normal(size=4) / 1.0
    n = np.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _frame_with_z(z: np.ndarray, roll: float) -> np.ndarray:
    """A rotation whose third column is the unit `z`, turned by `roll` about it."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    return np.stack([c * x + s * y, -s * x + c * y, z], axis=1)


class ForeignGenerator:
    """Presses of a pad into one mesh (mesh file's frame), from SPEC alone."""

    def __init__(self, vertices_mesh: np.ndarray, faces: np.ndarray, setting: Setting):
        import trimesh

        from yoto.raycast import MeshRaycaster

        self.mesh = trimesh.Trimesh(vertices=vertices_mesh, faces=faces, process=False)
        self.rays = MeshRaycaster(vertices_mesh, faces, "the foreign contact generator")
        self.setting = setting
        s = setting
        x = (np.arange(s.columns) - (s.columns - 1) / 2.0) * s.pitch_m
        y = (np.arange(s.rows) - (s.rows - 1) / 2.0) * s.pitch_m
        self.grid_x, self.grid_y = np.meshgrid(x, y)  # (rows, columns), x along columns, y along rows
        self.kernel = None
        if s.gel_m > 0:
            reach = int(np.ceil(4 * s.gel_m / s.pitch_m))
            offsets = np.arange(-reach, reach + 1) * s.pitch_m
            r = np.hypot(*np.meshgrid(offsets, offsets))
            kernel = np.exp(-r / s.gel_m)
            self.kernel = kernel / kernel.sum()

    def contact(self, T_world_mesh: np.ndarray, rng: np.random.Generator, noise_rng: np.random.Generator):
        """One reachable contact: (T_world_sensor, cloud points sensor frame, p_mesh truth, approach) or None. The
        geometry draws from `rng`, the noise and the decimation from `noise_rng` (settings that differ only in
        those read the same presses)."""
        s = self.setting
        points, face = self.mesh.sample(1, return_index=True, seed=int(rng.integers(2**31)))
        p_mesh, n_mesh = points[0], self.mesh.face_normals[face[0]]
        tilt_axis = np.cross(n_mesh, rng.normal(size=3))
        approach = _axis_angle(tilt_axis, np.radians(MAX_TILT_DEG) * np.sqrt(rng.uniform())) @ -n_mesh
        R_mesh_sensor = _frame_with_z(approach, rng.uniform(0, 2 * np.pi))
        offset = MAX_OFFSET_M * np.sqrt(rng.uniform()) * np.array([np.cos(a := rng.uniform(0, 2 * np.pi)), np.sin(a)])
        origin = p_mesh - R_mesh_sensor[:, :2] @ offset  # the pad centre, on the target's plane
        start = -0.15
        local = np.stack([self.grid_x.ravel(), self.grid_y.ravel(), np.full(self.grid_x.size, start)], axis=1)
        hits = self.rays.cast(origin + local @ R_mesh_sensor.T, approach)
        if not hits.hit.any():
            return None
        z_obj = np.where(hits.hit, start + hits.t_hit, np.inf).reshape(self.grid_x.shape)
        front = z_obj.min()
        depth = rng.uniform(*s.depth_m)
        if hits.back_face[np.isfinite(hits.t_hit) & (start + hits.t_hit < front + depth + 0.002)].any():
            return None  # an open mesh or a thin wall where the pad presses
        z_pressed = z_obj - front - depth  # the sensor moved along its z by front + depth
        penetration = np.where(np.isfinite(z_pressed), np.maximum(-z_pressed, 0.0), 0.0)
        gel = penetration
        if self.kernel is not None:
            reach = len(self.kernel) // 2
            padded = np.pad(penetration, reach, mode="edge")  # the surface goes on a little beyond the pad
            gel = np.maximum(penetration, signal.fftconvolve(padded, self.kernel, mode="valid"))
        touching = (penetration > s.contact_m) & (gel - penetration < 1e-7)
        if touching.sum() * s.pitch_m**2 < MIN_AREA_M2:
            return None
        centre = (np.abs(self.grid_y[:, 0] + offset[1]).argmin(), np.abs(self.grid_x[0] + offset[0]).argmin())
        if not touching[centre]:
            return None  # the target is not where the pad touches (a concavity at the pad's scale)
        if (touching[:, 0].any() and touching[:, -1].any()) or (touching[0].any() and touching[-1].any()):
            return None  # an edge or a ridge across the pad
        T_mesh_sensor = np.eye(4)
        T_mesh_sensor[:3, :3] = R_mesh_sensor
        T_mesh_sensor[:3, 3] = origin + (front + depth) * approach
        vertices_sensor = (self.mesh.vertices - T_mesh_sensor[:3, 3]) @ R_mesh_sensor
        inside_body = (
            (np.abs(vertices_sensor[:, 0]) < BODY_HALF_M[0])
            & (np.abs(vertices_sensor[:, 1]) < BODY_HALF_M[1])
            & (vertices_sensor[:, 2] < -depth - 3e-4)
            & (vertices_sensor[:, 2] > -BODY_DEPTH_M)
        )
        if inside_body.any():
            return None
        heights = -gel
        patch = np.stack([self.grid_x[touching], self.grid_y[touching], heights[touching]], axis=1)
        centroid_mesh = T_mesh_sensor[:3, :3] @ patch.mean(axis=0) + T_mesh_sensor[:3, 3]
        truth_mesh = self.rays.closest_points(centroid_mesh[None])[0]
        noisy = heights + self._noise(noise_rng)
        keep = np.ones_like(touching) if s.whole_pad else touching
        cloud = np.stack([self.grid_x[keep], self.grid_y[keep], noisy[keep]], axis=1)
        if s.keep and len(cloud) > s.keep:
            cloud = cloud[np.sort(noise_rng.choice(len(cloud), s.keep, replace=False))]
        return T_world_mesh @ T_mesh_sensor, cloud, truth_mesh, -approach

    def _noise(self, rng: np.random.Generator) -> np.ndarray:
        s = self.setting
        if s.noise_m == 0:
            return np.zeros(self.grid_x.shape)
        white = rng.normal(size=self.grid_x.shape)
        if s.noise_length_m > 0:
            white = ndimage.gaussian_filter(white, s.noise_length_m / s.pitch_m, mode="wrap")
            white /= white.std()
        return s.noise_m * white

    def pair(self, rng: np.random.Generator, noise_rng: np.random.Generator, tries: int = 400):
        """(T_world_mesh, [left, right] contacts) of a random object pose, or None."""
        T_world_mesh = np.eye(4)
        T_world_mesh[:3, :3] = _rotation(rng)
        T_world_mesh[:3, 3] = rng.uniform(-0.2, 0.2, 3) + np.array([0.0, 0.0, 0.5])
        found = []
        for _ in range(tries):
            contact = self.contact(T_world_mesh, rng, noise_rng)
            if contact is None:
                continue
            if found:
                first = found[0]
                n_a = T_world_mesh[:3, :3] @ first[3]
                n_b = T_world_mesh[:3, :3] @ contact[3]
                d = contact[0][:3, 3] - first[0][:3, 3]
                if np.linalg.norm(d) < 0.02:
                    continue  # the sensor bodies would overlap
                singular = np.linalg.svd(np.stack([d / np.linalg.norm(d), n_a, n_b], axis=1), compute_uv=False)
                if singular[1] / singular[0] < 0.15:
                    continue  # coaxial approaches: the rotation about their axis is free
            found.append(contact)
            if len(found) == 2:
                return T_world_mesh, found
        return None


def _calibration_error(rng: np.random.Generator) -> np.ndarray:
    """A reported-pose error: a random direction at 1 mm mean (half-normal), a random axis at 1 deg mean."""
    error = np.eye(4)
    scale = np.sqrt(np.pi / 2.0)
    error[:3, :3] = _axis_angle(rng.normal(size=3), np.radians(CALIBRATION_DEG) * scale * abs(rng.normal()))
    direction = rng.normal(size=3)
    error[:3, 3] = direction / np.linalg.norm(direction) * CALIBRATION_MM * 1e-3 * scale * abs(rng.normal())
    return error


def _write_ply(path: Path, points: np.ndarray, how: str) -> None:
    """A PLY cloud written by hand: float32 binary little endian, or ascii with 7 significant digits."""
    if how == "ascii":
        header = f"ply\nformat ascii 1.0\nelement vertex {len(points)}\n"
        header += "property float x\nproperty float y\nproperty float z\nend_header\n"
        body = "\n".join(" ".join(f"{v:.7g}" for v in row) for row in points.astype(np.float32).tolist())
        path.write_text(header + body + "\n")
        return
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
    header += "property float x\nproperty float y\nproperty float z\nend_header\n"
    path.write_bytes(header.encode() + points.astype("<f4").tobytes())


def write_foreign_pair(folder: Path, index: int, name: str, generated, setting: Setting, rng) -> Path:
    """The SPEC pair file of a generated pair (sensor poses with their calibration error, float32)."""
    T_world_mesh, contacts = generated
    record: dict = {"object": name}
    for side, (T_world_sensor, cloud, _, _) in zip(("left", "right"), contacts, strict=True):
        ply = f"pair_{index:04d}_{side}.ply"
        _write_ply(folder / ply, cloud, setting.ply)
        reported = (T_world_sensor @ _calibration_error(rng)).astype(np.float32)
        record[side] = {"points": ply, "T_world_sensor": reported.tolist()}
    record["ground_truth"] = {
        "T_world_object": T_world_mesh.tolist(),
        "left_p_object": contacts[0][2].tolist(),
        "right_p_object": contacts[1][2].tolist(),
    }
    path = folder / f"pair_{index:04d}.json"
    path.write_text(json.dumps(record))
    return path


def evaluate(path: Path, model, localizer, config) -> dict:
    """Read a pair file as `yoto pose` does and pose it: errors against its ground truth."""
    from yoto.contacts import SIDES, read_contact_pair
    from yoto.errors import YotoError
    from yoto.evaluation.bench import symmetric_errors
    from yoto.geometry import transform_points
    from yoto.pose.pipeline import estimate_pose

    pair = read_contact_pair(path)
    points = [len(pair.contact(side).points_sensor) for side in SIDES]
    try:
        estimate = estimate_pose(pair, model, localizer, config)
    except YotoError as exc:
        return {"failed": str(exc), "points": points}
    errors = symmetric_errors(model, estimate.T_world_mesh, pair.T_world_mesh_true)
    localization = [
        1000.0 * float(np.linalg.norm(
            transform_points(model.T_mesh_object, estimate.candidates[side][0].p_object) - pair.p_mesh_true[side]
        ))
        for side in SIDES
    ]  # fmt: skip
    return {**errors, "localization_mm": localization, "points": points, "confidence": float(estimate.confidence)}


def yoto_pairs(model, folder: Path, count: int, seed: int) -> list[Path]:
    """YOTO's own simulator's pairs (the benchmark's calibration error), written as pair files."""
    from yoto.contacts import write_contact_pair
    from yoto.simulate.scenarios import PairSimulator, ScenarioConfig

    scenario = ScenarioConfig(
        calibration_translation_m=CALIBRATION_MM / 1000.0, calibration_rotation_rad=np.radians(CALIBRATION_DEG)
    )
    simulator = PairSimulator(model, scenario)
    paths = []
    for index in range(count):
        path = folder / f"pair_{index:04d}.json"
        write_contact_pair(path, simulator.pair(seed, index).pair)
        paths.append(path)
    return paths


def foreign_pairs(model, setting: Setting, folder: Path, count: int, seed: int) -> list[Path]:
    generator = ForeignGenerator(model.mesh_vertices_mesh, model.mesh_faces, setting)
    paths = []
    for index in range(count):
        rng, noise_rng, calibration_rng = (np.random.default_rng([seed, index, stream]) for stream in range(3))
        generated = None
        while generated is None:
            generated = generator.pair(rng, noise_rng)
        paths.append(write_foreign_pair(folder, index, model.name, generated, setting, calibration_rng))
    return paths


def summary(rows: list[dict]) -> str:
    done = [r for r in rows if "failed" not in r]
    right = sum(r["translation_mm"] < 5.0 and r["rotation_deg"] < 5.0 for r in done)
    localization = np.array([e for r in done for e in r["localization_mm"]]) if done else np.zeros(1)
    translation = np.median([r["translation_mm"] for r in done]) if done else np.nan
    rotation = np.median([r["rotation_deg"] for r in done]) if done else np.nan
    points = int(np.median([p for r in rows for p in r["points"]]))
    return (
        f"{right:>3d} / {len(rows):<3d} | {np.median(localization):6.2f} | {np.percentile(localization, 90):6.2f} | "
        f"{translation:5.2f} / {rotation:5.2f} | {len(rows) - len(done)} | {points}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--objects", nargs="+", default=DEFAULT_OBJECTS)
    parser.add_argument("--settings", nargs="+", default=DEFAULT_SETTINGS, choices=[*SETTINGS, "all"])
    parser.add_argument("-n", type=int, default=10, help="pairs per object and setting")
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--no-yoto", action="store_true", help="leave out YOTO's own simulator's row")
    parser.add_argument("--workspace", default=os.environ.get("YOTO_WORKSPACE"))
    parser.add_argument("--keep", help="write the pair files under this folder (else a temporary one, removed)")
    parser.add_argument("--json", help="write every pair's figures here")
    args = parser.parse_args()
    if "all" in args.settings:
        args.settings = list(SETTINGS)

    from yoto.evaluation.bench import resolve_object
    from yoto.localize import make_localizer
    from yoto.pose.pipeline import PoseConfig

    config = PoseConfig(suggest_next_touch=False)
    localizer = make_localizer("match")
    table, pooled, record = [], {}, {}
    tick = time.process_time()
    with tempfile.TemporaryDirectory(prefix="foreign_contacts_") as scratch:  # ~0.7 MB a pair: removed when read
        root = Path(args.keep) if args.keep else Path(scratch)
        for spec in args.objects:
            model = resolve_object(spec, args.workspace)
            sources = ([] if args.no_yoto else ["yoto"]) + args.settings
            for source in sources:
                folder = root / model.name / source
                folder.mkdir(parents=True, exist_ok=True)
                if source == "yoto":
                    paths = yoto_pairs(model, folder, args.n, args.seed)
                else:
                    paths = foreign_pairs(model, SETTINGS[source], folder, args.n, args.seed)
                rows = [evaluate(path, model, localizer, config) for path in paths]
                if not args.keep:
                    shutil.rmtree(folder)
                record[f"{model.name}/{source}"] = rows
                pooled.setdefault(source, []).extend(rows)
                table.append(f"| {model.name} | {source} | {summary(rows)} |")
                print(table[-1], flush=True)
    header = (
        "| object | contacts | right | loc. median mm | loc. p90 mm | pose median mm / deg | failed | points |\n"
        "|---|---|---|---|---|---|---|---|"
    )
    print(f"\nForeign contact pairs, {args.n} per object and setting, seed {args.seed}, match + default pose stage")
    print(header)
    print("\n".join(table))
    print("\nPooled over the objects:")
    print(header)
    for source, rows in pooled.items():
        print(f"| all | {source} | {summary(rows)} |")
    print(f"\nCPU {time.process_time() - tick:.0f} s" + (f"; pair files under {args.keep}" if args.keep else ""))
    if args.json:
        Path(args.json).write_text(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
