"""The SSZ discriminator: a conditional 3D PatchGAN (conventions section 8).

It sees class probabilities of a fruxel volume (the generator's softmax, or the one-hot ground truth) together
with the image, resampled to the grid's rows and columns and copied along depth, and judges overlapping patches
of the volume: do objects sit where the image puts them, with plausible shapes. The conditioning on the image is
Z-GAN's; the patch output is pix2pix's PatchGAN, in 3D.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class PatchDiscriminator3d(nn.Module):
    """Conditional 3D PatchGAN.

    Args:
        classes: C, channels of the probability volume.
        widths: channels of the stride-2 layers, e.g. ``(32, 64, 128)``: each halves the resolution, so a patch
            logit covers about ``2^len(widths) * 2`` cells per axis.
    """

    def __init__(self, classes: int, widths: tuple[int, ...]) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        cin = classes + 3
        for i, c in enumerate(widths):
            layers.append(nn.Conv3d(cin, c, 4, stride=2, padding=1, bias=i == 0))
            if i:
                # Instance statistics per sample: batch statistics would let real and fake batches leak into
                # each other's judgement (they are passed separately).
                layers.append(nn.InstanceNorm3d(c, affine=True))
            layers.append(nn.LeakyReLU(0.2, inplace=True))
            cin = c
        layers.append(nn.Conv3d(cin, 1, 3, padding=1))
        self.net = nn.Sequential(*layers)

    def forward(self, probs: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """Patch logits.

        Args:
            probs: ``(B, C, D, H, W)`` class probabilities (rows sum to 1), grid frame.
            image: ``(B, 3, h, w)`` RGB in [0, 1] of the grid's own camera, ``h / w = H / W``.

        Returns:
            ``(B, 1, D', H', W')`` logits, one per patch (positive = judged real).
        """
        _, _, d, h, w = probs.shape
        img = F.adaptive_avg_pool2d(image.to(probs.dtype), (h, w)) * 2.0 - 1.0
        img = img.unsqueeze(2).expand(-1, -1, d, -1, -1)
        return self.net(torch.cat([probs, img], dim=1))


def hinge_d_loss(real: torch.Tensor, fake: torch.Tensor) -> torch.Tensor:
    """Discriminator hinge loss: ``mean(relu(1 - real)) + mean(relu(1 + fake))`` over patches."""
    return F.relu(1.0 - real.float()).mean() + F.relu(1.0 + fake.float()).mean()


def hinge_g_loss(fake: torch.Tensor) -> torch.Tensor:
    """Generator's adversarial loss against a hinge discriminator: ``-mean(fake)``."""
    return -fake.float().mean()


