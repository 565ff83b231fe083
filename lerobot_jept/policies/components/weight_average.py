"""An exponential moving average of a network's trained weights, kept beside them (not in the paper).

Training updates the network's own weights; evaluation runs on their average. :class:`WeightAverage` holds the
average of every trained parameter as buffers, so it is saved in the same ``model.safetensors`` and a resumed run
continues both exactly. Switching the policy to eval mode exchanges the network's weights with the average, back
to train mode exchanges them again. A checkpoint always holds the trained weights under their own names and the
average under ``weight_average.*``, whichever mode saved it (:meth:`WeightAverage.trained_weights`), so loading it
without the average gives the trained weights.
"""

from contextlib import contextmanager

import torch
from torch import nn


def buffer_name(parameter: str) -> str:
    return parameter.replace(".", "__")


class WeightAverage(nn.Module):
    """EMA of ``module``'s parameters that require a gradient, with decay ``min(decay, (1 + n) / (10 + n))``
    at optimizer step ``n`` (counted from 0; the usual warm-up: early steps follow the weights closely)."""

    def __init__(self, module: nn.Module, decay: float):
        super().__init__()
        self.decay = decay
        trained = [(name, p) for name, p in module.named_parameters() if p.requires_grad]
        self.names = [name for name, _ in trained]
        for name, p in trained:
            self.register_buffer(buffer_name(name), p.detach().clone())
        # The average is in the network (eval mode): a plain flag, so reading it costs no device sync per step.
        self.swapped = False

    def pairs(self, module: nn.Module) -> list[tuple[torch.Tensor, torch.Tensor]]:
        params = dict(module.named_parameters())
        return [(params[name], getattr(self, buffer_name(name))) for name in self.names]

    @torch.no_grad()
    def update(self, module: nn.Module, step: int) -> None:
        """After optimizer step ``step`` (in train mode): move the average towards ``module``'s weights."""
        if self.swapped:
            raise RuntimeError("The weight average is in the network (eval mode): call policy.train() first.")
        decay = min(self.decay, (1 + step) / (10 + step))
        pairs = self.pairs(module)  # one fused lerp over all tensors, as timm's ModelEmaV3
        torch._foreach_lerp_([a for _, a in pairs], [p.detach() for p, _ in pairs], 1.0 - decay)

    @torch.no_grad()
    def use(self, module: nn.Module, averaged: bool) -> None:
        """Put the average (``averaged``) or the trained weights into ``module``; exact both ways."""
        if self.swapped == averaged:
            return
        for p, average in self.pairs(module):
            trained = p.detach().clone()
            p.copy_(average)
            average.copy_(trained)
        self.swapped = averaged

    @contextmanager
    def trained_weights(self, module: nn.Module):
        """The trained weights in ``module`` for the block (to save them), then the mode's weights again."""
        averaged = self.swapped
        self.use(module, averaged=False)
        try:
            yield
        finally:
            self.use(module, averaged=averaged)
