"""A checkpoint on the line between a fine-tuned network and the one it started from: weight-space
interpolation (Wortsman et al., "Robust fine-tuning of zero-shot models", CVPR 2022: the mixture
keeps much of the start's robustness and of the fine-tune's gain), of the agent or of the encoders.

    python -m cmr.interpolate --start runs/v11-shipped.pt --tuned runs/v21/snap/agent_00500.pt \
        --alpha 0.5 --out runs/v23/wise_v21_050.pt
    python -m cmr.interpolate --part encoders --start runs/v11-shipped.pt \
        --tuned runs/v30/snap/embed_004000.pt --alpha 0.5 --out runs/v31/wise_0.5.pt

The result is `--tuned` with one part replaced by (1 - alpha) * start + alpha * tuned, parameter by
parameter (alpha 0 = the start's, 1 = the tuned one's; integer buffers such as BatchNorm's batch
counts are the tuned one's):
- `agent` (default): the shipped agent (`agent_ema` when present, else `models.agent`). Both
  checkpoints must hold the same encoders and frustum head, since the agent reads their embeddings.
- `encoders`: the point encoder, the image encoder (BatchNorm statistics included) and the frustum
  head. Both checkpoints must ship the same agent, which reads the mixed embeddings.
ValueError on a differing fixed part, an alpha outside [0, 1], or any key or shape mismatch.
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import torch

from .export import shipped_agent
from .files import atomic_write_bytes

ENCODERS = ("point_encoder", "image_encoder", "frustum_head")


def lerp_state(a: dict, b: dict, alpha: float) -> dict:
    """(1 - alpha) * a + alpha * b for every floating tensor of two state dicts; b's other tensors."""
    if a.keys() != b.keys() or any(a[k].shape != b[k].shape for k in a):
        raise ValueError("the parameters differ in names or shapes")
    return {k: torch.lerp(a[k].float(), b[k].float(), alpha).to(b[k].dtype) if b[k].is_floating_point() else b[k].clone() for k in b}


def same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def interpolate(start: dict, tuned: dict, alpha: float, part: str = "agent") -> dict:
    """`tuned` with its agent (`part="agent"`) or its encoders (`part="encoders"`) moved to
    (1 - alpha) * start's + alpha * tuned's; the inputs are left as they were."""
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha {alpha} is outside [0, 1]")
    out = dict(tuned)
    if part == "agent":
        for name in ENCODERS:
            if not same(start["models"][name], tuned["models"][name]):
                raise ValueError(f"the checkpoints' {name} differ: an agent reads its own encoders' embeddings")
        mixed = lerp_state(shipped_agent(start), shipped_agent(tuned), alpha)
        out["models"] = dict(tuned["models"], agent=mixed)
        if tuned.get("agent_ema") is not None:
            out["agent_ema"] = mixed
        out["opt_agent"] = None  # not a training state: the mixture was never optimised
    elif part == "encoders":
        if not same(shipped_agent(start), shipped_agent(tuned)):
            raise ValueError("the checkpoints' agents differ: mixed encoders need the agent both were read by")
        out["models"] = dict(tuned["models"], **{n: lerp_state(start["models"][n], tuned["models"][n], alpha) for n in ENCODERS})
        out["opt_embed"] = None
    else:
        raise ValueError(f"part {part!r} is neither 'agent' nor 'encoders'")
    out["meta"] = dict(tuned.get("meta", {}), interpolated=dict(start=start.get("meta", {}).get("training"), alpha=alpha, part=part))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--start", required=True, type=Path, help="checkpoint the fine-tune started from")
    ap.add_argument("--tuned", required=True, type=Path, help="the fine-tuned checkpoint")
    ap.add_argument("--alpha", required=True, type=float, help="0 = the start's, 1 = the tuned one's")
    ap.add_argument("--part", choices=("agent", "encoders"), default="agent", help="what is mixed; the rest is the tuned one's")
    ap.add_argument("--out", required=True, type=Path)
    args = ap.parse_args()
    load = lambda p: torch.load(p, map_location="cpu", weights_only=False)  # noqa: E731
    state = interpolate(load(args.start), load(args.tuned), args.alpha, args.part)
    buffer = io.BytesIO()
    torch.save(state, buffer)
    atomic_write_bytes(args.out, buffer.getvalue())
    print(f"wrote {args.out}: {args.part} = {1 - args.alpha:g} x {args.start} + {args.alpha:g} x {args.tuned}")


if __name__ == "__main__":
    main()
