"""Where a result came from: commit, package versions, device. Stamped on benchmarks and checkpoints.

Nothing runs at import time; `run_info()` reads git and the installed packages when a report is written.
"""

from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path
from typing import Any

import numpy as np

from yoto import __version__


def git_commit(short: bool = True) -> str:
    """The commit of the checkout YOTO runs from, or "unknown" (an installed wheel, no git)."""
    command = ["git", "rev-parse", "--short", "HEAD"] if short else ["git", "rev-parse", "HEAD"]
    try:
        result = subprocess.run(command, capture_output=True, text=True, cwd=Path(__file__).parent, timeout=5)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return result.stdout.strip() or "unknown"


def cpu_name() -> str:
    name = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return name


def versions() -> dict[str, str]:
    """Versions of YOTO, Python and the numerical packages that shape results (those installed)."""
    found = {"yoto": __version__, "python": platform.python_version(), "numpy": np.__version__}
    try:
        import torch

        found["torch"] = str(torch.__version__)
    except ImportError:
        pass
    try:
        import open3d

        found["open3d"] = str(open3d.__version__)
    except ImportError:
        pass
    return found


def device() -> str:
    """The CPU (and GPU, when torch sees one) results were measured on."""
    text = f"CPU: {cpu_name()}, {os.cpu_count()} cores"
    try:
        import torch

        if torch.cuda.is_available():
            text += f"; GPU: {torch.cuda.get_device_name(0)}"
    except ImportError:
        pass
    return text


def run_info() -> dict[str, Any]:
    """Commit, versions and device in one record, for report headers and checkpoint cards."""
    info: dict[str, Any] = {**versions(), "commit": git_commit(), "device": device()}
    try:
        import torch

        info["torch_threads"] = torch.get_num_threads()
    except ImportError:
        pass
    return info
