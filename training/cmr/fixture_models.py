"""A tiny, randomly initialised model set that follows the model contract, for the Rust tests.

The server's and evaluator's tests need real ONNX graphs with the contract's names and shapes,
but must not change whenever the default model is retrained, and should stay fast and small
(a few hundred kilobytes in git). The graphs go through the same exporter and manifest writer as
the default model (`cmr.export.export_models`); only the networks are tiny. Their outputs are
meaningless but deterministic.

    cd training && ../.venv/bin/python -m cmr.fixture_models ../tests/fixtures/tiny-model

`--intensity` writes the variant whose point encoder reads a fourth column, each point's
intensity rank (`data.intensity_rank`; manifest `points.channels`), and whose features depend on
it, for the Rust tests of intensity sets:

    cd training && ../.venv/bin/python -m cmr.fixture_models --intensity ../tests/fixtures/tiny-model-intensity
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from torch import nn

from .export import export_models
from .models import FEATURE_DIM, NUM_DOFS, NUM_STEPS, STRIDE, l2_normalise


class TinyPointEncoder(nn.Module):
    """[1, N, 3] x, y, z, or with `in_channels` = 4 [1, N, 4] with the intensity rank, whose
    features then move with the rank as much as with a few metres of position."""

    def __init__(self, in_channels: int = 3):
        super().__init__()
        self.in_channels = in_channels
        self.mlp = nn.Sequential(nn.Linear(in_channels, 32), nn.ReLU(), nn.Linear(32, FEATURE_DIM))

    def forward(self, points):
        if self.in_channels == 3:
            return l2_normalise(self.mlp(points - points.mean(dim=1, keepdim=True)), -1)
        xyz, rank = points[..., :3], points[..., 3:]
        return l2_normalise(self.mlp(torch.cat([xyz - xyz.mean(dim=1, keepdim=True), (rank - 0.5) * 8.0], -1)), -1)


class TinyImageEncoder(nn.Module):
    def __init__(self):
        super().__init__()
        self.conv = nn.Conv2d(3, FEATURE_DIM, kernel_size=STRIDE, stride=STRIDE)

    def forward(self, image):
        return l2_normalise(self.conv(image), 1)


class TinyFrustumHead(nn.Module):
    def __init__(self):
        super().__init__()
        self.proj = nn.Linear(FEATURE_DIM, FEATURE_DIM)

    def forward(self, point_features, image_features):
        context = image_features.mean(dim=(2, 3))
        return (self.proj(point_features) * context[:, None, :]).sum(-1) * 4.0


class TinyAgent(nn.Module):
    def __init__(self):
        super().__init__()
        self.conv = nn.Conv2d(2 * FEATURE_DIM, 16, kernel_size=1)
        self.point_mlp = nn.Sequential(nn.Linear(5, 16), nn.ReLU())
        self.policy = nn.Linear(32, NUM_DOFS * NUM_STEPS)
        self.value = nn.Linear(32, 1)

    def forward(self, state_2d, state_3d):
        h = torch.cat([torch.relu(self.conv(state_2d)).mean(dim=(2, 3)), self.point_mlp(state_3d).max(dim=1).values], 1)
        return self.policy(h).reshape(-1, NUM_DOFS, NUM_STEPS), self.value(h)


def main(out_dir: str, intensity: bool = False) -> None:
    torch.manual_seed(0)
    models = {"point_encoder": TinyPointEncoder(4 if intensity else 3), "image_encoder": TinyImageEncoder(),
              "frustum_head": TinyFrustumHead(), "agent": TinyAgent()}
    provenance = dict(data="none: random weights, test fixture only", seeds=dict(torch=0),
                      git_commit="n/a", created="python -m cmr.fixture_models")
    export_models(models, Path(out_dir), provenance)
    print(f"wrote {out_dir}")


if __name__ == "__main__":
    args = sys.argv[1:]
    intensity = "--intensity" in args
    args = [a for a in args if a != "--intensity"]
    default = "tiny-model-intensity" if intensity else "tiny-model"
    main(args[0] if args else str(Path(__file__).resolve().parents[2] / "tests" / "fixtures" / default), intensity)
