"""Evaluation figures and the model card come from real runs of the pipeline."""

import json

from cmr.data import find_sequences, list_frames
from cmr.evaluate import evaluate
from cmr.export import export_models
from cmr.model_card import data_summary, render
from cmr.models import build_all


def test_evaluation_and_model_card(tmp_path, tiny_dataset):
    models = build_all()
    frames = list_frames(find_sequences(tiny_dataset))[:2]
    result = evaluate(models, frames, iterations=3, num_points=2048, chunk=2)
    assert [r["iteration"] for r in result["agent"]] == [1, 2, 3]
    assert result["expert"][-1]["rte_m"] < result["initial"]["rte_m"]  # the teacher makes progress
    assert 0.0 <= result["frustum"]["precision"] <= 1.0 and 0.0 <= result["match_accuracy"] <= 1.0
    doc = export_models(models, tmp_path, dict(data="test", seeds={}), dict(final=result["agent"][-1]))
    text = render(doc, result, {"agent_ms": 1.0}, data_summary([str(tiny_dataset)]), [], "curves.png", "note")
    assert "| 3 |" in text and "Greedy expert" in text and str(sum(doc["parameters"].values())) not in ("0",)
    assert json.loads((tmp_path / "manifest.json").read_text())["validation"]["final"]["iteration"] == 3
