"""A 1×1 convolution as one matrix product over the map's positions, the same bits in any batch.

Every position of every image is a row of ``C_in`` channels and ``out = rows · Wᵀ + b``: a per-pixel linear layer,
with the weights and ``state_dict`` of ``nn.Conv2d(C_in, C_out, 1)``. The course backbone's projection and the
aggregators' 1×1 layers (NetVLAD's soft assignment, SALAD's two MLPs) use it.

Why not ``nn.Conv2d``'s own path everywhere: without oneDNN (the pinned kernels of :mod:`vpr_nb.kernels`) torch
runs a stride-1 convolution of >= 16 images through NNPACK, whose channel sums depend on the batch size and on the
processor's level-1 cache, or else unfolds each image and multiplies it on its own (ten times slower on the
course's maps). As rows, the product is one BLAS call whose result for an image does not depend on the batch it
came in, and its output is an NCHW tensor in channels-last memory (``[B, H, W, C]`` underneath), the layout in
which the aggregators' reductions over channels are fast. Where oneDNN is on (the processor's own kernels) torch's
convolution is faster and is used unchanged.
"""
from __future__ import annotations

import torch
from torch import nn


class PointwiseConv2d(nn.Conv2d):
    """``nn.Conv2d(in_channels, out_channels, 1)`` computed as ``rows · Wᵀ + b`` when oneDNN is off (module
    docstring); any other kernel size, stride or grouping falls back to ``nn.Conv2d``."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size=1, **kwargs) -> None:
        super().__init__(in_channels, out_channels, kernel_size, **kwargs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pointwise = (self.kernel_size == (1, 1) and self.stride == (1, 1) and self.groups == 1
                     and self.padding in ((0, 0), "valid") and self.dilation == (1, 1))
        if not pointwise or x.dim() != 4 or x.device.type != "cpu" or torch.backends.mkldnn.enabled:
            return super().forward(x)
        b, c, h, w = x.shape
        rows = x.permute(0, 2, 3, 1).reshape(b * h * w, c)         # a view for channels-last input
        weight = self.weight.view(self.out_channels, c).t()
        out = rows @ weight if self.bias is None else torch.addmm(self.bias, rows, weight)
        return out.view(b, h, w, self.out_channels).permute(0, 3, 1, 2)
