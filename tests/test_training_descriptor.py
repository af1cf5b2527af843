"""Training of the anchor-descriptor network (`cpu` preset): virtual contacts, a tiny run, resume, stage 2."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

torch = pytest.importorskip("torch")

from test_training import write_cut_pairs  # noqa: E402

from yoto.geometry import transform_points  # noqa: E402
from yoto.network.checkpoint import LocalizerCheckpoint  # noqa: E402
from yoto.network.presets import AnchorNetConfig  # noqa: E402
from yoto.objects.model import ObjectModelConfig, build_object_model  # noqa: E402
from yoto.training.config import PRESETS, DescriptorTrainConfig, StageConfig  # noqa: E402
from yoto.training.state import TrainingState  # noqa: E402
from yoto.training.train import train  # noqa: E402
from yoto.training.virtual_contacts import (  # noqa: E402
    VirtualContactConfig,
    press_cloud,
    virtual_contacts,
    virtual_contacts_path,
)
from yoto.workspace import object_model_path  # noqa: E402

TINY = DescriptorTrainConfig(
    network=AnchorNetConfig(rings=6, angles=16, harmonics=4, hidden_dims=(48,), feature_dim=16, anchor_spacing_m=0.004),
    stage1=StageConfig(epochs=8, lr=3e-3, encoder_lr=3e-3),
    stage2=StageConfig(epochs=1, lr=1e-3, encoder_lr=1e-3, real_oversample=3, real_weight=2.0, virtual_fraction=0.5),
    batch_size=48,
    virtual=VirtualContactConfig(count=400, pixel_m=0.0002),
    val_fraction=0.1,
)


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def fruit_workspace(builtin_models, tmp_path_factory) -> Path:
    workspace = tmp_path_factory.mktemp("ws_descriptor")
    builtin_models["fruit"].save(object_model_path("fruit", workspace))
    return workspace


def tiny_descriptor_run(workspace: Path, run: str = "run_a", config: DescriptorTrainConfig = TINY, **kwargs) -> Path:
    run_dir = workspace / "runs" / run
    if not (run_dir / "model.pt").exists():
        train(config, ["fruit"], workspace, run_dir, progress=False, **kwargs)
    return run_dir / "model.pt"


def test_a_virtual_contact_is_the_surface_a_pressed_pad_meets():
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=0.05)
    model = build_object_model(mesh, "sphere", ObjectModelConfig(num_points=20_000))
    rng = np.random.default_rng(3)
    config = VirtualContactConfig(depth_m=(0.001, 0.001), max_tilt_deg=0.0, max_offset_m=0.0)
    target = model.points_object[0].astype(np.float64)
    points, T_object_sensor = press_cloud(model, target, rng, config)
    assert points[:, 2].max() <= 0.0 and points[:, 2].min() == pytest.approx(-0.001, abs=2e-5)
    # A 1 mm press into a 50 mm sphere touches a disc of radius sqrt(2 R d) = 10 mm (a little more on the facets
    # of the tessellated sphere), cut by the pad's 7.6 mm half-height.
    radii = np.hypot(points[:, 0], points[:, 1])
    assert 0.0097 < radii.max() < 0.0105 and np.abs(points[:, 1]).max() < 0.0077
    centre = transform_points(model.T_object_mesh, np.zeros(3))  # the sphere's centre in the object frame
    on_object = transform_points(T_object_sensor, points) - centre
    np.testing.assert_allclose(np.linalg.norm(on_object, axis=1), 0.05, atol=2e-5)
    inward = (centre - target) / np.linalg.norm(centre - target)
    assert T_object_sensor[:3, 2] @ inward > 0.9995  # z into the object, along the (estimated) normal


def test_tiny_run_learns_to_retrieve_anchors_and_writes_a_checkpoint(fruit_workspace):
    path = tiny_descriptor_run(fruit_workspace)
    checkpoint = LocalizerCheckpoint.load(path)
    assert checkpoint.network_config == TINY.network and checkpoint.real_pairs is None
    assert [o.name for o in checkpoint.objects] == ["fruit"] and checkpoint.objects[0].num_blocks > 100
    assert DescriptorTrainConfig.from_dict(checkpoint.train_config) == TINY
    history = [json.loads(line) for line in (path.parent / "log.jsonl").read_text().splitlines()]
    assert len(history) == 8 and history[-1]["train_loss"] < history[0]["train_loss"]
    # About 2 of the fruit's ~1000 anchors lie within 3 mm of a contact: 128 drawn at random hold one a quarter of
    # the time. The tiny run (8 epochs of 360 virtual contacts) finds one three times in four.
    assert history[-1]["val_virtual_recall_at_128"] >= 0.6
    assert history[-1]["val_virtual_recall_at_128"] > history[0]["val_virtual_recall_at_128"]
    assert (path.parent / "curves.png").stat().st_size > 1000


def test_virtual_contacts_are_stored_and_reused(fruit_workspace, builtin_models):
    tiny_descriptor_run(fruit_workspace)
    path = virtual_contacts_path("fruit", fruit_workspace)
    before = path.stat().st_mtime_ns
    contacts = virtual_contacts(builtin_models["fruit"], TINY.network, TINY.virtual, fruit_workspace)
    assert path.stat().st_mtime_ns == before and len(contacts) == TINY.virtual.count
    assert contacts.maps.shape[1:] == (2, 6, 16) and set(np.unique(contacts.maps[:, 1])) <= {0.0, 1.0}
    # Every true location is on the object's surface.
    distances, _ = builtin_models["fruit"].kdtree.query(contacts.p_object)
    assert distances.max() < 3 * builtin_models["fruit"].point_spacing_m


def test_an_interrupted_run_resumes_to_the_same_weights(fruit_workspace):
    whole = LocalizerCheckpoint.load(tiny_descriptor_run(fruit_workspace))
    run_dir = fruit_workspace / "runs" / "interrupted"
    train(TINY, ["fruit"], fruit_workspace, run_dir, progress=False, max_steps=12)  # mid-way through epoch 2
    state = TrainingState.load(run_dir / "state.pt")
    assert state is not None and state.epoch >= 1 and not (run_dir / "model.pt").exists()
    resumed = LocalizerCheckpoint.load(train(TINY, ["fruit"], fruit_workspace, run_dir, progress=False))
    for name, value in whole.state_dict.items():
        assert torch.equal(value, resumed.state_dict[name]), name


def test_stage_two_fine_tunes_on_contact_pairs(fruit_workspace, builtin_models, rng):
    pairs = fruit_workspace / "pairs_real"
    write_cut_pairs(builtin_models["fruit"], pairs, 4, rng)
    path = tiny_descriptor_run(fruit_workspace, "stage2", real_pairs_dir=pairs, val_pairs_dir=None)
    checkpoint = LocalizerCheckpoint.load(path)
    assert checkpoint.real_pairs is not None and checkpoint.real_pairs.count == 8
    history = [json.loads(line) for line in (path.parent / "log.jsonl").read_text().splitlines()]
    assert [r["stage"] for r in history] == ["stage1"] * 8 + ["stage2"]
    assert (path.parent / "model_stage1.pt").exists()


def test_the_cpu_preset_is_the_descriptor_network_and_round_trips():
    config = PRESETS["cpu"]
    assert isinstance(config, DescriptorTrainConfig)
    assert DescriptorTrainConfig.from_dict(config.to_dict()) == config
    assert DescriptorTrainConfig.from_dict(replace(config, seed=3).to_dict()).seed == 3


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (CI has none)")
def test_a_gpu_run_in_bf16_learns_and_writes_cpu_weights(fruit_workspace):
    config = replace(TINY, precision="bf16")
    path = tiny_descriptor_run(fruit_workspace, "gpu", config, device="cuda")
    checkpoint = LocalizerCheckpoint.load(path)
    assert all(value.device.type == "cpu" and value.dtype == torch.float32 for value in checkpoint.state_dict.values())
    history = [json.loads(line) for line in (path.parent / "log.jsonl").read_text().splitlines()]
    assert history[-1]["val_virtual_recall_at_128"] >= 0.6


def test_the_speed_test_times_descriptor_steps(fruit_workspace):
    from yoto.training.speed import measure_training_speed

    tiny_descriptor_run(fruit_workspace)  # its virtual contacts are stored
    result = measure_training_speed(TINY, ["fruit"], fruit_workspace, steps=3, warmup=1)
    assert len(result.step_s) == 3 and (result.step_s > 0).all() and result.samples_per_s > 0
    assert result.info["anchors"][0] > 100 and "samples/s" in result.summary()
