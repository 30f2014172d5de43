"""Floating-point operations of the four graphs, counted from the ONNX files (not from PyTorch).

FLOPs per op: Conv / ConvTranspose 2·Cin/groups·kh·kw per output element; MatMul and Gemm 2·K per
output element; reductions one per input element; every other op with a float output one per
output element (activations, elementwise arithmetic, resizes); shape-only ops zero. Shapes come
from ONNX shape inference with the dynamic axes fixed to one request's sizes: N points, batch 1
(the agent's count is per policy row). Control flow (`If`) bodies are not counted.

    python -m cmr.flops ../models             # prints the table
    python -m cmr.flops ../models --write     # also records graphs.<name>.flops in manifest.json
"""

import argparse
import json
from pathlib import Path

import numpy as np
import onnx
from onnx import shape_inference

SHAPE_ONLY = {"Shape", "Size", "Constant", "ConstantOfShape", "Reshape", "Flatten", "Squeeze", "Unsqueeze", "Transpose",
              "Slice", "Gather", "GatherElements", "Concat", "Expand", "Cast", "Identity", "If", "Pad", "Equal",
              "Greater", "Where", "ScatterElements", "Floor"}
REDUCTIONS = {"ReduceSum", "ReduceMean", "ReduceMax", "ReduceMin", "AveragePool", "MaxPool", "GlobalAveragePool"}


def _fixed(model: onnx.ModelProto, sizes: dict[str, int]) -> onnx.ModelProto:
    """A copy whose symbolic input dims are replaced by `sizes` (by dim_param), default 1."""
    model = onnx.ModelProto.FromString(model.SerializeToString())
    for value in model.graph.input:
        for dim in value.type.tensor_type.shape.dim:
            if dim.dim_param or dim.dim_value == 0:
                dim.dim_value = sizes.get(dim.dim_param, 1)
    return shape_inference.infer_shapes(model, data_prop=True)


def _shapes(model: onnx.ModelProto) -> dict[str, list[int]]:
    out = {}
    for value in list(model.graph.value_info) + list(model.graph.input) + list(model.graph.output):
        dims = [d.dim_value if d.dim_value > 0 else None for d in value.type.tensor_type.shape.dim]
        out[value.name] = dims
    for init in model.graph.initializer:
        out[init.name] = list(init.dims)
    return out


def _numel(dims) -> int | None:
    if dims is None or any(d is None for d in dims):
        return None
    return int(np.prod(dims)) if dims else 1


def count(model: onnx.ModelProto, sizes: dict[str, int]) -> tuple[int, list[str]]:
    """FLOPs of one run, and the ops whose shapes inference could not resolve."""
    model = _fixed(model, sizes)
    shapes = _shapes(model)
    total, unresolved = 0, []
    for node in model.graph.node:
        if node.op_type in SHAPE_ONLY:
            continue
        out = _numel(shapes.get(node.output[0]))
        if out is None:
            unresolved.append(f"{node.op_type}:{node.name}")
            continue
        if node.op_type in ("Conv", "ConvTranspose"):
            w = shapes.get(node.input[1])
            if w is None or any(d is None for d in w):
                unresolved.append(f"{node.op_type}:{node.name}")
                continue
            groups = next((a.i for a in node.attribute if a.name == "group"), 1)
            per = 2 * int(np.prod(w[1:])) if node.op_type == "Conv" else 2 * w[0] // groups * int(np.prod(w[2:]))
            total += per * out
        elif node.op_type in ("MatMul", "Gemm"):
            a = shapes.get(node.input[0]) or [None]
            trans_a = next((a_.i for a_ in node.attribute if a_.name == "transA"), 0)
            k = a[-2] if trans_a else a[-1]
            if k is None:
                unresolved.append(f"{node.op_type}:{node.name}")
                continue
            total += 2 * k * out
        elif node.op_type in REDUCTIONS:
            total += _numel(shapes.get(node.input[0])) or out
        else:
            total += out
    return total, unresolved


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("models", type=Path)
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()
    manifest_path = args.models / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    n = manifest["points"]["num_points"]
    for name, spec in manifest["graphs"].items():
        model = onnx.load(str(args.models / spec["file"]))
        flops, unresolved = count(model, {"N": n, "B": 1})
        note = f"  (unresolved: {', '.join(unresolved[:4])})" if unresolved else ""
        print(f"{name:14s} {flops / 1e9:8.4f} GFLOP{' per policy row' if name == 'agent' else ''}{note}")
        spec["flops"] = int(flops)
    if args.write:
        manifest_path.write_text(json.dumps(manifest, indent=2) + "\n")


if __name__ == "__main__":
    main()
