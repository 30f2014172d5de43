"""CMR-Agent training pipeline: data, models, losses, training loops and ONNX export."""
