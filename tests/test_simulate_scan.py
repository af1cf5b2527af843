"""Simulated phone scans: bounded surface error, exact scale error, determinism, the CLI."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh

from yoto.cli import main
from yoto.simulate.scan import ScanConfig, degrade_mesh

o3d = pytest.importorskip("open3d")

# A coarse resolution keeps the reconstruction fast; the error bounds scale with the noise, not the resolution.
CONFIG = ScanConfig(resolution_m=0.002, noise_std_m=0.0003, holes=3, hole_radius_m=0.004, scale_error=0.008)


@pytest.fixture(scope="module")
def pebble():
    """A 60 x 44 x 36 mm ellipsoid with a few mm-scale bumps (fine detail a scan smooths away)."""
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    directions = mesh.vertices / np.linalg.norm(mesh.vertices, axis=1, keepdims=True)
    bumps = 0.03 * np.sin(9 * directions[:, 0]) * np.sin(7 * directions[:, 1])
    mesh.vertices = directions * (1.0 + bumps[:, None]) * np.array([0.030, 0.022, 0.018])
    return mesh


def surface_distances(source: trimesh.Trimesh, query_mesh: trimesh.Trimesh, count: int = 20_000) -> np.ndarray:
    """Distances from area-uniform samples of `query_mesh` to the surface of `source` (metres)."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(source.vertices.astype(np.float32)), o3d.core.Tensor(source.faces.astype(np.uint32))
    )
    samples, _ = trimesh.sample.sample_surface(query_mesh, count, seed=0)
    return scene.compute_distance(o3d.core.Tensor(samples.astype(np.float32))).numpy()


def unscaled(scan: trimesh.Trimesh, factor: float) -> trimesh.Trimesh:
    centre = np.array(scan.metadata["yoto_scan"]["scale_centre_m"])
    return trimesh.Trimesh(centre + (scan.vertices - centre) / factor, scan.faces, process=False)


def test_scan_error_is_within_the_configured_bounds(pebble):
    scan = degrade_mesh(pebble, CONFIG, np.random.default_rng(0))
    assert scan.is_watertight and len(scan.faces) > 1000
    restored = unscaled(scan, 1.0 + CONFIG.scale_error)
    to_source = surface_distances(pebble, restored)
    to_scan = surface_distances(restored, pebble)
    # Mean surface distance of the order of the noise; no part of either surface strays far (Hausdorff).
    assert 0.3 * CONFIG.noise_std_m < to_source.mean() < 1.5 * CONFIG.noise_std_m
    assert max(to_source.max(), to_scan.max()) < 6 * CONFIG.noise_std_m + 0.5 * CONFIG.hole_radius_m
    # Without undoing the scale error the scan is measurably further off.
    assert surface_distances(pebble, scan).mean() > to_source.mean() + 0.05e-3


def test_scale_error_is_as_configured(pebble):
    for scale_error in (0.008, -0.005):
        config = dataclasses.replace(CONFIG, scale_error=scale_error)
        scan = degrade_mesh(pebble, config, np.random.default_rng(1))
        # Zero-mean noise and a light smoothing leave the volume nearly unchanged: the cube root of the
        # volume ratio is the scale factor.
        measured = (scan.volume / pebble.volume) ** (1 / 3)
        assert measured == pytest.approx(1.0 + scale_error, abs=0.001)


def test_scan_is_deterministic_for_a_seed(pebble):
    config = dataclasses.replace(CONFIG, resolution_m=0.003)
    first = degrade_mesh(pebble, config, np.random.default_rng(4))
    second = degrade_mesh(pebble, config, np.random.default_rng(4))
    other = degrade_mesh(pebble, config, np.random.default_rng(5))
    assert np.array_equal(first.vertices, second.vertices) and np.array_equal(first.faces, second.faces)
    assert len(other.vertices) != len(first.vertices) or not np.allclose(other.vertices, first.vertices)


def test_scan_cli_writes_a_mesh(pebble, tmp_path, capsys):
    source = tmp_path / "pebble.ply"
    pebble.export(source)
    out = tmp_path / "scan.ply"
    args = ["simulate", "scan", str(source), "--out", str(out), "--resolution-mm", "3", "--scale-error", "0.01"]
    assert main(args) == 0
    scan = trimesh.load(out, process=False)
    assert len(scan.faces) > 500
    assert (scan.volume / pebble.volume) ** (1 / 3) == pytest.approx(1.01, abs=0.003)
    assert "+1.00 %" in capsys.readouterr().out
    assert main(["simulate", "scan", str(source), "--out", str(tmp_path / "scan.xyz")]) == 2
