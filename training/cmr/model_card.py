"""Write `models/MODEL_CARD.md` from measured artefacts (nothing in it is typed by hand).

    python -m cmr.model_card --models ../models --eval eval.json --bench bench.json \
        --train-data ../data/synth-dev --curves training_curves.png [--run runs/x]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from .data import find_sequences, list_frames
from .export import atomic_write_bytes


def data_summary(roots: list[str]) -> list[dict]:
    """Per sequence: path, frames, and the generator's seed/style when a synth.json is present."""
    rows = []
    for root in roots:
        for seq in find_sequences(Path(root)):
            row = dict(sequence=str(seq), frames=len(list_frames([seq])))
            meta = seq / "synth.json"
            if meta.is_file():
                m = json.loads(meta.read_text())
                style = m.get("style", {})
                row.update(seed=m.get("seed"), index=m.get("sequence"), preset=style.get("preset"),
                           palette=style.get("palette"), time_of_day_h=style.get("time_of_day_h"),
                           clutter=style.get("clutter"))
            rows.append(row)
    return rows


def _table(rows: list[dict], keys: list[str], heads: list[str]) -> str:
    out = ["| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)]
    for r in rows:
        cells = []
        for k in keys:
            v = r.get(k)
            cells.append(f"{v:.3f}" if isinstance(v, float) else str(v))
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def _alignment(diagnosis: dict | None) -> str:
    if not diagnosis:
        return ""
    rows = [dict(perturbation=k, truth_wins=v, median_margin=diagnosis["median_margin"][k])
            for k, v in diagnosis["truth_wins"].items()]
    return f"""
Alignment signal of the 2D state (`python -m cmr.diagnose`, {diagnosis['frames']} held-out frames): how
often the true pose's mean point-to-image-cell cosine similarity beats the truth perturbed by a
yaw (degrees) or shift (metres, camera frame); 0.5 = no signal, 1.0 = always.

{_table(rows, ["perturbation", "truth_wins", "median_margin"], ["perturbation", "truth wins", "median margin"])}
"""


def _agent_tables(evaluation: dict, keys: list[str], heads: list[str]) -> str:
    h = evaluation.get("hypotheses", 1)
    if h <= 1:
        return f"Agent (argmax policy), after each iteration:\n\n{_table(evaluation['agent'], keys, heads)}"
    return f"""Agent (argmax policy), multi-start search with {h} starts, after each iteration. The starts are
the prior turned about the map pivot by {h} evenly spaced yaw offsets; the answer is the hypothesis
whose pose has the highest alignment score (mean point-to-image-cell feature similarity):

{_table(evaluation['agent'], keys, heads)}

Agent (argmax policy), single start (the paper's protocol: one trajectory from the prior):

{_table(evaluation['agent_single_start'], keys, heads)}"""


def compute_table(manifest: dict) -> str:
    """The graphs' FLOPs from the manifest (`graphs.*.flops`, counted by `cmr.flops`; N = 40,960
    points, batch 1) and, for a correlation-form agent (`state_2d`), the server's share of each
    policy row counted as if every cell were occupied (an upper bound)."""
    graphs = manifest["graphs"]
    if not all("flops" in g for g in graphs.values()):
        return "FLOPs: not recorded in this manifest."
    f = manifest["features"]
    spec = manifest.get("state_2d", {"form": "features"})
    rows = [f"| {name} ({'per policy row' if name == 'agent' else 'per request' if name != 'point_encoder' else 'per map'}) "
            f"| {graphs[name]['flops'] / 1e9:.3f} |" for name in graphs]
    note = f"Agent state form: `{spec['form']}`."
    if spec["form"] == "correlation":
        shifts = len(spec["row_shifts"]) + len(spec["column_shifts"])
        upper = 2 * shifts * f["dim"] * f["grid_height"] * f["grid_width"]
        rows.append(f"| correlation in the server (per policy row, at most) | {upper / 1e9:.3f} |")
        note += (" The server computes the parameter-free correlation on the occupied cells and the graph "
                 "starts after it (docs/architecture.md, model contract).")
    return "| graph | GFLOP |\n|---|---|\n" + "\n".join(rows) + "\n\n" + note


def render(manifest: dict, evaluation: dict, bench: dict, train_rows: list[dict], test_rows: list[dict],
           curves: str, notes: str, diagnosis: dict | None = None) -> str:
    params = manifest["parameters"]
    sizes = "\n".join(f"| {k} | {v:,} |" for k, v in params.items())
    it_keys = ["iteration", "rte_m", "rre_euler_deg", "rre_geodesic_deg", "rr", "rte_median_m"]
    it_heads = ["iteration", "RTE mean (m)", "RRE Euler-sum mean (deg)", "RRE geodesic mean (deg)", "RR", "RTE median (m)"]
    seq_keys = ["sequence", "frames", "seed", "index", "preset", "palette", "time_of_day_h", "clutter"]
    init = evaluation.get("initial", {})
    return f"""# Model card: cmr-agent default model

{notes}

## Graphs and size
Four ONNX graphs (opset 18, standard operators) described by `manifest.json` (format
`{manifest['format']}`). Parameters:

| graph | parameters |
|---|---|
{sizes}
| **total** | **{sum(params.values()):,}** |

Provenance: `{json.dumps(manifest['provenance'].get('training', {}))}`, git commit
`{manifest['provenance'].get('git_commit')}`, created {manifest['provenance'].get('created')}.

Compute:

{compute_table(manifest)}

## Data
Training sequences (KITTI-odometry layout written by `cmr-agent synth`):

{_table(train_rows, seq_keys, seq_keys)}

Held-out evaluation sequences:

{_table(test_rows, seq_keys, seq_keys)}

## Speed on this machine (ONNX Runtime {bench.get('onnxruntime', '')}, Python, 2 threads, median of repeats)
`python -m cmr.bench --models ../models` (N = 40,960 points, B = 1):

| stage | ms |
|---|---|
""" + "\n".join(f"| {k[:-3]} | {v} |" for k, v in bench.items() if k.endswith("_ms")) + f"""

Load average (1 min) on this shared machine during the measurement: {bench.get('load_average_1min', 'not recorded')}.

## Evaluation (paper protocol, held-out frames: {evaluation['frames']}, seed {evaluation['seed']})
Initial error (before any step): RTE {init.get('rte_m', float('nan')):.2f} m, RRE {init.get('rre_euler_deg', float('nan')):.1f} deg, RR {init.get('rr', float('nan')):.3f}.

{_agent_tables(evaluation, it_keys, it_heads)}

Greedy expert (uses the ground truth; the imitation teacher and the ceiling of pure imitation):

{_table(evaluation['expert'], it_keys, it_heads)}

What limits the agent (one-shot embeddings on the same frames):
- frustum head: precision {evaluation['frustum']['precision']:.3f}, recall {evaluation['frustum']['recall']:.3f}
- embedding match accuracy (best of the 40x128 image cells within one cell of the true projection):
  {evaluation['match_accuracy']:.3f}
{_alignment(diagnosis)}
## Training curves
![training curves]({curves})
"""


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", type=Path, required=True)
    ap.add_argument("--eval", type=Path, required=True)
    ap.add_argument("--bench", type=Path, required=True)
    ap.add_argument("--train-data", required=True, help="comma-separated roots")
    ap.add_argument("--test-data", default="", help="comma-separated roots")
    ap.add_argument("--curves", default="training_curves.png")
    ap.add_argument("--notes", type=Path, help="markdown paragraph(s) placed under the title")
    ap.add_argument("--diagnose", type=Path, help="output of `python -m cmr.diagnose` (JSON)")
    args = ap.parse_args(argv)
    manifest = json.loads((args.models / "manifest.json").read_text())
    text = render(manifest, json.loads(args.eval.read_text()), json.loads(args.bench.read_text()),
                  data_summary([r for r in args.train_data.split(",") if r]),
                  data_summary([r for r in args.test_data.split(",") if r]), args.curves,
                  args.notes.read_text() if args.notes else "",
                  json.loads(args.diagnose.read_text()) if args.diagnose else None)
    atomic_write_bytes(args.models / "MODEL_CARD.md", text.encode())


if __name__ == "__main__":
    main()
