"""Training: a tiny run learns, is bitwise deterministic, resumes exactly, is idempotent; stage 2 and data."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from yoto.contacts import ContactPair, TactileContact, write_contact_pair  # noqa: E402
from yoto.errors import InputError  # noqa: E402
from yoto.geometry import invert_transform, make_transform, random_rotations, transform_points  # noqa: E402
from yoto.network.checkpoint import LocalizerCheckpoint, TrainedObject  # noqa: E402
from yoto.network.presets import NetworkConfig  # noqa: E402
from yoto.patches.generate import generate_patches  # noqa: E402
from yoto.patches.virtual import VirtualPatchConfig  # noqa: E402
from yoto.training.augment import AugmentConfig  # noqa: E402
from yoto.training.batches import collate, epoch_batch_count  # noqa: E402
from yoto.training.config import StageConfig, TrainConfig  # noqa: E402
from yoto.training.data import load_objects  # noqa: E402
from yoto.training.state import TrainingState  # noqa: E402
from yoto.training.train import train  # noqa: E402
from yoto.workspace import object_model_path  # noqa: E402

TINY_NETWORK = NetworkConfig(
    points_per_patch=48,
    points_per_block=48,
    centre_fraction=0.5,
    knn_scales=(4, 8, 16),
    point_dim=16,
    edge_dim=8,
    fusion_dim=24,
    prepool_dim=24,
    feature_dim=24,
    candidates=5,
    fine_dims=(32, 16),
)
TINY_PATCHES = VirtualPatchConfig(fixed_variants=1, random_variants=0, attempts_per_variant=80)
TINY_TRAINING = TrainConfig(
    network=TINY_NETWORK,
    stage1=StageConfig(epochs=3, lr=5e-3, encoder_lr=5e-3),
    stage2=StageConfig(epochs=1, lr=1e-3, encoder_lr=1e-3, real_oversample=3, real_weight=2.0),
    batch_size=24,
    augment=AugmentConfig(voxel_size_m=0.0, rotation_max_rad=np.pi, crop_prob=0.3),
    val_fraction=0.1,
    hypotheses=3,
)

_WORKSPACES: dict[str, Path] = {}


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """Small tensors gain nothing from threads, and on a shared machine extra threads only spin."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def tiny_workspace(builtin_models, tmp_path_factory, name: str = "fruit") -> Path:
    """A workspace holding the (reduced) built-in model and a small virtual patch set; built once."""
    if name not in _WORKSPACES:
        workspace = tmp_path_factory.mktemp(f"ws_{name}")
        builtin_models[name].save(object_model_path(name, workspace))
        generate_patches(name, TINY_PATCHES, workspace, workers=1, progress=False)
        _WORKSPACES[name] = workspace
    return _WORKSPACES[name]


def tiny_run(builtin_models, tmp_path_factory, run: str = "run_a", **kwargs) -> Path:
    """Train the tiny network on the fruit (once per run name per session); returns model.pt. On the CPU unless
    `device` says otherwise: the tests' bitwise figures hold there (a GPU's reductions and bf16 differ)."""
    kwargs.setdefault("device", "cpu")
    workspace = tiny_workspace(builtin_models, tmp_path_factory)
    run_dir = workspace / "runs" / run
    if not (run_dir / "model.pt").exists():
        train(TINY_TRAINING, ["fruit"], workspace, run_dir, patch_config=TINY_PATCHES, progress=False, **kwargs)
    return run_dir / "model.pt"


def cut_contact(model, p_index: int, rng, depth_m: float = 0.001, radius_m: float = 0.007):
    """A tactile cloud cut from the parent cloud as a pressed sensor would see it: sensor z into the object,
    surface within `depth_m` of the gel plane (z <= 0). Returns (points_sensor, T_object_sensor, p_object)."""
    p_object = model.points_object[p_index].astype(np.float64)
    normal = model.aggregated_normal(p_object)
    z_axis = -normal
    x_axis = np.cross(z_axis, rng.normal(size=3))
    x_axis /= np.linalg.norm(x_axis)
    rotation = np.stack([x_axis, np.cross(z_axis, x_axis), z_axis], axis=1)
    T_object_sensor = make_transform(rotation, p_object + depth_m * z_axis)
    near = model.kdtree.query_ball_point(p_object, radius_m)
    points_sensor = transform_points(invert_transform(T_object_sensor), model.points_object[near].astype(np.float64))
    keep = (points_sensor[:, 2] <= 0.0) & (model.normals_object[near] @ z_axis < 0)
    return points_sensor[keep], T_object_sensor, p_object


def write_cut_pairs(model, folder: Path, count: int, rng) -> list[Path]:
    """Contact-pair files (SPEC) of contacts cut from the parent cloud, with ground truth in the mesh frame."""
    paths = []
    for i in range(count):
        first, second = rng.choice(len(model.points_object), size=2, replace=False)
        T_world_object = make_transform(random_rotations(rng, 1)[0], rng.uniform(-0.2, 0.2, size=3))
        contacts, truth = {}, {}
        for side, index in (("left", first), ("right", second)):
            points, T_object_sensor, p_object = cut_contact(model, int(index), rng)
            contacts[side] = TactileContact(points, T_world_object @ T_object_sensor)
            truth[side] = transform_points(model.T_mesh_object, p_object)
        pair = ContactPair(
            object_name=model.name,
            left=contacts["left"],
            right=contacts["right"],
            T_world_mesh_true=T_world_object @ model.T_object_mesh,
            p_mesh_true=truth,
        )
        paths.append(write_contact_pair(folder / f"pair_{i:04d}.json", pair))
    return paths


def _fixed_batch_losses(builtin_models, tmp_path_factory, state_dict) -> tuple[dict, dict]:
    """Loss parts of the seeded initial network and of `state_dict` on the same 48 training patches (eval mode)."""
    from yoto.network.model import ContactLocalizationNet
    from yoto.training.data import draw_patch
    from yoto.training.losses import localization_loss

    workspace = tiny_workspace(builtin_models, tmp_path_factory)
    (data,) = load_objects(["fruit"], [builtin_models["fruit"]], workspace, TINY_TRAINING, TINY_PATCHES, False)
    rng = np.random.default_rng(1)
    batch = collate([draw_patch(data, "virtual", int(i), 48, rng, None) for i in data.virtual_train[:48]], 1.0)
    blocks = data.blocks.tensors()
    losses = []
    torch.manual_seed(TINY_TRAINING.seed)
    initial = ContactLocalizationNet(TINY_NETWORK)
    trained = ContactLocalizationNet(TINY_NETWORK)
    trained.load_state_dict(state_dict)
    for net in (initial, trained):
        net.eval()
        with torch.no_grad():
            out = net({"patch_points": batch["patch_points"], "patch_normals": batch["patch_normals"], **blocks})
            loss, parts = localization_loss(
                out, batch["block"], batch["p_object"], blocks["block_centres"], batch["weight"], TINY_TRAINING.loss
            )
        losses.append(parts)
    return losses[0], losses[1]


def _assert_same_weights(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key


def test_tiny_run_learns_and_writes_a_complete_checkpoint(builtin_models, tmp_path_factory):
    path = tiny_run(builtin_models, tmp_path_factory)
    checkpoint = LocalizerCheckpoint.load(path)
    model = builtin_models["fruit"]
    assert checkpoint.objects == [TrainedObject("fruit", model.fingerprint, model.num_blocks)]
    assert checkpoint.network_config == TINY_NETWORK
    assert TrainConfig.from_dict(checkpoint.train_config) == TINY_TRAINING
    assert checkpoint.seed == 0 and {"torch", "numpy", "yoto", "python"} <= set(checkpoint.versions)
    assert checkpoint.calibration.temperature > 0
    history = [json.loads(line) for line in (path.parent / "log.jsonl").read_text().splitlines()]
    assert [h["epoch"] for h in history] == [1, 2, 3]
    # On a fixed batch of training patches the trained network retrieves blocks better than the initial one:
    # lower block cross-entropy, higher top-K recall. (The total loss is not comparable across the two: the
    # top-K margin applies only to samples already within the top K, so it grows as recall does.)
    initial, trained = _fixed_batch_losses(builtin_models, tmp_path_factory, checkpoint.state_dict)
    assert trained["cls"] < initial["cls"] - 0.1
    assert trained["topk_recall"] > initial["topk_recall"] + 0.1
    assert history[-1]["val_virtual_topk"] >= TINY_NETWORK.candidates / model.num_blocks
    assert (path.parent / "log.csv").read_text().startswith("stage,epoch,step")
    assert (path.parent / "curves.png").stat().st_size > 1000


def test_training_is_bitwise_deterministic_and_idempotent(builtin_models, tmp_path_factory):
    first = tiny_run(builtin_models, tmp_path_factory)
    second = tiny_run(builtin_models, tmp_path_factory, run="run_repeat")
    _assert_same_weights(LocalizerCheckpoint.load(first).state_dict, LocalizerCheckpoint.load(second).state_dict)
    # An up-to-date finished run is kept as it is.
    stamp = first.stat().st_mtime_ns
    workspace = tiny_workspace(builtin_models, tmp_path_factory)
    again = train(TINY_TRAINING, ["fruit"], workspace, first.parent, patch_config=TINY_PATCHES, progress=False)
    assert again == first and first.stat().st_mtime_ns == stamp
    # The same run folder with other settings is refused rather than silently mixed.
    with pytest.raises(InputError, match="other settings"):
        train(replace(TINY_TRAINING, seed=1), ["fruit"], workspace, first.parent, patch_config=TINY_PATCHES)


def test_interrupted_training_resumes_to_the_same_weights(builtin_models, tmp_path_factory):
    reference = tiny_run(builtin_models, tmp_path_factory)
    workspace = tiny_workspace(builtin_models, tmp_path_factory)
    run_dir = workspace / "runs" / "interrupted"
    # Stop one step into epoch 2: state.pt holds epoch 1, model.pt does not exist yet.
    objects = load_objects(["fruit"], [builtin_models["fruit"]], workspace, TINY_TRAINING, TINY_PATCHES, False)
    data_steps = epoch_batch_count(objects, TINY_TRAINING.stage1, TINY_TRAINING.batch_size, False)
    stopped = train(
        TINY_TRAINING,
        ["fruit"],
        workspace,
        run_dir,
        patch_config=TINY_PATCHES,
        progress=False,
        max_steps=data_steps + 1,
        device="cpu",
    )
    assert stopped.name == "state.pt" and not (run_dir / "model.pt").exists()
    state = TrainingState.load(stopped)
    assert state is not None and (state.stage_index, state.epoch, len(state.history)) == (0, 1, 1)
    resumed = train(
        TINY_TRAINING, ["fruit"], workspace, run_dir, patch_config=TINY_PATCHES, progress=False, device="cpu"
    )
    _assert_same_weights(LocalizerCheckpoint.load(reference).state_dict, LocalizerCheckpoint.load(resumed).state_dict)
    history = [json.loads(line) for line in (run_dir / "log.jsonl").read_text().splitlines()]
    assert [h["epoch"] for h in history] == [1, 2, 3]


def test_stage_two_fine_tunes_on_contact_pairs(builtin_models, tmp_path_factory, rng):
    workspace = tiny_workspace(builtin_models, tmp_path_factory)
    model = builtin_models["fruit"]
    pairs = workspace / "pairs_finetune"
    write_cut_pairs(model, pairs, 4, rng)
    (pairs / "simulation.json").write_text('{"settings": "not a pair"}')  # other JSON in the folder is skipped
    held_out = workspace / "pairs_heldout"
    write_cut_pairs(model, held_out, 2, rng)
    config = replace(TINY_TRAINING, stage1=replace(TINY_TRAINING.stage1, epochs=1))
    path = train(
        config,
        ["fruit"],
        workspace,
        workspace / "runs" / "finetuned",
        real_pairs_dir=pairs,
        val_pairs_dir=held_out,
        patch_config=TINY_PATCHES,
        progress=False,
    )
    checkpoint = LocalizerCheckpoint.load(path)
    assert checkpoint.real_pairs is not None and checkpoint.real_pairs.count == 8
    history = [json.loads(line) for line in (path.parent / "log.jsonl").read_text().splitlines()]
    assert [h["stage"] for h in history] == ["stage1", "stage2"]
    assert history[-1]["val_real_count"] == 4
    assert 0.0 <= history[-1]["val_real_top1"] <= 1.0
    # Stage 2 mixes real contacts in: over-sampled 3x (8 contacts -> 24 draws) on top of the virtual patches.
    first_stage = epoch_batch_count([], config.stage1, config.batch_size, False)
    assert first_stage == 0
    with pytest.raises(InputError, match="also fine-tuning"):
        train(config, ["fruit"], workspace, workspace / "runs" / "leak", real_pairs_dir=pairs, val_pairs_dir=pairs)


def test_contact_samples_are_labelled_like_virtual_patches(builtin_models, rng):
    from yoto.training.data import contact_sample, dominant_block

    model = builtin_models["fruit"]
    index = int(rng.integers(len(model.points_object)))
    points, T_object_sensor, p_object = cut_contact(model, index, rng)
    sample = contact_sample(points, model, p_object, T_object_sensor)
    assert sample.block == dominant_block(model, transform_points(T_object_sensor, points))
    # Canonical form: centred, concave direction +z, outward normals toward -z.
    np.testing.assert_allclose(sample.points.mean(axis=0), 0.0, atol=1e-6)
    assert sample.normals[:, 2].mean() < -0.9


def test_augmentations_keep_labels_and_shapes(builtin_models, tmp_path_factory):
    from yoto.network.inputs import make_block_set
    from yoto.patches.virtual import VirtualPatchDataset
    from yoto.training.data import ObjectData, draw_patch
    from yoto.workspace import patch_dataset_path

    workspace = tiny_workspace(builtin_models, tmp_path_factory)
    model = builtin_models["fruit"]
    dataset = VirtualPatchDataset.load(patch_dataset_path("fruit", workspace), model)
    data = ObjectData(model, make_block_set(model, TINY_NETWORK), dataset, np.arange(len(dataset)), np.arange(0))
    rng = np.random.default_rng(0)
    plain = draw_patch(data, "virtual", 3, 48, rng, None)
    np.testing.assert_allclose(plain.p_object, dataset.p_object[3])
    cropped = draw_patch(data, "virtual", 3, 48, rng, AugmentConfig(crop_prob=1.0, crop_disc_prob=1.0))
    assert cropped.points.shape == (48, 3) and cropped.normals.shape == (48, 3)
    # A cropped patch is relabelled to the parent point nearest its own centroid: still on the surface, close by.
    assert np.min(np.linalg.norm(model.points_object - cropped.p_object, axis=1)) < 1e-6
    assert np.linalg.norm(cropped.p_object - dataset.p_object[3]) < 0.008
    np.testing.assert_allclose(np.linalg.norm(cropped.normals, axis=1), 1.0, atol=1e-4)


def test_press_patches_look_like_pad_contacts(builtin_models):
    from yoto.training.press import PressPatchConfig, generate_press_patches

    model = builtin_models["figurine"]
    config = PressPatchConfig(count=25, depth_m=(0.0008, 0.0008), seed=3)
    dataset = generate_press_patches(model, config)
    assert len(dataset) == 25 and dataset.meta["kind"] == "press"
    half_diagonal = 0.5 * float(np.hypot(*config.pad_size_m))
    for i in range(len(dataset)):
        members = dataset.indices[dataset.offsets[i] : dataset.offsets[i + 1]]
        points = model.points_object[members].astype(np.float64)
        assert len(members) >= config.min_points
        # Inside the pad (around the target, offset at most max_offset) and labelled with one of its points.
        assert np.linalg.norm(points - points.mean(axis=0), axis=1).max() <= half_diagonal + config.max_offset_m
        assert np.min(np.linalg.norm(points - dataset.p_object[i], axis=1)) == 0.0
        # Pressed 0.8 mm deep: along its own axis the contact spans about the depth, far less than its width.
        canonical, _ = dataset.patch(i)
        assert np.ptp(canonical[:, 2]) < 0.3 * np.ptp(canonical[:, :2], axis=0).max()
    # Deterministic for its seed.
    again = generate_press_patches(model, config)
    np.testing.assert_array_equal(again.indices, dataset.indices)


def test_pairs_of_one_object_can_train_the_model_of_its_scan(builtin_models, tmp_path, rng):
    """Contacts recorded on the real object train the model built from its scan (same mesh frame)."""
    from yoto.training.data import contact_samples, load_labelled_contacts

    model = builtin_models["fruit"]
    scan_model = replace(model, name="fruit_scan")
    write_cut_pairs(model, tmp_path, 2, rng)
    contacts, files = load_labelled_contacts([tmp_path], {"fruit_scan": scan_model})
    assert len(files) == 2 and contacts["fruit_scan"] == []  # without the mapping the pairs are not this model's
    contacts, _ = load_labelled_contacts([tmp_path], {"fruit_scan": scan_model}, {"fruit": "fruit_scan"})
    assert len(contacts["fruit_scan"]) == 4
    samples = contact_samples(contacts["fruit_scan"], scan_model)  # the point network's canonical samples
    assert len(samples) == 4 and all(0 <= sample.block < scan_model.num_blocks for sample in samples)


def test_the_speed_test_times_point_network_steps(builtin_models, tmp_path_factory):
    from yoto.training.speed import measure_training_speed

    workspace = tiny_workspace(builtin_models, tmp_path_factory)
    result = measure_training_speed(
        TINY_TRAINING, ["fruit"], workspace, steps=2, warmup=1, device="cpu", patch_config=TINY_PATCHES
    )
    assert len(result.step_s) == 2 and (result.step_s > 0).all()
    assert result.info["device"] == "cpu" and result.info["precision"] == "fp32"
    assert result.samples_per_s == pytest.approx(np.median(result.batch_sizes) / np.median(result.step_s))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (CI has none)")
def test_a_gpu_run_validates_on_the_gpu_and_writes_cpu_weights(builtin_models, tmp_path_factory):
    path = tiny_run(builtin_models, tmp_path_factory, run="run_gpu", device="cuda")
    checkpoint = LocalizerCheckpoint.load(path)
    assert all(value.device.type == "cpu" and value.dtype == torch.float32 for value in checkpoint.state_dict.values())
    history = [json.loads(line) for line in (path.parent / "log.jsonl").read_text().splitlines()]
    assert all(np.isfinite(record["val_virtual_error_mean_mm"]) for record in history if "stage" in record)
