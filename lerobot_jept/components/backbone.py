"""The spatial backbone: a timm model created by name, producing one token sequence per image.

The paper uses a pretrained, frozen ``vit_base_patch16_224``; swapping in another timm model (the paper's visual
prior injection, Section 4.4) is a change of ``name``. ``weights_path`` loads pretrained weights from a local
file through timm's own pretrained loading (``pretrained_cfg_overlay``), for machines without Hub access.
"""

from pathlib import Path

import torch
from einops import rearrange
from torch import Tensor, nn


class BackboneWeightsUnavailableError(RuntimeError):
    """Pretrained backbone weights were requested but could not be loaded."""


def create_backbone_model(name: str, pretrained: bool, image_size: int, weights_path: str | None = None):
    import timm

    kwargs = {"pretrained": pretrained, "num_classes": 0}
    if "vit" in name or "deit" in name:
        kwargs["img_size"] = image_size
    if pretrained and weights_path:
        if not Path(weights_path).is_file():
            raise BackboneWeightsUnavailableError(f"backbone_weights_path {weights_path} does not exist.")
        kwargs["pretrained_cfg_overlay"] = {"file": str(weights_path)}
    try:
        return timm.create_model(name, **kwargs)
    except (OSError, RuntimeError, ValueError) as err:
        if not pretrained or isinstance(err, BackboneWeightsUnavailableError):
            raise
        raise BackboneWeightsUnavailableError(
            f"Could not load pretrained weights for timm model {name!r} ({type(err).__name__}: {err}). "
            "Without Hub access, pass a local weights file with --policy.backbone_weights_path=PATH "
            "(a timm checkpoint, .safetensors or .pth), or train from scratch with "
            "--policy.pretrained_backbone=false."
        ) from err


class SpatialBackbone(nn.Module):
    """(B, 3, H, W) images in [0, 1] -> (B, N, C) tokens; frozen (eval mode, no grad) when ``freeze``."""

    def __init__(
        self, name: str, pretrained: bool, freeze: bool, image_size: int, weights_path: str | None = None
    ):
        super().__init__()
        self.model = create_backbone_model(name, pretrained, image_size, weights_path)
        self.freeze = freeze
        cfg = self.model.pretrained_cfg
        self.register_buffer("mean", torch.tensor(cfg.get("mean", (0.5, 0.5, 0.5))).view(1, 3, 1, 1), False)
        self.register_buffer("std", torch.tensor(cfg.get("std", (0.5, 0.5, 0.5))).view(1, 3, 1, 1), False)
        if freeze:
            self.model.requires_grad_(False)
        with torch.no_grad():
            self.model.eval()
            probe = self.tokens(torch.zeros(1, 3, image_size, image_size))
        self.num_tokens, self.dim = probe.shape[1], probe.shape[2]

    def train(self, mode: bool = True):
        super().train(mode)
        if self.freeze:
            self.model.eval()  # a frozen backbone keeps its normalisation statistics and no dropout
        return self

    def tokens(self, images: Tensor) -> Tensor:
        features = self.model.forward_features((images - self.mean) / self.std)
        if features.ndim == 4:  # CNN feature map
            features = rearrange(features, "b c h w -> b (h w) c")
        return features

    def forward(self, images: Tensor) -> Tensor:
        if self.freeze:
            with torch.no_grad():
                return self.tokens(images)
        return self.tokens(images)
