"""Export: four graphs that follow the contract, a manifest that describes them, and parity between
PyTorch and ONNX Runtime on random inputs (relative error < 1e-4)."""

import hashlib
import json

import numpy as np
import onnxruntime as ort
import pytest
import torch

from cmr.export import GRAPH_IO, MANIFEST_FORMAT, example_inputs, export_models, to_correlation
from cmr.models import build_all


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    torch.manual_seed(0)
    models = build_all()
    # Non-trivial batch-norm statistics so parity also covers the folded normalisation.
    for m in models.values():
        for mod in m.modules():
            if isinstance(mod, torch.nn.BatchNorm2d):
                mod.running_mean.uniform_(-0.2, 0.2)
                mod.running_var.uniform_(0.5, 2.0)
        m.eval()
    out = tmp_path_factory.mktemp("models")
    doc = export_models(models, out, dict(data="test", seeds={}))
    return models, out, doc


def test_manifest_describes_the_files(exported):
    _, out, doc = exported
    assert doc["format"] == MANIFEST_FORMAT
    on_disk = json.loads((out / "manifest.json").read_text())
    assert on_disk == doc
    for key in ("image", "features", "points", "actions", "graphs", "provenance", "validation", "parameters"):
        assert key in doc
    assert doc["points"] == dict(num_points=40960, num_state_points=2048, state_xyz_scale_m=10.0)
    assert doc["actions"]["dofs"] == ["yaw_deg", "tx_m", "tz_m"]
    for name, spec in doc["graphs"].items():
        data = (out / spec["file"]).read_bytes()
        assert hashlib.sha256(data).hexdigest() == spec["sha256"]
        sess = ort.InferenceSession(str(out / spec["file"]), providers=["CPUExecutionProvider"])
        assert [i.name for i in sess.get_inputs()] == list(spec["inputs"])
        assert [o.name for o in sess.get_outputs()] == list(spec["outputs"])


@pytest.mark.parametrize("name", list(GRAPH_IO))
def test_parity(exported, name):
    models, out, _ = exported
    kwargs = dict(batch=3) if name == "agent" else dict(num_points=5000) if name != "image_encoder" else {}
    inputs = example_inputs(name, seed=11, **kwargs)
    with torch.no_grad():
        want = models[name](*inputs)
    want = want if isinstance(want, tuple) else (want,)
    if name == "agent":  # the correlation form: the graph starts after `Agent.correlate`
        with torch.no_grad():
            inputs = (models["agent"].correlate(inputs[0]), inputs[1])
    sess = ort.InferenceSession(str(out / f"{name}.onnx"), providers=["CPUExecutionProvider"])
    got = sess.run(None, {i.name: t.numpy() for i, t in zip(sess.get_inputs(), inputs)})
    for w, g_ in zip(want, got):
        w = w.numpy()
        assert w.shape == g_.shape
        rel = np.abs(w - g_).max() / max(np.abs(w).max(), 1e-6)
        assert rel < 1e-4, f"{name}: relative error {rel}"


def test_features_are_unit_length_and_origin_free(exported):
    models, out, _ = exported
    sess = ort.InferenceSession(str(out / "point_encoder.onnx"), providers=["CPUExecutionProvider"])
    (pts,) = example_inputs("point_encoder", num_points=3000, seed=2)
    a = sess.run(None, {"points": pts.numpy()})[0]
    b = sess.run(None, {"points": (pts + torch.tensor([1000.0, -500.0, 20.0])).numpy()})[0]
    assert a.shape == (1, 3000, 64)
    assert np.allclose(np.linalg.norm(a, axis=-1), 1.0, atol=1e-4)
    # Centring inside the graph: moving the map origin changes (almost) nothing.
    assert np.median(np.abs(a - b)) < 1e-3


def test_to_correlation_cuts_a_features_form_agent_without_changing_it(tmp_path):
    """v3 and older ship the agent in the features form; `--to-correlation` cuts the graph at the
    correlation volume. The cut graph fed with `Agent.correlate` answers as the network did."""
    torch.manual_seed(1)
    models = build_all()
    for m in models.values():
        m.eval()
    doc = export_models(models, tmp_path, dict(data="test", seeds={}), correlation=False)
    assert "state_2d" not in doc and list(doc["graphs"]["agent"]["inputs"]) == ["state_2d", "state_3d"]
    doc = to_correlation(tmp_path)
    assert doc["state_2d"]["form"] == "correlation"
    assert json.loads((tmp_path / "manifest.json").read_text()) == doc
    data = (tmp_path / "agent.onnx").read_bytes()
    assert hashlib.sha256(data).hexdigest() == doc["graphs"]["agent"]["sha256"]
    sess = ort.InferenceSession(data, providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == ["correlation", "state_3d"]
    state_2d, state_3d = example_inputs("agent", batch=2, seed=5)
    with torch.no_grad():
        want = models["agent"](state_2d, state_3d)
        volume = models["agent"].correlate(state_2d)
    got = sess.run(None, {"correlation": volume.numpy(), "state_3d": state_3d.numpy()})
    for w, g_ in zip(want, got):
        assert np.abs(w.numpy() - g_).max() <= 1e-4 * max(np.abs(w.numpy()).max(), 1e-6)
    # The FLOPs left in the graph: the dense correlation product is gone.
    assert doc["graphs"]["agent"]["flops"] < 0.5 * 146e6
    with pytest.raises(ValueError, match="already"):
        to_correlation(tmp_path)


def test_to_correlation_refuses_an_agent_without_a_correlation(tmp_path):
    from cmr.fixture_models import TinyAgent, TinyFrustumHead, TinyImageEncoder, TinyPointEncoder
    torch.manual_seed(0)
    models = {"point_encoder": TinyPointEncoder(), "image_encoder": TinyImageEncoder(),
              "frustum_head": TinyFrustumHead(), "agent": TinyAgent()}
    export_models(models, tmp_path, dict(data="test", seeds={}))
    with pytest.raises(ValueError, match="not models.Agent"):
        to_correlation(tmp_path)


def test_only_replaces_the_named_graphs_when_they_answer_the_same(tmp_path):
    """`--only`: today's graphs of the same weights replace the old ones; other weights are
    refused and leave the set as it was."""
    from cmr.export import replace_graphs
    torch.manual_seed(3)
    models = build_all()
    for m in models.values():
        m.eval()
    export_models(models, tmp_path, dict(data="test", seeds={}))
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    other = build_all()
    for name in ("agent", "point_encoder"):
        with pytest.raises(ValueError, match=f"new {name} graph differs"):
            replace_graphs(tmp_path, {"frustum_head": models["frustum_head"], name: other[name].eval()}, "other")
        assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    doc = replace_graphs(tmp_path, {k: models[k] for k in ("agent", "point_encoder")}, "same")
    for name in ("agent", "point_encoder"):
        data = (tmp_path / f"{name}.onnx").read_bytes()
        assert hashlib.sha256(data).hexdigest() == doc["graphs"][name]["sha256"]
        assert "same" in doc["provenance"][f"{name}_graph"]
    assert json.loads((tmp_path / "manifest.json").read_text()) == doc
    for name in ("image_encoder", "frustum_head"):
        assert (tmp_path / f"{name}.onnx").read_bytes() == before[f"{name}.onnx"]


def test_point_encoder_is_deterministic_on_two_threads(exported):
    """The point encoder answers the same on every run with two intra-op threads (an export with
    ScatterND and a max reduction, tried for speed, did not: that op races in ONNX Runtime 1.31)."""
    import onnx
    _, out, _ = exported
    ops = [n.op_type for n in onnx.load(str(out / "point_encoder.onnx")).graph.node]
    assert "ScatterND" not in ops
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 2
    sess = ort.InferenceSession(str(out / "point_encoder.onnx"), opts, providers=["CPUExecutionProvider"])
    (pts,) = example_inputs("point_encoder", num_points=20000, seed=3)
    first = sess.run(None, {"points": pts.numpy()})[0]
    for _ in range(5):
        assert np.array_equal(sess.run(None, {"points": pts.numpy()})[0], first)


def test_point_encoder_graph_has_no_emptiness_guard(exported):
    """`without_empty_guards` wires in the scatter's else branch: no `If` left, and the graph still
    answers as the network on clouds of 1, 7 and 5,000 points."""
    import onnx
    models, out, _ = exported
    assert "If" not in [n.op_type for n in onnx.load(str(out / "point_encoder.onnx")).graph.node]
    sess = ort.InferenceSession(str(out / "point_encoder.onnx"), providers=["CPUExecutionProvider"])
    for n in (1, 7, 5000):
        (pts,) = example_inputs("point_encoder", num_points=n, seed=n)
        with torch.no_grad():
            want = models["point_encoder"](pts).numpy()
        got = sess.run(None, {"points": pts.numpy()})[0]
        assert got.shape == want.shape and np.abs(got - want).max() < 1e-4, n


def test_pooled_points_is_the_pointnet_max(exported):
    """`Agent.pooled_points` (channel-major, bias and ReLU after the max) is `pointnet(...).amax`."""
    agent = exported[0]["agent"]
    _, state_3d = example_inputs("agent", batch=3, seed=4)
    with torch.no_grad():
        want = agent.pointnet(state_3d).amax(dim=1)
        got = agent.pooled_points(state_3d)
    assert torch.allclose(got, want, rtol=1e-5, atol=1e-6)


def test_the_tiny_intensity_fixture_reads_the_rank(tmp_path):
    """`python -m cmr.fixture_models --intensity`: the manifest names the four columns, and the
    point encoder's features move with the fourth (what the Rust tests of intensity sets need)."""
    from cmr.fixture_models import main

    main(str(tmp_path), intensity=True)
    doc = json.loads((tmp_path / "manifest.json").read_text())
    assert doc["points"]["channels"] == ["x", "y", "z", "intensity_rank"]
    assert doc["graphs"]["point_encoder"]["inputs"] == {"points": [1, "N", 4]}
    session = ort.InferenceSession(str(tmp_path / "point_encoder.onnx"), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(1, 256, 3)).astype(np.float32) * 10
    rank = rng.random((1, 256, 1)).astype(np.float32)
    run = lambda r: session.run(None, {"points": np.concatenate([xyz, r], -1)})[0]
    assert np.abs(run(rank) - run(np.full_like(rank, 0.5))).max() > 0.05
