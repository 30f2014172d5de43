"""Losses for the one-shot embeddings: circle loss over 2D-3D correspondences and weighted BCE."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def circle_loss_one_side(dist: torch.Tensor, positive: torch.Tensor, scale: float, pos_margin: float,
                         neg_margin: float) -> torch.Tensor:
    """Circle loss with each row of `dist` [n, n] as an anchor. Weights are the (detached) distances
    to the optimum, so pairs already beyond their margin stop contributing."""
    pos_w = (dist - pos_margin).clamp(min=0).detach()
    neg_w = (neg_margin - dist).clamp(min=0).detach()
    very_negative = -1e4
    pos_term = torch.where(positive, scale * pos_w * (dist - pos_margin), torch.full_like(dist, very_negative))
    neg_term = torch.where(~positive, scale * neg_w * (neg_margin - dist), torch.full_like(dist, very_negative))
    valid = positive.any(dim=1) & (~positive).any(dim=1)
    if not valid.any():
        return dist.sum() * 0.0
    per_anchor = F.softplus(torch.logsumexp(pos_term, dim=1) + torch.logsumexp(neg_term, dim=1)) / scale
    return per_anchor[valid].mean()


def circle_loss(point_feats: torch.Tensor, pixel_feats: torch.Tensor, pixel_uv: torch.Tensor, radius_px: float,
                scale: float = 10.0, pos_margin: float = 0.1, neg_margin: float = 1.4) -> torch.Tensor:
    """point_feats, pixel_feats [n, f] (row i = point i and the image feature where it projects),
    pixel_uv [n, 2] in feature-map units. Positives: pixels within `radius_px`; both directions."""
    dist = torch.cdist(point_feats, pixel_feats)
    positive = torch.cdist(pixel_uv, pixel_uv) <= radius_px
    return (circle_loss_one_side(dist, positive, scale, pos_margin, neg_margin)
            + circle_loss_one_side(dist.t(), positive.t(), scale, pos_margin, neg_margin))


def weighted_bce(logits: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """BCE with positives weighted by #neg/#pos, so the small in-frustum class counts as much."""
    labels = labels.float()
    pos = labels.sum().clamp(min=1.0)
    neg = (1 - labels).sum().clamp(min=1.0)
    return F.binary_cross_entropy_with_logits(logits, labels, pos_weight=neg / pos)
