"""`yoto bench` end to end on a few pairs: the report's numbers and tables, and resuming a finished run."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np

from yoto.evaluation.bench import BenchConfig, MethodSpec, run_benchmark


def test_oracle_benchmark_reports_both_localizations_and_resumes(tmp_path):
    exact = {"sensor_noise_mm": 0.0, "sensor_noise_deg": 0.0, "prior_mm": 0.0, "prior_deg": 0.0}
    config = BenchConfig(num_pairs=3, warmup_pairs=1, retouch=False, **exact)
    methods = [MethodSpec("Oracle", "oracle")]
    out = tmp_path / "bench"
    report = run_benchmark(["fruit"], methods, config, out, workspace=tmp_path / "ws")

    oracle = report["all"]["Oracle"]
    assert oracle["pairs"] == 3 and oracle["failures"] == 0
    # The oracle's top candidate is the true contact; under the chosen pose (exact sensors and an exact prior, a
    # curvy object) the contact lands within a millimetre of it, and every pose is right.
    assert oracle["localization_mm"]["max"] < 1e-9
    assert 0.0 < oracle["localization_chosen_mm"]["max"] < 1.0
    assert oracle["right_share"] == 1.0
    # The paper's pose stage uses the top candidates as they are: its chosen contacts are the true ones.
    assert report["all"]["Oracle, paper pose stage"]["localization_chosen_mm"]["max"] < 1e-9

    text = (out / "bench.md").read_text()
    assert "localizer's top candidate" in text and "through the pose stage" in text
    assert json.loads((out / "bench.json").read_text())["all"]["Oracle"]["pairs"] == 3

    again = run_benchmark(["fruit"], methods, config, out, workspace=tmp_path / "ws")
    assert again["all"]["Oracle"]["localization_chosen_mm"] == oracle["localization_chosen_mm"]

    # Cached results are reused by the code that made them and by no other: a result cached by another commit is
    # computed again, and its file rewritten with this code's stamp.
    from yoto import provenance
    from yoto.evaluation import bench

    (cached,) = (out / "partial").glob("fruit__Oracle__*.json")
    stored = json.loads(cached.read_text())
    assert stored["fingerprint"]["code"] == {"yoto": bench.__version__, "commit": provenance.git_commit()}
    stored["results"][0]["translation_mm"] = [123.0, 123.0, 123.0]  # not what this code finds
    cached.write_text(json.dumps(stored))
    reused = run_benchmark(["fruit"], methods, config, out, workspace=tmp_path / "ws")
    assert reused["all"]["Oracle"]["translation_mm"]["median"] == 123.0
    stored["fingerprint"]["code"]["commit"] = "0000000"  # as an older YOTO would have cached it
    cached.write_text(json.dumps(stored))
    fresh = run_benchmark(["fruit"], methods, config, out, workspace=tmp_path / "ws")
    assert fresh["all"]["Oracle"]["translation_mm"] == oracle["translation_mm"]
    assert json.loads(cached.read_text())["fingerprint"]["code"]["commit"] == provenance.git_commit()


def test_both_cores_gives_the_same_poses_and_counts_both_contacts_at_once(tmp_path):
    config = BenchConfig(num_pairs=3, warmup_pairs=1, retouch=False, pose_stages=("full",))
    methods = [MethodSpec("Matched filter", "match")]
    results = {}
    for out, both_cores in (("one", False), ("both", True)):
        run_benchmark(["fruit"], methods, replace(config, both_cores=both_cores), tmp_path / out, tmp_path / "ws")
        (cached,) = (tmp_path / out / "partial").glob("fruit__*.json")
        results[out] = json.loads(cached.read_text())["results"][0]
    # The same poses, hypotheses and confidences, bit for bit (the helper computes half of each large batch).
    for key in ("translation_mm", "rotation_deg", "confidence", "hypotheses", "truth_in_hypotheses"):
        assert results["both"][key] == results["one"][key]
    # A pose's latency is the pair's localization plus the pose stage: one core adds the two contacts' own times;
    # with both cores it is the time of both at once, which encloses this process's (left) contact. (Not asserted:
    # that at once is faster than the sum, a wall-time race a loaded machine can lose.)
    for out, at_once in (("one", False), ("both", True)):
        timed = results[out]
        contacts, stage, pose = (np.array(timed[k]) for k in ("contact_latency_ms", "pose_stage_ms", "pose_latency_ms"))
        localization, summed = pose - stage, contacts[0::2] + contacts[1::2]
        assert len(pose) == 2
        assert np.allclose(localization, summed, rtol=0, atol=1e-6) != at_once
        assert np.all(localization >= contacts[0::2] - 1e-6)
    assert "both cores" in (tmp_path / "both" / "bench.md").read_text()
