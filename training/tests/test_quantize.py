"""cmr.quantize: a model set's Conv layers in int8 (QDQ), calibrated on frames, checked against the
float set it came from; the quantised set still imports for fine-tuning."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest

from cmr.data import find_sequences, list_frames
from cmr.export import export_models
from cmr.import_onnx import dequantized, import_models
from cmr.quantize import (QUANTIZED, RECIPES, WEIGHT_LIMIT, calibration_inputs, feature_agreement, int8_weight_range,
                          quantize_set)
from test_import_onnx import randomised


@pytest.fixture(scope="module")
def sets(tmp_path_factory, tiny_dataset):
    root = tmp_path_factory.mktemp("quantize")
    float_dir, int8_dir = root / "float", root / "int8"
    export_models(randomised("batch"), float_dir, dict(data="test", seeds={}))
    frames = list_frames(find_sequences(tiny_dataset))[:2]
    quantize_set(float_dir, int8_dir, frames, QUANTIZED, hypotheses=2, steps=2, max_rows=16)
    return float_dir, int8_dir, frames


def _producers(model):
    return {o: n for n in model.graph.node for o in n.output}


def test_only_convolutions_are_quantised(sets):
    _, int8_dir, _ = sets
    for name in QUANTIZED:
        model = onnx.load(str(int8_dir / f"{name}.onnx"))
        producer = _producers(model)
        from_dq = lambda node: [i for i in node.input if getattr(producer.get(i), "op_type", "") == "DequantizeLinear"]  # noqa: E731
        convs = [n for n in model.graph.node if n.op_type == "Conv"]
        if RECIPES[name]["first_conv_float"]:  # the stem reads pixels in float
            assert not from_dq(convs[0]), f"{name}: {convs[0].name} is quantised"
            convs = convs[1:]
        assert convs and all(len(from_dq(n)) >= 2 for n in convs), name  # activation and weight
        for node in model.graph.node:
            if node.op_type in ("MatMul", "Gemm"):
                assert not from_dq(node), f"{name}: {node.name} reads a dequantised tensor"


def test_quantised_graphs_answer_as_the_float_ones(sets):
    float_dir, int8_dir, frames = sets
    models, _ = import_models(float_dir)
    feeds = calibration_inputs(models, frames, hypotheses=2, steps=2, max_rows=16)
    for name in QUANTIZED:
        want_session = ort.InferenceSession(str(float_dir / f"{name}.onnx"), providers=["CPUExecutionProvider"])
        got_session = ort.InferenceSession(str(int8_dir / f"{name}.onnx"), providers=["CPUExecutionProvider"])
        for feed in feeds[name][:2]:
            want, got = want_session.run(None, feed)[0], got_session.run(None, feed)[0]
            assert np.isfinite(got).all()
            if RECIPES[name]["method"] == "MinMax":  # every value inside the calibrated ranges
                rel = np.abs(want - got).max() / np.abs(want).max()
            else:  # RMS: a percentile calibration clips the rare extremes on purpose
                rel = np.sqrt(np.mean((want - got) ** 2) / np.mean(want ** 2))
            assert 0 < rel < 0.05, f"{name}: relative error {rel:.3g}"


def test_int8_weights_fit_seven_bits_so_every_cpu_computes_the_same(sets):
    """x86 CPUs without VNNI (AVX2 only) multiply uint8 activations by int8 weights and add the
    products pairwise in int16, which saturates beyond 32,767: with weights within 7 bits it cannot,
    and ONNX Runtime's fused integer kernels compute exactly what the QDQ graph says (what ONNX
    Runtime computes with its optimisations off, in float, to rounding: an activation rounded the
    other way now and then, which deeper graphs carry on). On an AVX2-only CPU (2026-12-07) the same
    set with 8-bit weights was off by 1.2-1.4 % RMS in the image encoder; with 7 bits by 0.004-0.07 %."""
    float_dir, int8_dir, frames = sets
    models, _ = import_models(float_dir)
    feeds = calibration_inputs(models, frames, hypotheses=2, steps=2, max_rows=16)
    for name in QUANTIZED:
        lo, hi = int8_weight_range(onnx.load(str(int8_dir / f"{name}.onnx")))
        assert -WEIGHT_LIMIT <= lo < 0 < hi <= WEIGHT_LIMIT, (name, lo, hi)
        runs = []
        for level in (ort.GraphOptimizationLevel.ORT_ENABLE_ALL, ort.GraphOptimizationLevel.ORT_DISABLE_ALL):
            options = ort.SessionOptions()
            options.graph_optimization_level = level
            runs.append(ort.InferenceSession(str(int8_dir / f"{name}.onnx"), options, providers=["CPUExecutionProvider"]))
        for feed in feeds[name][:2]:
            fused, reference = (s.run(None, feed)[0] for s in runs)
            assert np.sqrt(np.mean((fused - reference) ** 2) / np.mean(reference ** 2)) <= 2e-3, name


def test_the_shipped_int8_weights_fit_seven_bits():
    shipped = Path(__file__).resolve().parents[2] / "models"
    doc = json.loads((shipped / "manifest.json").read_text())
    for name, spec in doc["graphs"].items():
        lo, hi = int8_weight_range(onnx.load(str(shipped / spec["file"])))
        assert -WEIGHT_LIMIT <= lo <= hi <= WEIGHT_LIMIT, (name, lo, hi)


def test_a_row_does_not_depend_on_its_batch(sets):
    """Activation scales are fixed at calibration: a row next to an outlier answers as alone (a
    dynamically quantised graph would rescale the whole batch to the outlier)."""
    _, int8_dir, _ = sets
    session = ort.InferenceSession(str(int8_dir / "agent.onnx"), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(3)
    corr = rng.uniform(-0.3, 0.3, (2, *session.get_inputs()[0].shape[1:])).astype(np.float32)
    corr[1] *= 100.0
    state = rng.uniform(0, 1, (2, *session.get_inputs()[1].shape[1:])).astype(np.float32)
    alone = session.run(None, {"correlation": corr[:1], "state_3d": state[:1]})[0]
    batched = session.run(None, {"correlation": corr, "state_3d": state})[0][:1]
    assert np.abs(alone - batched).max() <= 1e-5 * max(np.abs(alone).max(), 1.0)


def test_the_set_names_its_files_and_keeps_the_other_graphs(sets):
    float_dir, int8_dir, _ = sets
    doc = json.loads((int8_dir / "manifest.json").read_text())
    for name, spec in doc["graphs"].items():
        data = (int8_dir / spec["file"]).read_bytes()
        assert hashlib.sha256(data).hexdigest() == spec["sha256"]
        if name not in QUANTIZED:
            assert data == (float_dir / spec["file"]).read_bytes()
    assert doc["provenance"]["quantized"]["graphs"] == list(QUANTIZED)
    assert "Percentile 99.9" in doc["provenance"]["quantized"]["recipes"]["image_encoder"]
    assert "within 7 bits" in doc["provenance"]["quantized"]["format"]  # the server's start-up check reads it
    with pytest.raises(ValueError, match="--out must differ"):
        quantize_set(int8_dir, int8_dir, [])
    with pytest.raises(ValueError, match="quantised already"):
        quantize_set(int8_dir, int8_dir.parent / "twice", [])
    assert not (int8_dir.parent / "twice").exists()


def test_a_quantised_set_imports_with_its_dequantised_weights(sets):
    float_dir, int8_dir, _ = sets
    floats, _ = import_models(float_dir)
    imported, _ = import_models(int8_dir)  # checked inside against the dequantised graphs
    model = dequantized(onnx.load(str(int8_dir / "agent.onnx")))
    assert not any(n.op_type in ("QuantizeLinear", "DequantizeLinear") for n in model.graph.node)
    want = floats["agent"].state_dict()["cnn.0.weight"]
    got = imported["agent"].state_dict()["cnn.0.weight"]
    step = want.abs().flatten(1).max(dim=1).values / WEIGHT_LIMIT  # per output channel
    assert not got.equal(want)
    assert ((got - want).abs().flatten(1).max(dim=1).values <= step * 0.5 + 1e-7).all()


def test_feature_agreement_measures_the_int8_encoder_against_the_float_one(sets):
    float_dir, int8_dir, frames = sets
    same = feature_agreement(float_dir, float_dir, frames)
    assert same["frames"] == 2 and same["cells"] == 2 * 40 * 128
    assert same["min"] > 0.99999
    int8 = feature_agreement(float_dir, int8_dir, frames)
    assert 0.9 < int8["mean"] < 1.0 - 1e-6  # quantised: close, but not the float graph
    assert int8["min"] <= int8["p01"] <= int8["mean"]
    with pytest.raises(ValueError, match="no frames"):
        feature_agreement(float_dir, int8_dir, [])
