"""Training curves from `<run>/log.jsonl` to a PNG.

    python -m cmr.plots runs/default --out ../models/training_curves.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def plot(run_dir: Path, out: Path) -> None:
    records = [json.loads(line) for line in (Path(run_dir) / "log.jsonl").read_text().splitlines() if line.strip()]
    embed = [r for r in records if r["stage"] == "embed"]
    agent = [r for r in records if r["stage"] == "agent"]
    val = [r for r in records if r["stage"] == "val"]
    fig, axes = plt.subplots(2, 2, figsize=(11, 7))
    ax = axes[0, 0]
    for key in ("circle", "bce"):
        ax.plot([r["step"] for r in embed], [r[key] for r in embed], label=key)
    ax.set_title("embeddings: losses"), ax.set_xlabel("step"), ax.legend()
    ax = axes[0, 1]
    for key in ("precision", "recall"):
        ax.plot([r["step"] for r in embed], [r[key] for r in embed], label=f"frustum {key}")
    ax.set_title("frustum head (training batch)"), ax.set_xlabel("step"), ax.set_ylim(0, 1), ax.legend()
    ax = axes[1, 0]
    for key in ("bc", "value", "bc_accuracy", "reward"):
        ax.plot([r["step"] for r in agent], [r[key] for r in agent], label=key)
    ax.set_title("agent: BC loss / accuracy, value loss, mean reward"), ax.set_xlabel("iteration"), ax.legend()
    ax = axes[1, 1]
    # A run may change its validation set size on resume; each size is its own series.
    for frames in sorted({r.get("frames") for r in val}, key=lambda n: n or 0):
        part = [r for r in val if r.get("frames") == frames]
        steps = [r["step"] for r in part]
        tag = f" ({frames} frames)" if frames else ""
        ax.plot(steps, [r["final"]["rr"] for r in part], "o-", label=f"RR (agent, 10 it.){tag}")
        ax.plot(steps, [min(r["final"]["rte_m"], 20) / 20 for r in part], "s-", label=f"RTE / 20 m{tag}")
        ax.plot(steps, [r["match_accuracy"] for r in part], "^-", label=f"match accuracy{tag}")
    if val:
        ax.legend(fontsize=7)
    ax.set_title("validation (held-out frames)"), ax.set_xlabel("agent iteration"), ax.set_ylim(0, 1.05)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("run", type=Path)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    plot(args.run, args.out or args.run / "curves.png")


if __name__ == "__main__":
    main()
