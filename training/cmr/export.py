"""Export the four graphs to ONNX and write `models/manifest.json` (format cmr-agent-manifest/1).

    python -m cmr.export --checkpoint runs/x/agent.pt --out ../models [--validation eval.json]
    python -m cmr.export --to-correlation ../models
    python -m cmr.export --checkpoint runs/x/agent.pt --out ../models --only agent,point_encoder

Without --checkpoint the graphs carry their random initialisation (said so in the provenance).
Every file is written atomically (temp file in the same directory, fsync, rename).

The agent is exported in the correlation form (manifest `state_2d.form`): the graph starts after
`Agent.correlate`, which is parameter-free and which the server computes in Rust on the occupied
cells only; a network without `correlate` (the tiny test fixture) keeps the features form.
`--to-correlation DIR` converts a features-form model set whose agent is `models.Agent` (v3 and
older) by cutting its ONNX graph at the correlation volume: same weights, checked against the
uncut graph on random states before anything is written.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import hashlib
import io
import json
import warnings
from pathlib import Path

import numpy as np
import onnx
import onnx.utils
import torch

from . import geometry as g
from .data import FOCAL_RANGE_PX
from .files import atomic_write_bytes, git_commit  # noqa: F401 (re-exported: quantize, model_card, evaluate)
from .flops import count as count_flops
from .models import (COLUMN_SHIFTS, FEATURE_DIM, GRID_HEIGHT, GRID_WIDTH, IMAGE_HEIGHT, IMAGE_WIDTH, NUM_DOFS,
                     NUM_STEPS, ROW_SHIFTS, STRIDE, Agent, arch_of, build_all, parameter_counts,
                     point_channels_of)

MANIFEST_FORMAT = "cmr-agent-manifest/1"
OPSET = 18
NUM_POINTS = 40960
NUM_STATE_POINTS = 2048
STATE_XYZ_SCALE_M = 10.0
IMAGE_MEAN = (0.485, 0.456, 0.406)
IMAGE_STD = (0.229, 0.224, 0.225)
NOMINAL_SCALE = 0.5

# name -> (input names, output names, dynamic axes)
GRAPH_IO = {
    "point_encoder": (["points"], ["point_features"], {"points": {1: "N"}, "point_features": {1: "N"}}),
    "image_encoder": (["image"], ["image_features"], {}),
    "frustum_head": (["point_features", "image_features"], ["frustum_logits"],
                     {"point_features": {1: "N"}, "frustum_logits": {1: "N"}}),
    "agent": (["correlation", "state_3d"], ["policy_logits", "value"],
              {"correlation": {0: "B"}, "state_3d": {0: "B"}, "policy_logits": {0: "B"}, "value": {0: "B"}}),
}
# The agent in the features form (networks without `correlate`).
AGENT_FEATURES_IO = (["state_2d", "state_3d"], ["policy_logits", "value"],
                     {"state_2d": {0: "B"}, "state_3d": {0: "B"}, "policy_logits": {0: "B"}, "value": {0: "B"}})
CORRELATION_CHANNELS = len(ROW_SHIFTS) + len(COLUMN_SHIFTS) + 1
CORRELATION_STATE = dict(form="correlation", row_shifts=list(ROW_SHIFTS), column_shifts=list(COLUMN_SHIFTS))

CONTRACT_SHAPES = {
    "point_encoder": ({"points": [1, "N", 3]}, {"point_features": [1, "N", FEATURE_DIM]}),
    "image_encoder": ({"image": [1, 3, IMAGE_HEIGHT, IMAGE_WIDTH]},
                      {"image_features": [1, FEATURE_DIM, GRID_HEIGHT, GRID_WIDTH]}),
    "frustum_head": ({"point_features": [1, "N", FEATURE_DIM],
                      "image_features": [1, FEATURE_DIM, GRID_HEIGHT, GRID_WIDTH]},
                     {"frustum_logits": [1, "N"]}),
    "agent": ({"correlation": ["B", CORRELATION_CHANNELS, GRID_HEIGHT, GRID_WIDTH], "state_3d": ["B", NUM_STATE_POINTS, 5]},
              {"policy_logits": ["B", NUM_DOFS, NUM_STEPS], "value": ["B", 1]}),
}
AGENT_FEATURES_SHAPES = ({"state_2d": ["B", 2 * FEATURE_DIM, GRID_HEIGHT, GRID_WIDTH], "state_3d": ["B", NUM_STATE_POINTS, 5]},
                         {"policy_logits": ["B", NUM_DOFS, NUM_STEPS], "value": ["B", 1]})


class AgentOnCorrelation(torch.nn.Module):
    """`Agent.decide` as a graph: (correlation [B, S+1, GH, GW], state_3d [B, M, 5]) -> (policy
    logits [B, 3, 11], value [B, 1])."""

    def __init__(self, agent: Agent):
        super().__init__()
        self.agent = agent

    def forward(self, correlation, state_3d):
        return self.agent.decide(correlation, state_3d)


def is_correlation_agent(module: torch.nn.Module) -> bool:
    return hasattr(module, "correlate") and hasattr(module, "decide")


# The point encoder's input columns: x, y, z (map frame, metres), and for an intensity encoder each
# point's intensity rank among the N (`data.intensity_rank`). The manifest names them.
POINT_CHANNELS = {3: ["x", "y", "z"], 4: ["x", "y", "z", "intensity_rank"]}


def example_inputs(name: str, num_points: int = 4096, batch: int = 1, seed: int = 0,
                   point_channels: int = 3) -> tuple[torch.Tensor, ...]:
    """Random inputs with the contract's shapes (the points look like a street-sized cloud; with
    `point_channels` = 4 a uniform intensity rank beside them)."""
    gen = torch.Generator().manual_seed(seed)
    if name == "point_encoder":
        pts = torch.randn(1, num_points, 3, generator=gen) * torch.tensor([15.0, 15.0, 1.5]) + torch.tensor([5.0, -3.0, 0.0])
        if point_channels == 4:
            pts = torch.cat([pts, torch.rand(1, num_points, 1, generator=gen)], dim=-1)
        return (pts,)
    if name == "image_encoder":
        return (torch.randn(1, 3, IMAGE_HEIGHT, IMAGE_WIDTH, generator=gen),)
    if name == "frustum_head":
        pf = torch.nn.functional.normalize(torch.randn(1, num_points, FEATURE_DIM, generator=gen), dim=-1)
        im = torch.nn.functional.normalize(torch.randn(1, FEATURE_DIM, GRID_HEIGHT, GRID_WIDTH, generator=gen), dim=1)
        return pf, im
    if name == "agent":
        s2 = torch.randn(batch, 2 * FEATURE_DIM, GRID_HEIGHT, GRID_WIDTH, generator=gen) * 0.1
        # A state has empty cells (exactly zero point features), as in the server.
        s2[:, FEATURE_DIM:] *= (torch.rand(batch, 1, GRID_HEIGHT, GRID_WIDTH, generator=gen) < 0.4).float()
        s3 = torch.rand(batch, NUM_STATE_POINTS, 5, generator=gen)
        return s2, s3
    raise KeyError(name)


def graph_inputs(name: str, module: torch.nn.Module, correlation: bool, batch: int = 1, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """`example_inputs` as graph `name`'s ONNX export takes them: for an agent exported in the
    correlation form, `Agent.correlate` of the random state in place of the state."""
    inputs = example_inputs(name, batch=batch, seed=seed, point_channels=point_channels_of(module))
    if name == "agent" and correlation and is_correlation_agent(module):
        with torch.no_grad():
            inputs = (module.eval().correlate(inputs[0]), inputs[1])
    return inputs


def onnx_bytes(name: str, module: torch.nn.Module, correlation: bool = True) -> bytes:
    """One graph as ONNX bytes; `correlation`: export an agent that has `correlate` in the
    correlation form (else the features form)."""
    inputs, outputs, dynamic = GRAPH_IO[name]
    example = example_inputs(name, point_channels=point_channels_of(module))
    if name == "agent":
        if correlation and is_correlation_agent(module):
            with torch.no_grad():
                example = (module.eval().correlate(example[0]), example[1])
            module = AgentOnCorrelation(module)
        else:
            inputs, outputs, dynamic = AGENT_FEATURES_IO
    buf = io.BytesIO()
    # The TorchScript exporter is deprecated but yields plain opset-18 graphs with stable names.
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(module.eval(), example, buf, input_names=inputs, output_names=outputs,
                          dynamic_axes=dynamic or None, opset_version=OPSET, dynamo=False, do_constant_folding=True)
    if name == "point_encoder":
        return without_empty_guards(onnx.load_from_string(buf.getvalue())).SerializeToString()
    return buf.getvalue()


def without_empty_guards(model: onnx.ModelProto) -> onnx.ModelProto:
    """Wires in the else branch of every `If` on "is this tensor empty?" (`Equal(Size(t), 0)`)
    whose else branch only passes tensors through (`Identity`). The TorchScript exporter wraps
    `scatter_reduce` in two such guards (then: flatten an empty input); in `PointEncoder` the
    guarded tensor is the BEV grid, [B, C, cells^2], never empty, so the else branch is the one
    always taken. ONNX Runtime copies every tensor an `If` passes through (here the 5-10 MB index,
    feature and grid tensors: about 9 % of the encoder's time), and shape inference, hence
    `cmr.flops`, stops at an `If`. Raises ValueError for a guard it does not recognise."""
    graph = model.graph
    producer = {o: n for n in graph.node for o in n.output}

    def constant_zero(name: str) -> bool:
        n = producer.get(name)
        if n is None or n.op_type != "Constant":
            return False
        value = onnx.numpy_helper.to_array(n.attribute[0].t)
        return value.size == 1 and float(value) == 0.0

    rename, kept = {}, []
    for node in graph.node:
        cond = producer.get(node.input[0]) if node.op_type == "If" else None
        is_guard = (cond is not None and cond.op_type == "Equal" and constant_zero(cond.input[1])
                    and producer.get(cond.input[0]) is not None and producer[cond.input[0]].op_type == "Size")
        if not is_guard:
            kept.append(node)
            continue
        branch = next(a.g for a in node.attribute if a.name == "else_branch")
        if not all(n.op_type == "Identity" for n in branch.node):
            raise ValueError(f"{node.name}: an emptiness guard whose else branch computes something")
        passed = {n.output[0]: n.input[0] for n in branch.node}
        rename.update({out: passed[inner.name] for out, inner in zip(node.output, branch.output)})
    for node in kept:
        for i, name in enumerate(node.input):
            while name in rename:
                name = rename[name]
            node.input[i] = name
    for output in graph.output:
        if output.name in rename:
            raise ValueError(f"{output.name}: a graph output passes through an emptiness guard")
    del graph.node[:]
    graph.node.extend(kept)
    # The conditions (Equal, Size) are dead now; drop every node nothing reads.
    needed = {o.name for o in graph.output}
    live = []
    for node in reversed(list(graph.node)):
        if any(o in needed for o in node.output):
            live.append(node)
            needed.update(node.input)
    del graph.node[:]
    graph.node.extend(reversed(live))
    onnx.checker.check_model(model)
    return model


def action_frame_of(meta: dict) -> str:
    """The action frame a checkpoint was trained in (its config's `action_frame`; older
    checkpoints: camera_y)."""
    return g.check_frame(meta.get("config", {}).get("action_frame", g.CAMERA_Y))


def manifest(files: dict[str, tuple[str, str]], params: dict[str, int], provenance: dict, validation: dict,
             action_frame: str = g.CAMERA_Y, flops: dict[str, int] | None = None, correlation: bool = True,
             point_channels: int = 3) -> dict:
    """`point_channels`: the point encoder's input columns (3, or 4 with the intensity rank; the
    manifest's `points.channels` then names them, and older servers refuse the set)."""
    graphs = {}
    for name, (file, sha) in files.items():
        ins, outs = AGENT_FEATURES_SHAPES if name == "agent" and not correlation else CONTRACT_SHAPES[name]
        if name == "point_encoder":
            ins = {"points": [1, "N", point_channels]}
        graphs[name] = dict(file=file, sha256=sha, inputs=ins, outputs=outs)
        if flops and name in flops:
            graphs[name]["flops"] = flops[name]
    doc = {
        "format": MANIFEST_FORMAT,
        "image": dict(width=IMAGE_WIDTH, height=IMAGE_HEIGHT, nominal_scale=NOMINAL_SCALE,
                      focal_range_px=list(FOCAL_RANGE_PX), mean=list(IMAGE_MEAN), std=list(IMAGE_STD)),
        "features": dict(dim=FEATURE_DIM, stride=STRIDE, grid_height=GRID_HEIGHT, grid_width=GRID_WIDTH),
        "points": dict(num_points=NUM_POINTS, num_state_points=NUM_STATE_POINTS, state_xyz_scale_m=STATE_XYZ_SCALE_M),
        "actions": dict(dofs=list(g.DOFS), rotation_deg=[float(x) for x in g.ROTATION_STEPS_DEG],
                        translation_m=[float(x) for x in g.TRANSLATION_STEPS_M], frame=g.check_frame(action_frame)),
        "graphs": graphs,
        "provenance": provenance,
        "validation": validation,
        "parameters": params,
    }
    if correlation:
        doc["state_2d"] = dict(CORRELATION_STATE)
    if point_channels != 3:
        doc["points"]["channels"] = POINT_CHANNELS[point_channels]
    return doc


def export_models(models: dict[str, torch.nn.Module], out_dir: Path, provenance: dict, validation: dict | None = None,
                  action_frame: str = g.CAMERA_Y, correlation: bool = True) -> dict:
    """Writes the four graphs and the manifest. `correlation=False` keeps the agent in the
    features form even when it could take the correlation (for tests of `to_correlation`)."""
    out_dir = Path(out_dir)
    correlation = correlation and "agent" in models and is_correlation_agent(models["agent"])
    files, flops = {}, {}
    for name, module in models.items():
        data = onnx_bytes(name, module, correlation)
        atomic_write_bytes(out_dir / f"{name}.onnx", data)
        files[name] = (f"{name}.onnx", hashlib.sha256(data).hexdigest())
        sizes = {"N": NUM_POINTS, "B": 1}
        flops[name] = count_flops(onnx.load_from_string(data), sizes)[0]
    provenance = dict(provenance)
    provenance.setdefault("git_commit", git_commit())
    provenance.setdefault("created", _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))
    doc = manifest(files, parameter_counts(models), provenance, validation or {}, action_frame, flops,
                   correlation=correlation,
                   point_channels=point_channels_of(models["point_encoder"]) if "point_encoder" in models else 3)
    atomic_write_bytes(out_dir / "manifest.json", (json.dumps(doc, indent=2) + "\n").encode())
    return doc


def to_correlation(model_dir: Path, seed: int = 0) -> dict:
    """Converts a features-form model set in place: cuts `agent.onnx` at the correlation volume
    (the input of its first Conv, the output of `Agent.correlate`'s final Concat), renames that
    input `correlation`, checks the cut graph on `Agent.correlate` of random states against the
    uncut graph (relative error < 1e-4 on a batch of 4), then rewrites the graph and the manifest
    (state_2d section, agent sha256, inputs and FLOPs). Raises ValueError when the set is already
    converted or its agent is not `models.Agent`."""
    import onnxruntime as ort

    model_dir = Path(model_dir)
    doc = json.loads((model_dir / "manifest.json").read_text())
    if doc.get("state_2d", {}).get("form", "features") != "features":
        raise ValueError(f"{model_dir}: the agent is already in the {doc['state_2d']['form']} form")
    spec = doc["graphs"]["agent"]
    full = onnx.load(str(model_dir / spec["file"]))
    inferred = onnx.shape_inference.infer_shapes(full)
    convs = [n for n in inferred.graph.node if n.op_type == "Conv"]
    producers = {o: n for n in inferred.graph.node for o in n.output}
    if not convs or producers.get(convs[0].input[0]) is None or producers[convs[0].input[0]].op_type != "Concat":
        raise ValueError(f"{model_dir}: the agent graph is not models.Agent (no correlation volume before its CNN)")
    volume = convs[0].input[0]
    cut = onnx.utils.Extractor(inferred).extract_model([volume, "state_3d"], ["policy_logits", "value"])
    for node in cut.graph.node:
        node.input[:] = ["correlation" if i == volume else i for i in node.input]
    cut.graph.input[0].name = "correlation"
    cut.graph.input[0].type.tensor_type.shape.dim[0].dim_param = "B"
    channels = [d.dim_value for d in cut.graph.input[0].type.tensor_type.shape.dim[1:]]
    if channels != [CORRELATION_CHANNELS, GRID_HEIGHT, GRID_WIDTH]:
        raise ValueError(f"{model_dir}: the correlation volume is {channels}, expected {[CORRELATION_CHANNELS, GRID_HEIGHT, GRID_WIDTH]}")
    del cut.graph.value_info[:]
    onnx.checker.check_model(cut)
    data = cut.SerializeToString()

    # Same numbers: the uncut graph on random states vs the cut one on their correlation.
    state_2d, state_3d = example_inputs("agent", batch=4, seed=seed)
    with torch.no_grad():
        volume_in = Agent().correlate(state_2d)
    opts = ort.SessionOptions()
    want = ort.InferenceSession(full.SerializeToString(), opts, providers=["CPUExecutionProvider"]).run(
        None, {"state_2d": state_2d.numpy(), "state_3d": state_3d.numpy()})
    got = ort.InferenceSession(data, opts, providers=["CPUExecutionProvider"]).run(
        None, {"correlation": volume_in.numpy(), "state_3d": state_3d.numpy()})
    for w, g_ in zip(want, got):
        rel = float(np.abs(w - g_).max() / max(np.abs(w).max(), 1e-6))
        if not rel < 1e-4:
            raise ValueError(f"{model_dir}: the cut agent differs from the full one (relative error {rel:.2e})")

    atomic_write_bytes(model_dir / spec["file"], data)
    spec["sha256"] = hashlib.sha256(data).hexdigest()
    spec["inputs"] = CONTRACT_SHAPES["agent"][0]
    spec["flops"] = count_flops(cut, {"B": 1})[0]
    doc["state_2d"] = dict(CORRELATION_STATE)
    doc.setdefault("provenance", {})["converted"] = (
        "agent cut at the correlation volume by `python -m cmr.export --to-correlation` (same weights)")
    atomic_write_bytes(model_dir / "manifest.json", (json.dumps(doc, indent=2) + "\n").encode())
    return doc


def replace_graphs(model_dir: Path, models: dict[str, torch.nn.Module], source: str, seed: int = 0,
                   rtol: float = 1e-5) -> dict:
    """Replaces the named graphs of the model set in `model_dir` by `models` exported with today's
    code, when each answers as the graph it replaces: on the contract's example inputs (the agent:
    a batch of 4 random states, in the set's state form) the relative error of every output must
    stay below `rtol`, else ValueError and nothing is written. For changes to how a network
    computes, not what (e.g. `Agent.pooled_points`): the weights are the same, ONNX Runtime runs
    a different graph. Updates the manifest's sha256 and FLOPs of each graph and
    notes `source` in its provenance."""
    import onnxruntime as ort

    model_dir = Path(model_dir)
    doc = json.loads((model_dir / "manifest.json").read_text())
    correlation = doc.get("state_2d", {}).get("form") == "correlation"
    if "agent" in models and not correlation:
        raise ValueError(f"{model_dir}: not a correlation-form model set (convert it with --to-correlation first)")
    errors, new = {}, {}
    for name, module in models.items():
        spec = doc["graphs"][name]
        data = onnx_bytes(name, module.eval(), correlation)
        inputs = graph_inputs(name, module, correlation, batch=4, seed=seed)
        old_session = ort.InferenceSession(str(model_dir / spec["file"]), providers=["CPUExecutionProvider"])
        feeds = {i.name: t.numpy() for i, t in zip(old_session.get_inputs(), inputs)}
        old = old_session.run(None, feeds)
        got = ort.InferenceSession(data, providers=["CPUExecutionProvider"]).run(None, feeds)
        errors[name] = max(float(np.abs(w - g_).max() / max(np.abs(w).max(), 1e-6)) for w, g_ in zip(old, got))
        if not errors[name] < rtol:
            raise ValueError(f"{model_dir}: the new {name} graph differs from the one it replaces "
                             f"(relative error {errors[name]:.2e})")
        new[name] = data
    for name, data in new.items():
        spec = doc["graphs"][name]
        atomic_write_bytes(model_dir / spec["file"], data)
        spec["sha256"] = hashlib.sha256(data).hexdigest()
        spec["flops"] = count_flops(onnx.load_from_string(data), {"N": NUM_POINTS, "B": 1})[0]
        doc.setdefault("provenance", {})[f"{name}_graph"] = (
            f"re-exported from {source} by `python -m cmr.export --only` with the code of commit {git_commit()} "
            f"(same weights; relative error against the previous graph {errors[name]:.1e})")
    atomic_write_bytes(model_dir / "manifest.json", (json.dumps(doc, indent=2) + "\n").encode())
    return doc


def shipped_agent(state: dict) -> dict:
    """A checkpoint's agent as it ships: the moving average when the run kept one
    (`train.Run.shipped_models`), else `models.agent`."""
    return state["agent_ema"] if state.get("agent_ema") is not None else state["models"]["agent"]


def load_models(checkpoint: Path | None) -> tuple[dict[str, torch.nn.Module], dict]:
    models = build_all()
    meta: dict = {}
    if checkpoint is not None:
        state = torch.load(checkpoint, map_location="cpu", weights_only=False)
        # The encoders' normalisation and edge input are part of the architecture (older: v3's).
        models = build_all(**arch_of(state.get("meta", {}).get("config", {})))
        for name, module in models.items():
            if name in state["models"]:
                module.load_state_dict(shipped_agent(state) if name == "agent" else state["models"][name])
        meta = state.get("meta", {})
    for m in models.values():
        m.eval()
    return models, meta


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", type=Path, help="training checkpoint (.pt); random init when absent")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[2] / "models")
    ap.add_argument("--validation", type=Path, help="JSON file with validation figures to embed")
    ap.add_argument("--seed", type=int, default=0, help="init seed when no checkpoint is given")
    ap.add_argument("--to-correlation", type=Path, metavar="DIR",
                    help="convert the features-form model set in DIR to the correlation form, in place")
    ap.add_argument("--only", metavar="NAMES",
                    help="comma-separated graphs (e.g. agent,point_encoder): replace only these in the model set "
                         "in --out by the checkpoint's, each checked against the graph it replaces (same weights, "
                         "a faster graph)")
    args = ap.parse_args(argv)
    if args.only:
        if args.checkpoint is None:
            ap.error("--only needs --checkpoint")
        models, _ = load_models(args.checkpoint)
        names = args.only.split(",")
        if unknown := [n for n in names if n not in models]:
            ap.error(f"--only: unknown graphs {unknown}; the graphs are {list(models)}")
        doc = replace_graphs(args.out, {n: models[n] for n in names}, str(args.checkpoint))
        print(json.dumps({n: dict(doc["graphs"][n], provenance=doc["provenance"][f"{n}_graph"]) for n in names}, indent=2))
        return
    if args.to_correlation:
        doc = to_correlation(args.to_correlation)
        print(json.dumps({"state_2d": doc["state_2d"], "agent": doc["graphs"]["agent"]}, indent=2))
        return
    torch.manual_seed(args.seed)
    models, meta = load_models(args.checkpoint)
    if args.checkpoint is None:
        provenance = dict(data="none: random initialisation (untrained; for integration only)",
                          seeds=dict(init=args.seed))
    else:
        provenance = dict(data=meta.get("data", "unknown"), seeds=meta.get("seeds", {}),
                          checkpoint=str(args.checkpoint), training=meta.get("training", {}))
    validation = json.loads(args.validation.read_text()) if args.validation else {}
    doc = export_models(models, args.out, provenance, validation, action_frame_of(meta))
    print(json.dumps({k: doc[k] for k in ("parameters", "provenance")}, indent=2))


if __name__ == "__main__":
    main()
