"""The learned BEV detector network (torch): encoder to a BEV feature map, then heads.

Input: a LiDAR raster (N, C_in, H, W) on the detector's :class:`BevGrid`
(:mod:`roco_env.sensing.lidar`). The encoder (two stages, stride 2 then 4,
upsampled and merged back to stride 2; every stride-2 step is a 2x2 convolution so
feature values stay centred on their cells) returns non-negative features
(N, C, H/2, W/2): after a ReLU, so a zero-padded warp adds nothing and the
element-wise maximum is a sound fusion of maps from several agents. The heads
(CenterPoint-style, one 3x3 trunk then 1x1 convolutions) read a feature map,
the agent's own or a fused one, and return per feature cell:

* ``heatmap`` (1) logits of an object centre in the cell;
* ``offset`` (2) centre position inside the cell, in cells (x, y), in [0, 1];
* ``size`` (3) log of length, width, height in metres;
* ``yaw`` (2) sin and cos of the heading (up to the front/back ambiguity of a box);
* ``log_sigma`` (3) log standard deviation of the centre error (x, y, m) and the
  yaw error (rad): the model's own uncertainty.

With ``NetConfig.fusion == "gated"`` the network also holds a :class:`FusionGate`, the
learned part of intermediate fusion (:mod:`roco_env.fusion.intermediate`): a weight per
cell of each collaborator's warped map, so misplaced collaborator features can be
discounted before the maximum.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from roco_env.sensing.learned_params import FUSIONS
from roco_env.sensing.lidar import LIDAR_CHANNELS

__all__ = ["FUSIONS", "HEAD_CHANNELS", "BevDetectorNet", "FusionGate", "NetConfig"]

HEAD_CHANNELS = {"heatmap": 1, "offset": 2, "size": 3, "yaw": 2, "log_sigma": 3}

# Initial heatmap bias: sigmoid(-2.19) = 0.1, the focal-loss prior of CenterNet.
_HEATMAP_PRIOR = -2.19
# Initial gate logit: sigmoid(4) = 0.98, so an untrained gate fuses almost as the maximum.
_GATE_OPEN = 4.0


@dataclass(frozen=True)
class NetConfig:
    """Network shape: input channels and the widths (channels) of its stages.

    in_channels: raster channels; widths: (stage-1 width at stride 2, stage-2
    width at stride 4, feature width C of the output map at stride 2); fusion: how
    intermediate fusion combines maps (:data:`FUSIONS`; ``"gated"`` adds a
    :class:`FusionGate`).
    """

    in_channels: int = len(LIDAR_CHANNELS)
    widths: tuple[int, int, int] = (32, 64, 48)
    fusion: str = "max"

    def to_dict(self) -> dict:
        return {"in_channels": self.in_channels, "widths": list(self.widths),
                "fusion": self.fusion}

    @classmethod
    def from_dict(cls, data: dict) -> NetConfig:
        """The config of :meth:`to_dict` (files written before the fusion gate: ``"max"``)."""
        return cls(int(data["in_channels"]), tuple(int(w) for w in data["widths"]),
                   str(data.get("fusion", "max")))

    def __post_init__(self) -> None:
        if not (isinstance(self.in_channels, int) and self.in_channels >= 1):
            raise ValueError(f"NetConfig.in_channels must be an int >= 1; got {self.in_channels}")
        if len(self.widths) != 3 or not all(isinstance(w, int) and w >= 1 for w in self.widths):
            raise ValueError(f"NetConfig.widths must be 3 ints >= 1; got {self.widths}")
        if self.fusion not in FUSIONS:
            raise ValueError(f"NetConfig.fusion must be one of {FUSIONS}; got {self.fusion!r}")

    @property
    def stride(self) -> int:
        """Feature map cells per raster cell along each axis (fixed by the architecture)."""
        return 2


def _conv(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    """3x3 convolution, or with stride 2 a 2x2 one: each output cell then sees exactly the
    input cells it covers, so feature values sit at feature-cell centres (what warping and
    mirroring assume)."""
    kernel, pad = (3, 1) if stride == 1 else (2, 0)
    return nn.Sequential(nn.Conv2d(c_in, c_out, kernel, stride, pad, bias=False),
                         nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


class FusionGate(nn.Module):
    """A weight in (0, 1) per feature cell of a collaborator's map warped into the ego frame,
    from that map and the ego's own map at the cell (two 1x1 convolutions on
    [own, theirs, |own - theirs|]). Fusion keeps ``max(own, weight * theirs)``: a weight of 1
    is max fusion (where an untrained gate starts), a low one drops collaborator features
    that disagree with the ego's, such as a car a pose error has moved."""

    def __init__(self, channels: int, hidden: int = 16) -> None:
        super().__init__()
        self.body = nn.Sequential(nn.Conv2d(3 * channels, hidden, 1), nn.ReLU(inplace=True),
                                  nn.Conv2d(hidden, 1, 1))
        with torch.no_grad():
            self.body[2].weight.mul_(0.1)
            self.body[2].bias.fill_(_GATE_OPEN)

    def forward(self, own: torch.Tensor, theirs: torch.Tensor) -> torch.Tensor:
        """Weights (N, 1, H, W) of maps ``theirs`` (N, C, H, W) beside ``own`` (N, C, H, W).

        The 1x1 convolutions run as matrix products over the cells, the first split by its
        three inputs and accumulated (no concatenation): on channels-last maps the cells
        are views, and this is faster than the convolutions (docs/performance.md). (Fusion
        at run time on the CPU evaluates the same gate cell by cell in its compiled pass, from
        :meth:`cell_weights`.)"""
        first, last = self.body[0], self.body[2]
        n, c, h, w = own.shape
        weight = first.weight.flatten(1)  # (hidden, 3C)
        mine = own.permute(0, 2, 3, 1).reshape(-1, c)  # (cells, C)
        yours = theirs.permute(0, 2, 3, 1).reshape(-1, c)
        hidden = torch.addmm(first.bias, mine, weight[:, :c].t())
        hidden = torch.addmm(hidden, yours, weight[:, c:2 * c].t())
        hidden = torch.addmm(hidden, (mine - yours).abs(), weight[:, 2 * c:].t()).relu_()
        logit = torch.addmm(last.bias, hidden, last.weight.flatten(1).t())
        return logit.sigmoid_().reshape(n, h, w, 1).permute(0, 3, 1, 2)

    def cell_weights(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """The gate as per-cell arrays (float32, for the compiled fusion pass): w_in
        (3 C, hidden) (rows: own, theirs, |own - theirs| channels), b_in (hidden,),
        w_out (hidden,) and b_out; the weight is sigmoid(b_out + w_out . relu(b_in + x @ w_in))."""
        first, last = self.body[0], self.body[2]

        def as_array(tensor: torch.Tensor) -> np.ndarray:
            return np.ascontiguousarray(tensor.detach().cpu().numpy(), dtype=np.float32)

        return (as_array(first.weight.flatten(1).t()), as_array(first.bias),
                as_array(last.weight.flatten()), float(last.bias.detach()))


class BevDetectorNet(nn.Module):
    """Encoder + heads of the module docstring."""

    def __init__(self, config: NetConfig) -> None:
        super().__init__()
        self.config = config
        w1, w2, c = config.widths
        self.stage1 = nn.Sequential(_conv(config.in_channels, w1, 2), _conv(w1, w1))
        self.stage2 = nn.Sequential(_conv(w1, w2, 2), _conv(w2, w2), _conv(w2, w2))
        self.up = nn.Sequential(nn.ConvTranspose2d(w2, w1, 2, 2, bias=False),
                                nn.BatchNorm2d(w1), nn.ReLU(inplace=True))
        self.merge = nn.Sequential(nn.Conv2d(2 * w1, c, 1, bias=False), nn.BatchNorm2d(c),
                                   nn.ReLU(inplace=True))
        self.trunk = _conv(c, c)
        self.heads = nn.Conv2d(c, sum(HEAD_CHANNELS.values()), 1)
        with torch.no_grad():
            self.heads.bias.zero_()
            self.heads.bias[0] = _HEATMAP_PRIOR
        self.gate = FusionGate(c) if config.fusion == "gated" else None

    def encoder_modules(self) -> tuple[nn.Module, ...]:
        """The modules of :meth:`encode` (the rest, trunk and heads, is :meth:`decode`)."""
        return self.stage1, self.stage2, self.up, self.merge

    def detector_modules(self) -> tuple[nn.Module, ...]:
        """Every module but the fusion gate: the single-agent detector."""
        return (*self.encoder_modules(), self.trunk, self.heads)

    def encode(self, raster: torch.Tensor) -> torch.Tensor:
        """(N, C_in, H, W) -> non-negative features (N, C, H/2, W/2); H, W must be even."""
        if raster.dim() != 4 or raster.shape[1] != self.config.in_channels:
            raise ValueError(f"raster must have shape (N, {self.config.in_channels}, H, W); "
                             f"got {tuple(raster.shape)}")
        if raster.shape[-2] % 4 or raster.shape[-1] % 4:
            raise ValueError(f"raster H and W must be multiples of 4; got {tuple(raster.shape)}")
        s1 = self.stage1(raster)
        s2 = self.stage2(s1)
        return self.merge(torch.cat([s1, self.up(s2)], dim=1))

    def decode(self, features: torch.Tensor) -> dict[str, torch.Tensor]:
        """Head maps (N, k, h, w) by name (:data:`HEAD_CHANNELS`) of features (N, C, h, w)."""
        out = self.heads(self.trunk(features))
        maps = dict(zip(HEAD_CHANNELS, torch.split(out, list(HEAD_CHANNELS.values()), dim=1),
                        strict=True))
        maps["offset"] = torch.sigmoid(maps["offset"])
        maps["log_sigma"] = maps["log_sigma"].clamp(-6.0, 3.0)
        return maps

    def forward(self, raster: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.decode(self.encode(raster))

    def for_inference(self) -> BevDetectorNet:
        """This network in eval mode with every batch norm folded into the convolution before
        it (same outputs up to float rounding, a third less work per call); the original
        is left untouched, so it can still be trained or saved."""
        folded = copy.deepcopy(self).eval()
        for block in folded.modules():
            if (isinstance(block, nn.Sequential) and len(block) >= 2
                    and isinstance(block[0], nn.Conv2d | nn.ConvTranspose2d)
                    and isinstance(block[1], nn.BatchNorm2d)):
                block[0] = fuse_conv_bn_eval(block[0], block[1],
                                             transpose=isinstance(block[0], nn.ConvTranspose2d))
                block[1] = nn.Identity()
        return folded
