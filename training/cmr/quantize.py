"""Static int8 quantisation of the Conv layers of a model set's image encoder and agent (ONNX QDQ:
per-channel int8 weights, uint8 activations with ranges calibrated on frames; every other layer
stays float, and so does the image encoder's first convolution, which reads the image).

    python -m cmr.quantize --models ../models --calibration ../data/synth-val ../data/v2/val-flat --out /tmp/models-int8

The calibration inputs are what the served search feeds the graphs: the frames' images, and the
agent's observations (correlation volume, 3D state) along greedy multi-start rollouts of the set's
own (float) models from the frames' perturbed priors. Activation ranges are fixed at calibration,
so a row's answer does not depend on the other rows of a batch (dynamic quantisation would scale
each batch by its own range). Each graph has its recipe (`RECIPES`): the agent's ranges are the
calibration's extremes (MinMax); the image encoder's cut the outer 0.1 % of each activation's
histogram (Percentile 99.9), and its first convolution stays float. On the EfficientNet-Lite0
encoder of run v11 this raised the int8 features' cosine to the float ones on 22 real frames from
0.984 to 0.9985 at the same speed. The frustum head (0.3 ms) and the point encoder stay float:
most of the encoder's time is its BEV scatter and gathers, and its head MatMuls in int8 saved 6 %
(measurements: `training/README.md`, "Quantised graphs").

Every CPU the same: ONNX Runtime fuses each QDQ Conv into an integer kernel. On x86 CPUs with VNNI
(AVX512-VNNI, AVX-VNNI) it sums the uint8 x int8 products in int32; on CPUs with AVX2 alone it adds
pairs of products in int16 first, which saturates for 8-bit weights (255 * 127 * 2 > 32,767), so
the same set answered differently by CPU: the shipped v11 set registered 20 fewer of 712 frozen
cases on an AVX2-only AMD EPYC than on the Xeon with VNNI it was judged on (real-dev protocol 44
against 50 of 80). Every recipe therefore keeps the weights within 7 bits (`reduce_range`,
|w| <= 64: a pair of products stays within int16), and the fused kernels then compute what the
graph says on every CPU (`tests/test_quantize.py`). The shipped set (since 2026-12-07) quantises
the agent only: the image encoder with 7-bit weights followed its float self less closely (cosine
0.987, 1st percentile 0.81, over 22 real frames) and gained no speed on AVX2
(training/README.md, "Quantised graphs").

Writes a complete model set in `--out` (the other graphs copied, the manifest's sha256 updated and
the quantisation noted in its provenance); it never writes into `--models`. Judge the result with
`cmr-agent eval --models OUT` on synthetic and real frames before shipping it. How close its image
features stay to the float set's, on frames of your choice (the figure quoted above):

    python -m cmr.quantize --models FLOAT --check OUT --data ~/.cache/cmr-agent/data/real-split/val ../../shared/real-dev --frames 22
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import onnx
import onnx.numpy_helper
import torch

from .bench import session
from .data import find_sequences, list_frames, make_sample
from .episodes import embed, multi_start
from .export import atomic_write_bytes, git_commit
from .import_onnx import import_models

QUANTIZED = ("image_encoder", "agent")
# What the shipped set quantises (the module doc, "Every CPU the same"): the agent.
DEFAULT_GRAPHS = ("agent",)

# How each graph is calibrated: ONNX Runtime's calibration method, its percentile where it takes
# one, and whether the first Conv layer stays float (measurements: module doc). Weights are int8
# within 7 bits (`reduce_range`) in every recipe: see the module doc, "Every CPU the same".
RECIPES = {
    "image_encoder": dict(method="Percentile", percentile=99.9, first_conv_float=True),
    "agent": dict(method="MinMax", percentile=None, first_conv_float=False),
}
# The int8 weights' range with `reduce_range`: |w| <= 64, so that a u8 activation times a weight,
# two such products summed, stays within int16 (255 * 64 * 2 = 32,640 < 32,767).
WEIGHT_LIMIT = 64


def recipe_text(name: str) -> str:
    r = RECIPES[name]
    calibration = f"Percentile {r['percentile']}" if r["method"] == "Percentile" else r["method"]
    return f"{calibration} calibration" + (", the first Conv layer kept float" if r["first_conv_float"] else "")


@torch.no_grad()
def calibration_inputs(models: dict, frames: list, hypotheses: int = 4, steps: int = 10, seed: int = 7,
                       max_rows: int = 512, chunk: int = 4) -> dict[str, list[dict[str, np.ndarray]]]:
    """Feeds for each quantised graph: {graph: [feed dict, ...]}. Images [1, 3, H, W] one per
    frame; agent observations in batches of up to 16 rows, at most `max_rows` in all (an even
    subsample of every step of every start)."""
    images, observations = [], []
    for start in range(0, len(frames), chunk):
        samples = [make_sample(f, np.random.default_rng([seed, start + j]), train=False)
                   for j, f in enumerate(frames[start:start + chunk])]
        images.extend(s.image[None] for s in samples)
        eps = embed(models, samples, torch.device("cpu"))
        _, trajectories = multi_start(models["agent"], eps, steps, hypotheses, keep_states=True)
        for traj in trajectories:
            for corr, s3 in traj.states:
                observations.extend(zip(corr.numpy(), s3.numpy()))
    pick = np.linspace(0, len(observations) - 1, min(max_rows, len(observations))).round().astype(int)
    rows = [observations[i] for i in pick]
    agent = [dict(correlation=np.stack([c for c, _ in rows[i:i + 16]]), state_3d=np.stack([s for _, s in rows[i:i + 16]]))
             for i in range(0, len(rows), 16)]
    return dict(image_encoder=[dict(image=im) for im in images], agent=agent)


class _Reader:
    """onnxruntime.quantization.CalibrationDataReader over a list of feeds."""

    def __init__(self, feeds: list[dict[str, np.ndarray]]):
        self._it = iter(feeds)

    def get_next(self):
        return next(self._it, None)


def in_source_order(quantized: onnx.ModelProto, source: onnx.ModelProto) -> onnx.ModelProto:
    """`quantized` with its nodes in `source`'s order, each QuantizeLinear / DequantizeLinear
    placed just before the first node that reads it. The quantiser sorts the graph its own way;
    `import_onnx` matches weights by the order nodes first read them, so a quantised set keeps the
    order of the graph it came from. Raises ValueError unless every node finds its place."""
    nodes = {n.name: n for n in quantized.graph.node}
    producer = {o: n for n in quantized.graph.node for o in n.output}
    placed: list = []
    done: set[str] = set()

    def place(node) -> None:
        for name in node.input:
            feeder = producer.get(name)
            if feeder is not None and feeder.op_type in ("QuantizeLinear", "DequantizeLinear") and feeder.name not in done:
                place(feeder)
        done.add(node.name)
        placed.append(node)

    for node in source.graph.node:
        place(nodes[node.name])
    if len(placed) != len(quantized.graph.node):
        raise ValueError("the quantised graph has nodes the float graph does not explain")
    out = onnx.ModelProto()
    out.CopyFrom(quantized)
    del out.graph.node[:]
    out.graph.node.extend(placed)
    return out


def first_conv(model: onnx.ModelProto) -> list[str]:
    """The name of the graph's first Conv node (node order is topological: the image encoder's
    stem, the only layer that reads pixels), as a list; empty without one."""
    return [n.name for n in model.graph.node if n.op_type == "Conv"][:1]


def quantize_graph(src: Path, dst: Path, feeds: list[dict[str, np.ndarray]], recipe: dict) -> None:
    """Writes `src` quantised to `dst` by `recipe` (a `RECIPES` entry): Conv layers only (inputs
    and outputs through QDQ pairs, uint8 activations with int8 weights within 7 bits: ONNX
    Runtime's fast x86 kernels, exact on every CPU; see the module doc)."""
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    source = onnx.load(str(src))
    extra = {"CalibPercentile": recipe["percentile"]} if recipe["method"] == "Percentile" else {}
    quantize_static(str(src), str(dst), _Reader(feeds), quant_format=QuantFormat.QDQ,
                    activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True,
                    calibrate_method=getattr(CalibrationMethod, recipe["method"]), op_types_to_quantize=["Conv"],
                    reduce_range=True,
                    nodes_to_exclude=first_conv(source) if recipe["first_conv_float"] else [], extra_options=extra)
    onnx.save(in_source_order(onnx.load(str(dst)), source), str(dst))


def int8_weight_range(model: onnx.ModelProto) -> tuple[int, int]:
    """(lowest, highest) value of the int8 initialisers that DequantizeLinear nodes read (the
    quantised weights); (0, 0) for a float graph."""
    inits = {i.name: i for i in model.graph.initializer}
    lo = hi = 0
    for node in model.graph.node:
        if node.op_type == "DequantizeLinear" and node.input[0] in inits:
            w = onnx.numpy_helper.to_array(inits[node.input[0]])
            if w.dtype == np.int8 and w.size:
                lo, hi = min(lo, int(w.min())), max(hi, int(w.max()))
    return lo, hi


def is_quantized(model: onnx.ModelProto) -> bool:
    return any(n.op_type in ("QuantizeLinear", "DequantizeLinear", "QLinearConv") for n in model.graph.node)


def check_float_set(model_dir: Path, graphs: tuple[str, ...]) -> dict:
    """The set's manifest; ValueError when one of `graphs` is quantised already."""
    doc = json.loads((Path(model_dir) / "manifest.json").read_text())
    for name in graphs:
        if is_quantized(onnx.load(str(Path(model_dir) / doc["graphs"][name]["file"]))):
            raise ValueError(f"{model_dir}: {name} is quantised already; start from the float set "
                             "(training/README.md, \"Quantised graphs\")")
    return doc


def quantize_set(model_dir: Path, out_dir: Path, frames: list, graphs: tuple[str, ...] = DEFAULT_GRAPHS,
                 **calibration) -> dict:
    """Quantises `graphs` of the float set in `model_dir` into a complete set in `out_dir`
    (`calibration`: keyword arguments of `calibration_inputs`). Everything is computed before the
    first file is written. ValueError when `out_dir` is `model_dir` or a graph is quantised already."""
    model_dir, out_dir = Path(model_dir), Path(out_dir)
    if out_dir.resolve() == model_dir.resolve():
        raise ValueError("--out must differ from --models: the quantised set is judged before it replaces one")
    doc = check_float_set(model_dir, graphs)
    models, _ = import_models(model_dir)
    feeds = calibration_inputs(models, frames, **calibration)
    files = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, spec in doc["graphs"].items():
            src = model_dir / spec["file"]
            if name in graphs:
                quantize_graph(src, Path(tmp) / spec["file"], feeds[name], RECIPES[name])
                src = Path(tmp) / spec["file"]
            files[spec["file"]] = src.read_bytes()
            spec["sha256"] = hashlib.sha256(files[spec["file"]]).hexdigest()
    doc.setdefault("provenance", {})["quantized"] = dict(
        # "within 7 bits" is what the server reads (`Manifest::int8_saturation_warning`): without it, a
        # quantised set warns on CPUs without VNNI.
        graphs=list(graphs), format="QDQ: Conv layers with uint8 activations and per-channel int8 weights "
                                    "within 7 bits (reduce_range: no int16 saturation on CPUs without VNNI)",
        recipes={name: recipe_text(name) for name in graphs},
        calibration=dict(frames=len(frames), images=len(feeds["image_encoder"]),
                         agent_rows=int(sum(len(f["state_3d"]) for f in feeds["agent"]))),
        float_sha256={name: hashlib.sha256((model_dir / doc["graphs"][name]["file"]).read_bytes()).hexdigest()
                      for name in graphs},
        code_commit=git_commit())
    out_dir.mkdir(parents=True, exist_ok=True)
    for file, data in files.items():
        atomic_write_bytes(out_dir / file, data)
    for extra in ("MODEL_CARD.md", "training_curves.png"):
        if (model_dir / extra).exists():
            shutil.copyfile(model_dir / extra, out_dir / extra)
    atomic_write_bytes(out_dir / "manifest.json", (json.dumps(doc, indent=2) + "\n").encode())
    return doc


def feature_agreement(float_dir: Path, quantized_dir: Path, frames: list) -> dict:
    """How closely `quantized_dir`'s image encoder reproduces `float_dir`'s on `frames`: per feature
    cell (64 channels; [1, 64, 40, 128] per frame) the cosine of the two feature vectors, pooled over
    every cell of every frame. Returns {frames, cells, mean, p01 (1st percentile), min}; both sets
    must share the image contract (ValueError otherwise). ONNX Runtime on the CPU, one thread."""
    if not frames:
        raise ValueError("no frames to check")
    docs = [json.loads((Path(d) / "manifest.json").read_text()) for d in (float_dir, quantized_dir)]
    if docs[0]["image"] != docs[1]["image"]:
        raise ValueError(f"{float_dir} and {quantized_dir} differ in their image contract")
    sessions = [session(Path(d) / doc["graphs"]["image_encoder"]["file"], threads=1)
                for d, doc in zip((float_dir, quantized_dir), docs)]
    cosines = []
    for i, frame in enumerate(frames):
        image = make_sample(frame, np.random.default_rng([0, i]), train=False).image[None].astype(np.float32)
        a, b = (s.run(None, {s.get_inputs()[0].name: image})[0][0] for s in sessions)  # [C, H, W]
        dot = (a * b).sum(0)
        cosines.append((dot / np.maximum(np.linalg.norm(a, axis=0) * np.linalg.norm(b, axis=0), 1e-12)).ravel())
    c = np.concatenate(cosines)
    return dict(frames=len(frames), cells=int(c.size), mean=float(c.mean()), p01=float(np.percentile(c, 1)),
                min=float(c.min()))


def _frames(roots: list[Path], count: int) -> list:
    """`count` frames spread evenly over the KITTI-layout `roots` (ValueError when there are none)."""
    frames = [f for root in roots for f in list_frames(find_sequences(root))]
    if not frames:
        raise ValueError(f"no frames under {' '.join(map(str, roots))}")
    pick = np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int)
    return [frames[i] for i in pick]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", type=Path, required=True, help="float model set (manifest.json + graphs)")
    ap.add_argument("--calibration", type=Path, nargs="+",
                    help="KITTI-layout roots of synthetic frames (not the frames you evaluate on)")
    ap.add_argument("--out", type=Path, help="folder for the quantised model set")
    ap.add_argument("--frames", type=int, default=24, help="frames, spread evenly over the roots")
    ap.add_argument("--max-rows", type=int, default=512, help="agent observations kept for calibration")
    ap.add_argument("--graphs", default=",".join(DEFAULT_GRAPHS),
                    help=f"comma-separated graphs to quantise, among {','.join(QUANTIZED)}")
    ap.add_argument("--check", type=Path, metavar="QUANTIZED",
                    help="quantise nothing: print how closely QUANTIZED's image features follow --models' on --data")
    ap.add_argument("--data", type=Path, nargs="+", help="with --check: KITTI-layout roots of the frames")
    args = ap.parse_args(argv)
    try:
        if args.check:
            if not args.data:
                raise SystemExit("cmr.quantize: --check needs --data")
            print(json.dumps(feature_agreement(args.models, args.check, _frames(args.data, args.frames)), indent=2))
            return
        if not (args.calibration and args.out):
            raise SystemExit("cmr.quantize: --calibration and --out are required (or --check)")
        graphs = tuple(args.graphs.split(","))
        if not set(graphs) <= set(QUANTIZED):
            raise SystemExit(f"--graphs: choose among {','.join(QUANTIZED)}")
        check_float_set(args.models, graphs)
        doc = quantize_set(args.models, args.out, _frames(args.calibration, args.frames), graphs, max_rows=args.max_rows)
    except (ValueError, OSError) as e:  # DataError is a ValueError
        raise SystemExit(f"cmr.quantize: {e}") from None
    print(json.dumps(doc["provenance"]["quantized"], indent=2))


if __name__ == "__main__":
    main()
