"""Shared fixtures: a tiny KITTI-layout dataset.

The dataset comes from the Rust generator (`cmr-agent synth`, binary from $CMR_AGENT_BIN or
../target/release/cmr-agent), so the pipeline reads exactly the files the product writes.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[2]

torch.set_num_threads(2)


def _rust_binary() -> Path:
    path = Path(os.environ.get("CMR_AGENT_BIN", REPO / "target" / "release" / "cmr-agent"))
    if not path.is_file():
        pytest.fail(f"{path} is missing: build it first (`make test` does, via `cargo test --release`), "
                    "or point CMR_AGENT_BIN at a built cmr-agent")
    return path


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("synth")
    subprocess.run([str(_rust_binary()), "synth", "--out", str(root), "--sequences", "1", "--frames", "4", "--seed", "7",
                    "--image-size", "640x200", "--quiet"], check=True, capture_output=True, timeout=600)
    return root
