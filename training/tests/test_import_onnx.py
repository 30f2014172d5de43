"""import_onnx: a model set exported from PyTorch comes back as modules that compute what the
original modules computed (both agent forms, both normalisations), and a set that no architecture
explains is refused."""

import json
import shutil

import pytest
import torch

from cmr.export import example_inputs, export_models, is_correlation_agent
from cmr.import_onnx import import_models
from cmr.models import build_all


def randomised(norm: str, image_backbone: str = "scratch", point_encoder: str = "pillars") -> dict:
    torch.manual_seed(1)
    models = build_all(norm=norm, image_backbone=image_backbone, point_encoder=point_encoder)
    with torch.no_grad():
        for m in models.values():
            for mod in m.modules():
                if isinstance(mod, torch.nn.BatchNorm2d):
                    mod.running_mean.uniform_(-0.2, 0.2)
                    mod.running_var.uniform_(0.5, 2.0)
                    mod.weight.uniform_(0.5, 1.5)
                    mod.bias.uniform_(-0.3, 0.3)
                if isinstance(mod, torch.nn.GroupNorm):
                    mod.weight.uniform_(0.5, 1.5)
                    mod.bias.uniform_(-0.3, 0.3)
            m.eval()
    return models


def outputs(name: str, module: torch.nn.Module) -> list[torch.Tensor]:
    inputs = example_inputs(name, batch=2 if name == "agent" else 1, seed=3)
    with torch.no_grad():
        out = module.eval()(*inputs) if name != "agent" else module.eval().forward(*inputs)
    return list(out) if isinstance(out, tuple) else [out]


@pytest.mark.parametrize("norm,correlation,backbone", [("batch", True, "scratch"), ("batch", False, "scratch"),
                                                       ("group", True, "scratch"), ("group", True, "efficientnet_lite0"),
                                                       ("group", True, "efficientnet_lite0_s32"), ("group", True, "efficientnet_lite1")])
def test_round_trip_reproduces_the_modules(tmp_path, norm, correlation, backbone):
    original = randomised(norm, backbone)
    export_models(original, tmp_path, dict(data="test", seeds={}), action_frame="map_z", correlation=correlation)
    imported, meta = import_models(tmp_path)
    assert meta["config"] == dict(norm=norm, image_edges=False, image_backbone=backbone, action_frame="map_z")
    for name, module in original.items():
        for want, got in zip(outputs(name, module), outputs(name, imported[name])):
            rel = float((want - got).abs().max() / want.abs().max().clamp(min=1e-6))
            assert rel < 1e-4, (name, rel)
    assert is_correlation_agent(imported["agent"])


def test_a_set_no_architecture_explains_is_refused(tmp_path):
    export_models(randomised("batch"), tmp_path, dict(data="test", seeds={}))
    # The image encoder's file in the point encoder's place: no build_all architecture has that.
    doc = json.loads((tmp_path / "manifest.json").read_text())
    shutil.copy(tmp_path / doc["graphs"]["image_encoder"]["file"], tmp_path / doc["graphs"]["point_encoder"]["file"])
    with pytest.raises(ValueError, match="no architecture"):
        import_models(tmp_path)


def test_the_shipped_model_fine_tunes_on_a_drive(tmp_path, tiny_dataset):
    """The documented fine-tuning path: import `models/`, train its agent a step on a generated
    drive in the map_z frame with maps from neighbouring scans, export again."""
    from pathlib import Path

    from cmr import import_onnx
    from cmr.export import load_models
    from cmr.train import main

    shipped = Path(__file__).resolve().parents[2] / "models"
    ckpt = tmp_path / "shipped.pt"
    import_onnx.main([str(shipped), "--out", str(ckpt)])
    state = torch.load(ckpt, map_location="cpu", weights_only=False)
    main(["--data", str(tiny_dataset), "--out", str(tmp_path / "ft"), "--set", f"init_from={ckpt}", "embed_steps=0",
          "agent_iters=1", "action_frame=map_z", "map_window=2", "num_points=4096", "agent_envs=2", "pool_size=2",
          "pool_refresh=1", "rollout_steps=3", "minibatch=8", "eval_frames=1", "holdout_every=4", "eval_every=0"])
    tuned, meta = load_models(tmp_path / "ft" / "last.pt")
    assert meta["config"]["action_frame"] == "map_z" and meta["training"]["agent_iters"] == 1
    # The encoders are the shipped ones (stage 1 did not run); the agent moved.
    for k, v in tuned["image_encoder"].state_dict().items():
        assert torch.equal(v, state["models"]["image_encoder"][k]), k
    moved = [k for k, v in tuned["agent"].state_dict().items() if not torch.equal(v, state["models"]["agent"][k])]
    assert moved


def test_an_intensity_point_encoder_comes_back_as_one(tmp_path):
    original = randomised("group", "efficientnet_lite0", "pillars_intensity")
    with torch.no_grad():
        original["point_encoder"].local[0][0].weight[:, -1].normal_(0, 0.5)  # the intensity column in use
    export_models(original, tmp_path, dict(data="test", seeds={}), action_frame="map_z")
    imported, meta = import_models(tmp_path)
    assert meta["config"]["point_encoder"] == "pillars_intensity" and imported["point_encoder"].in_channels == 4
    (pts,) = example_inputs("point_encoder", seed=3, point_channels=4)
    with torch.no_grad():
        want, got = original["point_encoder"].eval()(pts), imported["point_encoder"].eval()(pts)
    assert float((want - got).abs().max()) < 1e-4
