"""A checkpoint whose agent lies on the line between two agents of the same encoders: weight-space
interpolation of a fine-tuned policy with the one it started from (Wortsman et al., "Robust
fine-tuning of zero-shot models", CVPR 2022: the interpolation keeps much of the start's
robustness and of the fine-tune's gain).

    python -m cmr.interpolate --start runs/v11-shipped.pt --tuned runs/v21/snap/agent_00500.pt \
        --alpha 0.5 --out runs/v23/wise_v21_050.pt

The result is `--tuned` with its shipped agent (`agent_ema` when present, else `models.agent`)
replaced by (1 - alpha) * start + alpha * tuned, parameter by parameter (alpha 0 = the start's
agent, 1 = the tuned one). Both checkpoints must hold the same encoders and frustum head (the
agent reads their embeddings): ValueError otherwise, and on any shape or key mismatch.
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import torch

from .export import shipped_agent
from .files import atomic_write_bytes

ENCODERS = ("point_encoder", "image_encoder", "frustum_head")


def interpolate(start: dict, tuned: dict, alpha: float) -> dict:
    """`tuned` with its shipped agent moved to (1 - alpha) * start's + alpha * tuned's."""
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha {alpha} is outside [0, 1]")
    for name in ENCODERS:
        a, b = start["models"][name], tuned["models"][name]
        if a.keys() != b.keys() or any(not torch.equal(a[k], b[k]) for k in a):
            raise ValueError(f"the checkpoints' {name} differ: an agent reads its own encoders' embeddings")
    a, b = shipped_agent(start), shipped_agent(tuned)
    if a.keys() != b.keys() or any(a[k].shape != b[k].shape for k in a):
        raise ValueError("the agents' parameters differ in names or shapes")
    mixed = {k: torch.lerp(a[k].float(), b[k].float(), alpha).to(b[k].dtype) if b[k].is_floating_point() else b[k].clone() for k in b}
    out = dict(tuned)
    out["models"] = dict(tuned["models"], agent=mixed)
    if tuned.get("agent_ema") is not None:
        out["agent_ema"] = mixed
    out["opt_agent"] = None  # not a training state: the mixture was never optimised
    out["meta"] = dict(tuned.get("meta", {}), interpolated=dict(start=start.get("meta", {}).get("training"), alpha=alpha))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--start", required=True, type=Path, help="checkpoint the fine-tune started from")
    ap.add_argument("--tuned", required=True, type=Path, help="the fine-tuned checkpoint")
    ap.add_argument("--alpha", required=True, type=float, help="0 = the start's agent, 1 = the tuned one")
    ap.add_argument("--out", required=True, type=Path)
    args = ap.parse_args()
    load = lambda p: torch.load(p, map_location="cpu", weights_only=False)  # noqa: E731
    state = interpolate(load(args.start), load(args.tuned), args.alpha)
    buffer = io.BytesIO()
    torch.save(state, buffer)
    atomic_write_bytes(args.out, buffer.getvalue())
    print(f"wrote {args.out}: agent = {1 - args.alpha:g} x {args.start} + {args.alpha:g} x {args.tuned}")


if __name__ == "__main__":
    main()
