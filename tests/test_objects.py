"""Object models: mesh loading and repair, units, the PCA canonical frame, blocks, the model file."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import trimesh
from conftest import TOL, shared_data

from yoto.errors import InputError
from yoto.geometry import make_transform, random_rotations, rotation_between, transform_points
from yoto.objects.build import build_object, load_object_model
from yoto.objects.mesh import load_mesh
from yoto.objects.model import ObjectModel, ObjectModelConfig, build_object_model, canonical_frame

SMALL = ObjectModelConfig(num_points=20_000)


def _box_mesh(extents=(0.12, 0.06, 0.03)) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents)


def _export(mesh: trimesh.Trimesh, path):
    mesh.export(path)
    return path


def test_canonical_frame_axes_follow_the_variances(rng):
    """An elongated cloud in a random pose: x along the longest axis, z along the shortest, right-handed."""
    points_local = rng.normal(size=(50_000, 3)) * np.array([0.05, 0.02, 0.005])
    rotation = random_rotations(rng, 1)[0]
    offset = np.array([0.3, -0.1, 0.2])
    T_mesh_object = canonical_frame(points_local @ rotation.T + offset)
    axes = T_mesh_object[:3, :3]
    assert np.allclose(T_mesh_object[:3, 3], offset, atol=1e-3)
    assert abs(axes[:, 0] @ rotation[:, 0]) > 0.999  # longest
    assert abs(axes[:, 2] @ rotation[:, 2]) > 0.999  # shortest
    assert np.allclose(axes.T @ axes, np.eye(3), atol=1e-12) and np.linalg.det(axes) > 0
    # Signs follow the mesh frame's +z and +x.
    assert axes[2, 2] >= 0 and axes[0, 0] >= 0


def test_object_model_of_a_box(tmp_path):
    mesh = _box_mesh()
    model = build_object_model(mesh, "box", SMALL)
    # Canonical extents sort the box's sides: x longest, z shortest (PCA of samples tilts axes by < 1 deg).
    assert np.allclose(np.ptp(model.points_object, axis=0), [0.12, 0.06, 0.03], atol=2e-3)
    # Normals are outward unit vectors: on a box centred at the origin they point away from it.
    normals = model.normals_object.astype(np.float64)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    assert (np.einsum("ij,ij->i", normals, model.points_object) > 0).mean() > 0.99
    # On the 6x3x3 grid only the four cells inside the box, (1..4, 1, 1), hold no surface.
    assert model.num_blocks == 50
    valid = {tuple(cell) for cell in model.block_cells}
    assert {(ix, 1, 1) for ix in range(1, 5)}.isdisjoint(valid) and len(valid) == 50
    # Block normals point away from the centre and the standardising rotation maps -n to +z.
    for normal, centre, rotation in zip(model.block_normals_object, model.block_centres_object, model.block_rotations):
        assert normal @ centre > 0
        assert np.allclose(rotation @ -normal, [0, 0, 1], atol=1e-12)
    # Points in the mesh frame come back onto the box's surface.
    points_mesh = transform_points(model.T_mesh_object, model.points_object.astype(np.float64))
    assert np.abs(np.abs(points_mesh) - np.array([0.06, 0.03, 0.015])).min(axis=1).max() < 1e-6

    path = model.save(tmp_path / "box.npz")
    loaded = ObjectModel.load(path)
    assert loaded.name == "box" and loaded.fingerprint == model.fingerprint
    assert np.array_equal(loaded.point_block, model.point_block)
    assert np.allclose(loaded.T_mesh_object, model.T_mesh_object, atol=TOL["float"])


def test_aggregated_normal_and_block_lookup(builtin_models):
    model = builtin_models["fruit"]
    index = 1234
    p = model.points_object[index].astype(np.float64)
    normal = model.aggregated_normal(p)
    assert normal @ model.normals_object[index] > 0.95
    assert model.block_of_points(p)[0] == model.point_block[index]


def test_model_is_independent_of_the_mesh_pose(rng):
    """The same object in two mesh poses gives the same canonical cloud up to the PCA axes' signs."""
    mesh = trimesh.creation.cone(radius=0.03, height=0.09, sections=64)
    model_a = build_object_model(mesh, "a", SMALL)
    moved = mesh.copy()
    moved.apply_transform(
        make_transform(rotation_between(np.array([0, 0, 1.0]), np.array([0.2, 0.1, 1.0])), [0.5, 0, 0])
    )
    model_b = build_object_model(moved, "b", SMALL)
    extents_a, extents_b = np.ptp(model_a.points_object, axis=0), np.ptp(model_b.points_object, axis=0)
    assert np.allclose(extents_a, extents_b, atol=1.5e-3)


def test_load_mesh_units_and_errors(tmp_path):
    mesh_mm = _box_mesh()
    mesh_mm.apply_scale(1000.0)
    path = tmp_path / "box_mm.stl"
    mesh_mm.export(path)
    with pytest.raises(InputError, match="box_mm.stl: read in m, .* with --units mm it is 120 mm across"):
        load_mesh(path, units="m")
    mesh, _, scale = load_mesh(path, units="mm")
    assert scale == 1e-3 and np.allclose(mesh.extents, [0.12, 0.06, 0.03])
    assert load_mesh(path, units="auto")[2] == 1e-3

    empty = tmp_path / "empty.ply"
    empty.write_text(
        "ply\nformat ascii 1.0\nelement vertex 0\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n"
    )
    with pytest.raises(InputError, match="empty.ply"):
        load_mesh(empty)
    with pytest.raises(InputError, match="unsupported mesh format"):
        load_mesh(tmp_path / "x.txt") if (tmp_path / "x.txt").write_text("x") else None
    with pytest.raises(InputError, match="not found"):
        load_mesh(tmp_path / "missing.obj")
    garbage = tmp_path / "garbage.obj"
    garbage.write_text("this is not a mesh\n")
    with pytest.raises(InputError, match="garbage.obj"):
        load_mesh(garbage)


@pytest.mark.parametrize(
    ("stored_in", "scale_to_file", "read_as", "suggested", "also"),
    [
        ("mm", 1000.0, "m", "mm", "cm"),  # a 75 mm apple saved in millimetres (75 units): cm would be 750 mm
        ("cm", 100.0, "m", "cm", "in"),  # 7.5 units
        ("in", 1 / 0.0254, "m", "in", "cm"),  # 2.95 units: inches, or a 30 mm object in centimetres
        ("m", 1.0, "mm", "m", None),  # 0.075 units read as millimetres
    ],
)
def test_a_mesh_in_the_wrong_unit_names_the_unit_that_fits(
    tmp_path, stored_in, scale_to_file, read_as, suggested, also
):
    """The error suggests the unit giving the size nearest a typical object's (10 cm), then the other plausible ones."""
    apple = trimesh.creation.icosphere(subdivisions=2, radius=0.0375)  # 75 mm across
    apple.apply_scale(scale_to_file)
    path = tmp_path / f"apple_{stored_in}.stl"
    apple.export(path)
    with pytest.raises(InputError, match=f"apple_{stored_in}.stl: read in {read_as}, ") as info:
        load_mesh(path, units=read_as)
    assert f"with --units {suggested} it is 75 mm across" in str(info.value)
    assert (f"--units {also}:" in str(info.value)) == (also is not None)
    mesh, _, _ = load_mesh(path, units=suggested)
    assert np.allclose(mesh.extents, 0.075, rtol=1e-6)


def test_a_flat_mesh_is_refused_naming_the_file(tmp_path):
    """All vertices in one plane (a box of zero thickness, a single quad): a clear error, no numpy warnings;
    a thin plate that is not flat is accepted."""
    for name, mesh in (
        ("flat_box.ply", _box_mesh((0.12, 0.06, 0.0))),
        (
            "quad.obj",
            trimesh.Trimesh([[0, 0, 0], [0.1, 0, 0], [0.1, 0.05, 0.05], [0, 0.05, 0.05]], [[0, 1, 2], [0, 2, 3]]),
        ),
    ):
        path = tmp_path / name
        mesh.export(path)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with pytest.raises(InputError, match=f"{name}: the mesh is flat: all its vertices lie in one plane"):
                load_mesh(path)
            with pytest.raises(InputError, match="the mesh of object 'flat' is flat"):
                build_object_model(mesh, "flat", SMALL)
    plate, report, _ = load_mesh(_export(_box_mesh((0.12, 0.06, 0.0005)), tmp_path / "plate.stl"))
    assert report.watertight and np.allclose(plate.extents, [0.12, 0.06, 0.0005])


def test_repair_reports_what_it_fixed(tmp_path):
    box = _box_mesh()
    # Break it as a scan would: duplicate every vertex (unmerged), add a duplicate face, a sliver, a floater,
    # and flip the winding of a few faces.
    vertices = box.vertices[box.faces].reshape(-1, 3)
    faces = np.arange(len(vertices)).reshape(-1, 3)
    faces[:3] = faces[:3, ::-1]
    faces = np.vstack([faces, faces[5:6], [[0, 0, 1]]])
    floater = trimesh.creation.icosphere(subdivisions=1, radius=0.001)
    vertices = np.vstack([vertices, floater.vertices + 0.2])
    faces = np.vstack([faces, floater.faces + len(box.vertices[box.faces].reshape(-1, 3))])
    path = tmp_path / "broken.ply"
    trimesh.Trimesh(vertices, faces, process=False).export(path)
    mesh, report, _ = load_mesh(path)
    assert report.merged_duplicate_vertices > 0
    assert report.removed_duplicate_faces == 1
    assert report.removed_degenerate_faces == 1
    assert report.removed_small_components == 1
    assert report.fixed_winding
    assert report.watertight and mesh.is_watertight and mesh.volume > 0
    assert np.isclose(mesh.volume, 0.12 * 0.06 * 0.03)


def test_build_object_is_idempotent_and_named_in_errors(tmp_path):
    path = tmp_path / "box.obj"
    _box_mesh().export(path)
    out = build_object(path, "box", SMALL, workspace=tmp_path)
    stamp = out.stat().st_mtime_ns
    assert build_object(path, "box", SMALL, workspace=tmp_path) == out
    assert out.stat().st_mtime_ns == stamp  # kept, not rebuilt
    assert load_object_model("box", tmp_path).name == "box"
    with pytest.raises(InputError, match="no object model named 'nothing'"):
        load_object_model("nothing", tmp_path)
    with pytest.raises(InputError, match="must be letters"):
        build_object(path, "bad name!", SMALL, workspace=tmp_path)


def test_model_file_errors(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not an npz")
    with pytest.raises(InputError, match="bad.npz"):
        ObjectModel.load(bad)


def test_shared_drill_builds_with_the_papers_block_counts():
    """The YCB drill: repaired, watertight, 40-54 valid blocks as in the paper's Table 6."""
    path = shared_data("meshes", "drill", "drill.ply")
    mesh, report, _ = load_mesh(path)
    model = build_object_model(mesh, "drill", ObjectModelConfig(num_points=60_000))
    assert report.watertight
    assert 40 <= model.num_blocks <= 54
    bbox_mm = np.array(model.meta["bbox_object_m"]) * 1000
    assert bbox_mm[0] >= bbox_mm[1] >= bbox_mm[2]


def test_nan_and_non_manifold_meshes(tmp_path, caplog):
    box = _box_mesh()
    vertices = box.vertices.copy()
    vertices[3] = np.nan
    path = tmp_path / "nan.obj"
    path.write_text(
        "".join(f"v {x} {y} {z}\n" for x, y, z in vertices)
        + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in box.faces)
    )
    with pytest.raises(InputError, match="nan.obj: mesh has 1 vertices with NaN"):
        load_mesh(path)

    # A fin: an extra triangle on one of the box's edges makes that edge shared by three faces.
    edge = box.edges_unique[0]
    fin_vertex = box.vertices[edge].mean(axis=0) * 1.5 + np.array([0.0, 0.0, 0.05])
    fin = trimesh.Trimesh(
        np.vstack([box.vertices, fin_vertex]), np.vstack([box.faces, [[edge[0], edge[1], 8]]]), process=False
    )
    path = tmp_path / "fin.ply"
    fin.export(path)
    _, report, _ = load_mesh(path)
    assert report.non_manifold_edges == 1
    with caplog.at_level("WARNING", logger="yoto"):
        build_object(path, "fin", SMALL, workspace=tmp_path)
    assert "fin.ply: 1 non-manifold edges" in caplog.text
