"""`benchmarks/tracking_meets.py --frames-at-truth-parts`: the frames' own change at the truth taken apart into
the frames as read, with the depth scale step only, with the pads' maps only, and both (the closed loop's)."""

import importlib.util
from pathlib import Path

import numpy as np

from yoto.tracking.config import CorrectionConfig


def _meets():
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "tracking_meets.py"
    spec = importlib.util.spec_from_file_location("tracking_meets", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_parts_are_the_frames_as_read_the_depth_scale_step_and_the_pads_maps_each_alone():
    """The three registrations beside the closed loop's: as read (no depth scale step, no pads' maps), the depth
    scale step at the tracker's default prior alone, the maps alone; each row gives a part's turn and shift
    (deg / mm), '-' where the motion left no instants on one side."""
    meets = _meets()
    assert [(name, pads) for name, _, pads in meets.PARTS] == [
        ("as read", False),
        ("depth scale out", False),
        ("pads' maps", True),
    ]
    assert [share for _, share, _ in meets.PARTS] == [0.0, CorrectionConfig().image_depth_scale, 0.0]
    turn = np.radians(1.5) / np.sqrt(2.0)
    record = {
        "seed": 11,
        "object": "fruit",
        "length_mm": 100,
        "index": 1,
        "right_touch": True,
        "closed": {"final_drift": {"deg": 1.08, "mm": 0.22}},
        "frames_change": [0.0, 0.0, np.radians(2.11), 0.0, 2.9e-4, 0.0],
        "frames_change_parts": {
            "as read": [turn, turn, 0.0, 1e-4, 0.0, 0.0],
            "depth scale out": None,
            "pads' maps": [0.0, np.radians(-2.12), 0.0, 0.0, 0.0, -2.9e-4],
        },
    }
    wrong = dict(record, right_touch=False)
    lines = meets.parts_rows([record, wrong])
    assert len(lines) == 3  # the header, its rule, the one right touch
    assert lines[2] == "| s11 fruit 100 mm #1 | 1.08 / 0.22 | 1.50 / 0.10 | - | 2.12 / 0.29 | 2.11 / 0.29 |"
