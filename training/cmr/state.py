"""The agent's hybrid state, built exactly as the server builds it (common brief, model contract).

state_2d = concat(image_features, F_k): F_k is the scatter-MEAN of the point features of every
point that projects into the 512 x 160 crop under the current pose, into stride-4 cell
(row, col) = (floor((v + 0.5) / 4), floor((u + 0.5) / 4)); empty cells are 0.
state_3d = for the first M sampled points: xyz in the current camera frame / 10 m,
sigmoid(frustum logit), 1/0 = in the current frustum.
"""

from __future__ import annotations

import torch

from .geometry import MIN_DEPTH_M
from .models import FEATURE_DIM, GRID_HEIGHT, GRID_WIDTH, IMAGE_HEIGHT, IMAGE_WIDTH, STRIDE

NUM_STATE_POINTS = 2048
STATE_XYZ_SCALE_M = 10.0


def to_camera(poses: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """poses [B, 4, 4] camera_from_map, points [B, N, 3] -> [B, N, 3]."""
    return points @ poses[:, :3, :3].transpose(1, 2) + poses[:, None, :3, 3]


def frustum_cells(k: torch.Tensor, p_cam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(cell index [B, N] with GRID_HEIGHT*GRID_WIDTH for points outside, in-frustum mask [B, N])."""
    fx, fy, cx, cy = (k[:, i:i + 1] for i in range(4))
    z = p_cam[..., 2]
    front = z >= MIN_DEPTH_M
    safe = torch.where(front, z, torch.ones_like(z))
    u = fx * p_cam[..., 0] / safe + cx
    v = fy * p_cam[..., 1] / safe + cy
    inside = front & (u >= -0.5) & (v >= -0.5) & (u < IMAGE_WIDTH - 0.5) & (v < IMAGE_HEIGHT - 0.5)
    row = torch.floor((v + 0.5) / STRIDE).clamp(0, GRID_HEIGHT - 1)
    col = torch.floor((u + 0.5) / STRIDE).clamp(0, GRID_WIDTH - 1)
    cell = torch.where(inside, (row * GRID_WIDTH + col).long(), torch.full_like(row, GRID_HEIGHT * GRID_WIDTH).long())
    return cell, inside


def build_state(poses, points, k, point_features, image_features, frustum_prob):
    """poses [B,4,4], points [B,N,3], k [B,4], point_features [B,N,64], image_features [B,64,40,128],
    frustum_prob [B,M] -> (state_2d [B,128,40,128], state_3d [B,M,5])."""
    b, n, _ = points.shape
    p_cam = to_camera(poses, points)
    cell, inside = frustum_cells(k, p_cam)
    cells = GRID_HEIGHT * GRID_WIDTH
    # Only in-frustum points contribute, so scatter just those (usually a small share of N).
    rows, cols = inside.nonzero(as_tuple=True)
    target = rows * cells + cell[rows, cols]
    feats = point_features[rows, cols].float()
    sums = feats.new_zeros(b * cells, FEATURE_DIM).index_add_(0, target, feats)
    counts = feats.new_zeros(b * cells).index_add_(0, target, torch.ones_like(target, dtype=feats.dtype))
    mean = (sums / counts[:, None].clamp(min=1.0)).view(b, cells, FEATURE_DIM)
    projected = mean.transpose(1, 2).reshape(b, FEATURE_DIM, GRID_HEIGHT, GRID_WIDTH)
    state_2d = torch.cat([image_features, projected], dim=1)
    m = frustum_prob.shape[1]
    state_3d = torch.cat([p_cam[:, :m] / STATE_XYZ_SCALE_M, frustum_prob[..., None], inside[:, :m, None].float()], dim=-1)
    return state_2d, state_3d


def alignment(poses, points, k, point_features, image_features) -> torch.Tensor:
    """How well each pose explains its image: the mean, over the points in view, of dot(point feature,
    image feature of the point's cell); -1 for rows with no point in view. The embeddings are trained
    to agree at true correspondences, so the multi-start search answers with the hypothesis scoring
    highest. Same in-view/cell decisions as `build_state`; twin of the server's `state::alignment`.
    poses [B,4,4], points [B,N,3], k [B,4], point_features [B,N,64], image_features [B,64,40,128] -> [B]."""
    b = points.shape[0]
    cell, inside = frustum_cells(k, to_camera(poses, points))
    rows, cols = inside.nonzero(as_tuple=True)
    cell_features = image_features.flatten(2).transpose(1, 2)  # [B, cells, 64]
    dots = (point_features[rows, cols].float() * cell_features[rows, cell[rows, cols]].float()).sum(-1)
    sums = dots.new_zeros(b).index_add_(0, rows, dots)
    counts = torch.bincount(rows, minlength=b).to(dots.dtype)
    return torch.where(counts > 0, sums / counts.clamp(min=1.0), torch.full_like(sums, -1.0))
