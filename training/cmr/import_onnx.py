"""A training checkpoint from an exported model set: the reverse of `export`, so the shipped
`models/` can be fine-tuned (or re-evaluated in PyTorch) without the run that produced it.

    python -m cmr.import_onnx ../models --out runs/shipped/import.pt
    python -m cmr.train --data D --out runs/ft --set init_from=runs/shipped/import.pt embed_steps=0 ...

How the weights are found. ONNX export folds each BatchNorm into the convolution before it, stores
`Linear` weights transposed as MatMul operands and names many initializers by number
(`onnx::Conv_251`). So names are not used: a fresh set of the same architecture is filled with
random "tag" values (BatchNorm scale 1, running mean 0, running variance 1 - eps, so folding leaves
the tags as they are) and exported with `export.onnx_bytes`; every initializer of that export is
matched to the parameter (or its transpose) it equals, and the model set's initializers, taken in
the same first-use order through the graph, are written back through that table. A folded
BatchNorm comes back as scale 1, mean 0, variance 1 - eps and the folded shift: the same function
in evaluation mode (a later stage-1 run in training mode would start from different batch
statistics).

The result is checked, not trusted: each imported PyTorch module must answer as the ONNX graph
does in ONNX Runtime on the contract's example inputs (relative error < 1e-4), else ValueError.
The architecture (`norm`, `image_edges`, `image_backbone`) is the one whose export has the model set's initializer
shapes; the action frame comes from the manifest (`actions.frame`, absent = camera_y).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import numpy_helper

from . import geometry as g
from .export import graph_inputs, is_correlation_agent, onnx_bytes
from .models import IMAGE_BACKBONES, NORMS, build_all

RTOL = 1e-4


def first_use_order(model: onnx.ModelProto) -> list[np.ndarray]:
    """The graph's initializers as arrays, in the order nodes first read them (export order is
    deterministic for one architecture; numbered names are not)."""
    inits = {i.name: i for i in model.graph.initializer}
    seen: dict[str, np.ndarray] = {}
    for node in model.graph.node:
        for name in node.input:
            if name in inits and name not in seen:
                seen[name] = numpy_helper.to_array(inits[name])
    return list(seen.values())


def dequantized(model: onnx.ModelProto) -> onnx.ModelProto:
    """A QDQ-quantised graph (`cmr.quantize`) as a float graph: each DequantizeLinear of a constant
    (int8 weight, int32 bias; per-tensor or per-channel) becomes the float initializer
    (q - zero_point) * scale, and each activation's QuantizeLinear -> DequantizeLinear pair is
    dropped. The weights are those the quantised graph computes with; only the activations'
    rounding is gone. A float graph comes back unchanged (a copy)."""
    out = onnx.ModelProto()
    out.CopyFrom(model)
    graph = out.graph
    inits = {i.name: i for i in graph.initializer}
    producer = {o: n for n in graph.node for o in n.output}
    rename: dict[str, str] = {}
    folded, kept = [], []
    for node in graph.node:
        if node.op_type == "DequantizeLinear" and node.input[0] in inits:
            q = numpy_helper.to_array(inits[node.input[0]]).astype(np.float64)
            scale = numpy_helper.to_array(inits[node.input[1]]).astype(np.float64)
            zero = (numpy_helper.to_array(inits[node.input[2]]).astype(np.float64)
                    if len(node.input) > 2 and node.input[2] else np.zeros_like(scale))
            if scale.ndim == 1 and q.ndim > 1:  # per channel along `axis` (default 1)
                axis = next((a.i for a in node.attribute if a.name == "axis"), 1)
                shape = [1] * q.ndim
                shape[axis] = -1
                scale, zero = scale.reshape(shape), zero.reshape(shape)
            folded.append(numpy_helper.from_array(((q - zero) * scale).astype(np.float32), node.output[0]))
        elif node.op_type == "DequantizeLinear" and getattr(producer.get(node.input[0]), "op_type", "") == "QuantizeLinear":
            rename[node.output[0]] = producer[node.input[0]].input[0]
        elif node.op_type != "QuantizeLinear":
            kept.append(node)
    if not folded and not rename:
        return out

    def source(name: str) -> str:
        while name in rename:
            name = rename[name]
        return name

    for node in kept:
        node.input[:] = [source(i) for i in node.input]
    for value in graph.output:
        if source(value.name) != value.name:
            kept.append(onnx.helper.make_node("Identity", [source(value.name)], [value.name]))
    del graph.node[:]
    graph.node.extend(kept)
    used = {i for node in kept for i in node.input}
    remaining = [i for i in graph.initializer if i.name in used] + [i for i in folded if i.name in used]
    del graph.initializer[:]
    graph.initializer.extend(remaining)
    return out


def _tag(module: torch.nn.Module, seed: int) -> None:
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.rand(p.shape, generator=gen) * 2 - 1)
        for m in module.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.weight.fill_(1.0)
                m.running_mean.zero_()
                m.running_var.fill_(1.0 - m.eps)


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return a.size == b.size and np.allclose(a.reshape(-1), b.reshape(-1), rtol=1e-5, atol=1e-6)


def weight_table(name: str, module: torch.nn.Module, correlation: bool, seed: int = 0):
    """Tags `module` (distinct values: the exporter merges equal constants, such as fresh zero
    shifts) and returns [(parameter name or None, transposed)] per initializer of its export, in
    first-use order, and the export's arrays (for the shapes). Raises ValueError when a parameter
    other than a BatchNorm scale has no initializer."""
    _tag(module, seed)
    arrays = first_use_order(onnx.load_from_string(onnx_bytes(name, module.eval(), correlation)))
    params = {k: p.detach().numpy() for k, p in module.named_parameters()}
    table, used = [], set()
    for arr in arrays:
        hit = None
        for k, p in params.items():
            if _same(arr, p):  # any shape of the same values (a GroupNorm scale is stored as [C, 1, 1])
                hit = (k, False)
            elif p.ndim == 2 and arr.shape == p.T.shape and _same(arr, p.T):
                hit = (k, True)
            if hit:
                break
        table.append(hit or (None, False))
        if hit:
            used.add(hit[0])
    bn_scales = {f"{k}.weight" for k, m in module.named_modules() if isinstance(m, torch.nn.BatchNorm2d)}
    missing = set(params) - used - bn_scales
    if missing:
        raise ValueError(f"{name}: parameters with no initializer in the export: {sorted(missing)}")
    return table, arrays


def _tables_if_matching(models: dict, graphs: dict, correlation: bool) -> dict | None:
    """{graph: `weight_table`} when every graph's tagged export of `models` has the model set's
    initializer shapes in the same order, else None (another architecture)."""
    tables = {}
    for name, model in graphs.items():
        table, ours = weight_table(name, models[name], correlation)
        if [a.shape for a in ours] != [a.shape for a in first_use_order(model)]:
            return None
        tables[name] = table
    return tables


def check_against_onnx(name: str, module: torch.nn.Module, model: onnx.ModelProto, correlation: bool) -> float:
    """Largest relative difference between the module and the graph in ONNX Runtime on the
    contract's example inputs; ValueError above `RTOL`."""
    import onnxruntime as ort

    module = module.eval()
    inputs = graph_inputs(name, module, correlation, batch=2, seed=7)
    with torch.no_grad():
        # A correlation-form agent's graph starts after `correlate`: it is `decide`.
        want = module.decide(*inputs) if name == "agent" and correlation and is_correlation_agent(module) else module(*inputs)
    want = [w.numpy() for w in (want if isinstance(want, tuple) else (want,))]
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    feeds = {i.name: x.numpy() for i, x in zip(session.get_inputs(), inputs)}
    got = session.run(None, feeds)
    worst = max(float(np.abs(w - o).max() / max(np.abs(w).max(), 1e-6)) for w, o in zip(want, got))
    if not worst < RTOL:
        raise ValueError(f"{name}: the imported module differs from the graph (relative error {worst:.2e})")
    return worst


def import_models(model_dir: Path) -> tuple[dict[str, torch.nn.Module], dict]:
    """(modules in evaluation mode, checkpoint meta) from a model set (manifest + four graphs).
    Raises ValueError when no known architecture has the set's initializers or a module does not
    reproduce its graph."""
    model_dir = Path(model_dir)
    doc = json.loads((model_dir / "manifest.json").read_text())
    correlation = doc.get("state_2d", {}).get("form", "features") == "correlation"
    # A quantised set (`cmr.quantize`) comes back with its weights dequantised.
    graphs = {name: dequantized(onnx.load(str(model_dir / spec["file"]))) for name, spec in doc["graphs"].items()}
    archs = [dict(norm=norm, image_edges=edges, image_backbone="scratch") for norm in NORMS for edges in (False, True)]
    archs += [dict(norm=norm, image_edges=False, image_backbone=b) for norm in NORMS for b in IMAGE_BACKBONES if b != "scratch"]
    archs += [dict(arch, point_encoder=p) for arch in archs for p in ("pillars_fine", "pillars_intensity")]
    for arch in archs:
        models = build_all(**arch)
        tables = _tables_if_matching(models, graphs, correlation)
        if tables is not None:
            break
    else:
        raise ValueError(f"{model_dir}: no architecture of models.build_all has these graphs' initializers")

    # The tagged modules have the folded BatchNorm's identity statistics already; only the
    # matched parameters take the set's values.
    errors = {}
    for name, module in models.items():
        state = module.state_dict()  # references to the module's tensors
        with torch.no_grad():
            for (param, transposed), arr in zip(tables[name], first_use_order(graphs[name])):
                if param is not None:
                    value = torch.from_numpy(arr.T.copy() if transposed else arr.copy())
                    state[param].copy_(value.reshape(state[param].shape))
        errors[name] = check_against_onnx(name, module, graphs[name], correlation)

    training = doc.get("provenance", {}).get("training", {})
    meta = dict(data=doc.get("provenance", {}).get("data", "unknown"), seeds=doc.get("provenance", {}).get("seeds", {}),
                config=dict(arch, action_frame=g.check_frame(doc.get("actions", {}).get("frame", g.CAMERA_Y))),
                training=training, imported_from=str(model_dir), import_relative_error=errors)
    return models, meta


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("models", type=Path, help="model set: manifest.json and its graphs")
    ap.add_argument("--out", type=Path, required=True, help="checkpoint to write (.pt)")
    args = ap.parse_args(argv)
    models, meta = import_models(args.models)
    training = meta["training"]
    state = dict(models={k: m.state_dict() for k, m in models.items()}, embed_step=training.get("embed_steps", 0),
                 agent_iter=training.get("agent_iters", 0), best=None, meta=meta)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    torch.save(state, tmp)
    tmp.replace(args.out)
    print(json.dumps({k: meta[k] for k in ("config", "import_relative_error")}, indent=2))


if __name__ == "__main__":
    main()
