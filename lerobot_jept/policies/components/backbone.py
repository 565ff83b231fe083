"""The spatial backbone: the frozen (or trained) model that turns frames into a token sequence.

The paper uses a pretrained, frozen ``vit_base_patch16_224`` from timm; any timm model name works the same way.
Section 4.4's visual priors replace its output with a pre-trained model's:

- DINOv2 and SAM: timm models (``vit_small_patch14_dinov2.lvd142m``, ``vit_base_patch14_dinov2.lvd142m``,
  ``samvit_base_patch16.sa1b``, ...), one frame in, tokens out;
- ``videomae_small`` / ``videomae_base``: Hugging Face's VideoMAE (``transformers``, the ``[priors]`` extra) on
  a two-frame tubelet, the previous frame and the current one;
- ``raft_small`` / ``raft_large``: torchvision's RAFT optical flow from the previous frame to the current one,
  cut into 8 x 8 patches (one token of 2 x 8 x 8 flow values per patch). FlowFormer, the paper's flow model, is
  not packaged; RAFT is the optical-flow prior that is.

The two temporal priors pair every frame with the one before it in its video (a prompt's frames, a training
window, the control context); the first frame of a sequence is paired with itself (no motion).

``weights_path`` loads pretrained weights from a local file (timm through its own pretrained loading,
``pretrained_cfg_overlay``; RAFT and VideoMAE as a state dict), for machines without Hub access.
"""

from pathlib import Path

import torch
import torch.nn.functional as F  # noqa: N812
from einops import rearrange
from torch import Tensor, nn

IMAGENET = ((0.485, 0.456, 0.406), (0.229, 0.224, 0.225))
VIDEOMAE_SIZES = {  # hidden, layers, heads, mlp: VideoMAE's ViT-S and ViT-B
    "videomae_small": (384, 12, 6, 1536),
    "videomae_base": (768, 12, 12, 3072),
}
VIDEOMAE_HUB = {
    "videomae_small": "MCG-NJU/videomae-small-finetuned-kinetics",
    "videomae_base": "MCG-NJU/videomae-base",
}
RAFT_MODELS = ("raft_small", "raft_large")
FLOW_PATCH = 8
RAFT_MIN_SIZE = 128  # RAFT's correlation pyramid needs 16 x 16 feature maps


class BackboneWeightsUnavailableError(RuntimeError):
    """Pretrained backbone weights were requested but could not be loaded."""


def is_temporal(name: str) -> bool:
    """Whether a frame's tokens come from the frame and the one before it (optical flow, video models)."""
    return name in RAFT_MODELS or name in VIDEOMAE_SIZES


def expected_weights(name: str) -> str:
    """Where a backbone's pretrained weights come from, as a user would download them."""
    if name in RAFT_MODELS:
        from torchvision.models import optical_flow

        url = getattr(
            optical_flow, "Raft_Small_Weights" if name == "raft_small" else "Raft_Large_Weights"
        ).DEFAULT.url
        return f"{url.rsplit('/', 1)[-1]} (torchvision, {url})"
    if name in VIDEOMAE_SIZES:
        return f"model.safetensors of https://huggingface.co/{VIDEOMAE_HUB[name]} (VideoMAEModel weights)"
    import timm

    cfg = timm.models.get_pretrained_cfg(name)
    if cfg is not None and cfg.hf_hub_id:
        return f"model.safetensors of https://huggingface.co/{cfg.hf_hub_id} (timm weights of {name})"
    return f"the timm weights of {name}" + (f" ({cfg.url})" if cfg is not None and cfg.url else "")


def weights_error(name: str, weights_path: str | None, reason: str) -> BackboneWeightsUnavailableError:
    where = f"backbone_weights_path {weights_path}" if weights_path else "The pretrained weights"
    return BackboneWeightsUnavailableError(
        f"{where} {reason} for vision_backbone={name}: expected {expected_weights(name)}. Pass that file with "
        "--policy.backbone_weights_path=PATH, or train from scratch with --policy.pretrained_backbone=false."
    )


def load_state_dict_file(model: nn.Module, name: str, weights_path: str) -> None:
    """A state dict from a .safetensors or .pth file into ``model``, strictly; a wrapper's prefix (``videomae.``,
    ``module.``) is dropped."""
    path = Path(weights_path)
    if not path.is_file():
        raise weights_error(name, weights_path, "does not exist")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(path))
        else:
            state = torch.load(str(path), map_location="cpu", weights_only=True)
        state = state.get("state_dict", state) if isinstance(state, dict) else state
        state = {k.removeprefix("module.").removeprefix("videomae."): v for k, v in state.items()}
        model.load_state_dict(state, strict=True)
    except Exception as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise weights_error(name, weights_path, f"does not fit ({first[:160]})") from err


def create_backbone_model(name: str, pretrained: bool, image_size: int, weights_path: str | None = None):
    import timm

    kwargs = {"pretrained": pretrained, "num_classes": 0}
    if "vit" in name or "deit" in name:
        kwargs["img_size"] = image_size
    if pretrained and weights_path:
        if not Path(weights_path).is_file():
            raise weights_error(name, weights_path, "does not exist")
        kwargs["pretrained_cfg_overlay"] = {"file": str(weights_path)}
    try:
        return timm.create_model(name, **kwargs)
    except (OSError, RuntimeError, ValueError) as err:
        if not pretrained:
            raise
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        reason = f"does not fit ({first[:160]})" if weights_path else f"could not be loaded ({first[:160]})"
        raise weights_error(name, weights_path, reason) from err


def create_raft(name: str, pretrained: bool, weights_path: str | None) -> nn.Module:
    from torchvision.models import optical_flow

    build = getattr(optical_flow, name)
    if not pretrained:
        return build(weights=None)
    if weights_path:
        model = build(weights=None)
        load_state_dict_file(model, name, weights_path)
        return model
    try:
        return build(weights="DEFAULT")
    except Exception as err:  # no network: urllib's errors
        raise weights_error(name, None, f"could not be downloaded ({type(err).__name__})") from err


def create_videomae(name: str, pretrained: bool, image_size: int, weights_path: str | None) -> nn.Module:
    try:
        from transformers import VideoMAEConfig, VideoMAEModel
    except ImportError as err:
        raise ImportError(
            f"vision_backbone={name} needs Hugging Face transformers: pip install 'lerobot_policy_jept[priors]'."
        ) from err
    hidden, layers, heads, mlp = VIDEOMAE_SIZES[name]
    config = VideoMAEConfig(
        image_size=image_size,
        num_frames=2,
        tubelet_size=2,
        hidden_size=hidden,
        num_hidden_layers=layers,
        num_attention_heads=heads,
        intermediate_size=mlp,
        use_mean_pooling=False,
    )
    model = VideoMAEModel(config)
    if pretrained:
        if not weights_path:
            raise weights_error(name, None, "are not downloaded at run time")
        load_state_dict_file(model, name, weights_path)
    return model


class SpatialBackbone(nn.Module):
    """(B, 3, H, W) images in [0, 1] -> (B, N, C) tokens; frozen (eval mode, no grad) when ``freeze``.

    A temporal prior (:func:`is_temporal`) also takes ``previous`` (B, 3, H, W), the frame before each image."""

    def __init__(
        self, name: str, pretrained: bool, freeze: bool, image_size: int, weights_path: str | None = None
    ):
        super().__init__()
        self.name, self.temporal = name, is_temporal(name)
        if name in RAFT_MODELS:
            if image_size % FLOW_PATCH:
                raise ValueError(
                    f"vision_backbone={name} needs an image_size divisible by 8, got {image_size}."
                )
            self.model = create_raft(name, pretrained, weights_path)
            mean, std = (0.5, 0.5, 0.5), (0.5, 0.5, 0.5)  # RAFT's [-1, 1] input
        elif name in VIDEOMAE_SIZES:
            self.model = create_videomae(name, pretrained, image_size, weights_path)
            mean, std = IMAGENET
        else:
            self.model = create_backbone_model(name, pretrained, image_size, weights_path)
            cfg = self.model.pretrained_cfg
            mean, std = cfg.get("mean", (0.5, 0.5, 0.5)), cfg.get("std", (0.5, 0.5, 0.5))
        self.freeze = freeze
        self.register_buffer("mean", torch.tensor(mean).view(1, 3, 1, 1), False)
        self.register_buffer("std", torch.tensor(std).view(1, 3, 1, 1), False)
        if freeze:
            self.model.requires_grad_(False)
        with torch.no_grad():
            self.model.eval()
            probe = self.tokens(torch.zeros(1, 3, image_size, image_size))
        self.num_tokens, self.dim = probe.shape[1], probe.shape[2]
        # plain list, not submodules: found once instead of walking the model on every pass
        self._batch_norms = [
            m for m in self.model.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)
        ]

    @property
    def uses_batch_statistics(self) -> bool:
        """Whether a frame's tokens depend on the other frames of its pass (batch norm in training mode), so
        that splitting a pass into chunks would change them."""
        return any(m.training for m in self._batch_norms)

    def train(self, mode: bool = True):
        super().train(mode)
        if self.freeze:
            self.model.eval()  # a frozen backbone keeps its normalisation statistics and no dropout
        return self

    def tokens(self, images: Tensor, previous: Tensor | None = None) -> Tensor:
        x = (images - self.mean) / self.std
        if self.temporal:
            before = x if previous is None else (previous - self.mean) / self.std
            if self.name in RAFT_MODELS:
                return self.flow_tokens(before, x)
            return self.model(pixel_values=torch.stack([before, x], 1)).last_hidden_state
        features = self.model.forward_features(x)
        if features.ndim == 4:  # CNN feature map
            features = rearrange(features, "b c h w -> b (h w) c")
        return features

    def flow_tokens(self, before: Tensor, after: Tensor) -> Tensor:
        """RAFT's flow (in pixels of the model's resolution), computed at 128 px at least (RAFT's correlation
        pyramid needs it), as 8 x 8 patches (B, (H/8)(W/8), 2 x 8 x 8)."""
        size = after.shape[-1]
        if size < RAFT_MIN_SIZE:
            before, after = (F.interpolate(x, size=RAFT_MIN_SIZE, mode="bilinear") for x in (before, after))
        flow = self.model(before, after)[-1]
        if size < RAFT_MIN_SIZE:
            flow = F.interpolate(flow, size=size, mode="area") * (size / RAFT_MIN_SIZE)
        return rearrange(flow, "b c (h p) (w q) -> b (h w) (c p q)", p=FLOW_PATCH, q=FLOW_PATCH)

    def forward(self, images: Tensor, previous: Tensor | None = None) -> Tensor:
        if self.freeze:
            with torch.no_grad():
                return self.tokens(images, previous)
        return self.tokens(images, previous)
