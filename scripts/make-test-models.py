"""Exports a tiny, randomly initialised model set that follows the model contract exactly.

The server's integration tests need real ONNX graphs with the contract's names and shapes, and
must not wait for (or be slowed down by) the trained default model. These graphs are small, so
the fixture stays a few hundred kilobytes; their outputs are meaningless but deterministic.

    .venv/bin/python scripts/make-test-models.py tests/fixtures/tiny-model
"""

import hashlib
import json
import sys
from pathlib import Path

import torch
from torch import nn

N_POINTS = 40960
M_STATE = 2048
DIM = 64
H, W, STRIDE = 160, 512, 4


def l2(x, dim):
    return x / torch.sqrt((x * x).sum(dim=dim, keepdim=True) + 1e-12)


class PointEncoder(nn.Module):
    def __init__(self):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(3, 32), nn.ReLU(), nn.Linear(32, DIM))

    def forward(self, points):
        centred = points - points.mean(dim=1, keepdim=True)
        return l2(self.mlp(centred), -1)


class ImageEncoder(nn.Module):
    def __init__(self):
        super().__init__()
        self.conv = nn.Conv2d(3, DIM, kernel_size=STRIDE, stride=STRIDE)

    def forward(self, image):
        return l2(self.conv(image), 1)


class FrustumHead(nn.Module):
    def __init__(self):
        super().__init__()
        self.proj = nn.Linear(DIM, DIM)

    def forward(self, point_features, image_features):
        context = image_features.mean(dim=(2, 3))  # [1, 64]
        return (self.proj(point_features) * context[:, None, :]).sum(-1) * 4.0


class Agent(nn.Module):
    def __init__(self):
        super().__init__()
        self.conv = nn.Conv2d(2 * DIM, 16, kernel_size=1)
        self.point_mlp = nn.Sequential(nn.Linear(5, 16), nn.ReLU())
        self.policy = nn.Linear(16 + 16, 3 * 11)
        self.value = nn.Linear(16 + 16, 1)

    def forward(self, state_2d, state_3d):
        g = torch.relu(self.conv(state_2d)).mean(dim=(2, 3))
        p = self.point_mlp(state_3d).max(dim=1).values
        h = torch.cat([g, p], dim=1)
        return self.policy(h).reshape(-1, 3, 11), self.value(h)


def export(module, args, names_in, names_out, dynamic, path):
    torch.onnx.export(
        module, args, path, input_names=names_in, output_names=names_out,
        dynamic_axes=dynamic, opset_version=17, dynamo=False,
    )


def sha256(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def main(out_dir):
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    n_small = 128
    graphs = {
        "point_encoder": (PointEncoder(), (torch.randn(1, n_small, 3),), ["points"], ["point_features"],
                          {"points": {1: "N"}, "point_features": {1: "N"}},
                          {"points": [1, "N", 3]}, {"point_features": [1, "N", DIM]}),
        "image_encoder": (ImageEncoder(), (torch.randn(1, 3, H, W),), ["image"], ["image_features"], None,
                          {"image": [1, 3, H, W]}, {"image_features": [1, DIM, H // STRIDE, W // STRIDE]}),
        "frustum_head": (FrustumHead(), (torch.randn(1, n_small, DIM), torch.randn(1, DIM, H // STRIDE, W // STRIDE)),
                         ["point_features", "image_features"], ["frustum_logits"],
                         {"point_features": {1: "N"}, "frustum_logits": {1: "N"}},
                         {"point_features": [1, "N", DIM], "image_features": [1, DIM, H // STRIDE, W // STRIDE]},
                         {"frustum_logits": [1, "N"]}),
        "agent": (Agent(), (torch.randn(2, 2 * DIM, H // STRIDE, W // STRIDE), torch.randn(2, M_STATE, 5)),
                  ["state_2d", "state_3d"], ["policy_logits", "value"],
                  {"state_2d": {0: "B"}, "state_3d": {0: "B"}, "policy_logits": {0: "B"}, "value": {0: "B"}},
                  {"state_2d": ["B", 2 * DIM, H // STRIDE, W // STRIDE], "state_3d": ["B", M_STATE, 5]},
                  {"policy_logits": ["B", 3, 11], "value": ["B", 1]}),
    }
    manifest_graphs = {}
    parameters = {}
    for name, (module, args, names_in, names_out, dynamic, shapes_in, shapes_out) in graphs.items():
        module.eval()
        path = out / f"{name}.onnx"
        with torch.no_grad():
            export(module, args, names_in, names_out, dynamic, str(path))
        manifest_graphs[name] = {"file": path.name, "sha256": sha256(path), "inputs": shapes_in, "outputs": shapes_out}
        parameters[name] = sum(p.numel() for p in module.parameters())
    rotation = [0.1 * s for s in (-625, -125, -25, -5, -1, 0, 1, 5, 25, 125, 625)]
    translation = [0.1 * s for s in (-81, -27, -9, -3, -1, 0, 1, 3, 9, 27, 81)]
    manifest = {
        "format": "cmr-agent-manifest/1",
        "image": {"width": W, "height": H, "nominal_scale": 0.5,
                  "mean": [0.485, 0.456, 0.406], "std": [0.229, 0.224, 0.225]},
        "features": {"dim": DIM, "stride": STRIDE, "grid_height": H // STRIDE, "grid_width": W // STRIDE},
        "points": {"num_points": N_POINTS, "num_state_points": M_STATE, "state_xyz_scale_m": 10.0},
        "actions": {"dofs": ["yaw_deg", "tx_m", "tz_m"], "rotation_deg": rotation, "translation_m": translation},
        "graphs": manifest_graphs,
        "provenance": {"data": "none: random weights, test fixture only", "seeds": {"torch": 0},
                       "git_commit": "n/a", "created": "scripts/make-test-models.py"},
        "validation": {},
        "parameters": parameters,
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "tests/fixtures/tiny-model")
