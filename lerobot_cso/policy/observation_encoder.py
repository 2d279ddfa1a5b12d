"""Observation and task encoders: they turn a batch into the prior's context tokens [task, observation]."""

from __future__ import annotations

import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.diffusion.modeling_diffusion import SpatialSoftmax
from torch import Tensor, nn
from torch.nn import functional as F  # noqa: N812
from torchvision.models import resnet18

IMAGE_BACKBONES = ("resnet18", "conv")


def _module_key(feature_key: str) -> str:
    return feature_key.replace(".", "__")


def resnet18_stem() -> nn.Sequential:
    """QueST's backbone: ResNet-18 stem + layer1 + layer2 (random init, nothing downloaded), stride 8."""
    net = resnet18(weights=None)
    return nn.Sequential(net.conv1, net.bn1, net.relu, net.maxpool, net.layer1, net.layer2)


def small_conv(channels: int = 32) -> nn.Sequential:
    """A four-layer conv net, stride 4, GroupNorm (no batch statistics: training and rollouts compute the same
    function): ~1/40 of the ResNet stem's multiply-adds at the same resolution, for two CPU cores."""

    def block(c_in: int, c_out: int, stride: int) -> list[nn.Module]:
        return [nn.Conv2d(c_in, c_out, 3, stride, 1), nn.GroupNorm(8, c_out), nn.ReLU()]

    c = channels
    return nn.Sequential(*block(3, c, 2), *block(c, c, 1), *block(c, 2 * c, 2), *block(2 * c, 2 * c, 1))


def random_shift(images: Tensor, pad: int) -> Tensor:
    """QueST's (and DrQ's) random-shift augmentation: pad each image by ``pad`` pixels (edge values) and crop
    it back at a random offset, drawn per image."""
    n, _, h, w = images.shape
    padded = F.pad(images, (pad, pad, pad, pad), mode="replicate")
    dy, dx = torch.randint(0, 2 * pad + 1, (2, n)).tolist()
    return torch.stack([padded[i, :, y : y + h, x : x + w] for i, (y, x) in enumerate(zip(dy, dx, strict=True))])


def resize_images(images: Tensor, size: int) -> Tensor:
    """Images (N, C, H, W) resized to ``size``² (bilinear, antialiased: a 480² frame averages into each pixel of a
    64² one rather than skipping most of it); unchanged when already that size."""
    if images.shape[-2:] == (size, size):
        return images
    return F.interpolate(images, size=(size, size), mode="bilinear", antialias=True, align_corners=False)


class ImageEncoder(nn.Module):
    """A conv backbone (``resnet18`` or ``conv``) → spatial-softmax keypoints → Linear; images resized to
    ``resize``² first when set; random shifts of ``shift`` pixels while training."""

    def __init__(
        self,
        image_shape: tuple[int, int, int],
        keypoints: int,
        embed_dim: int,
        backbone: str = "resnet18",
        shift: int = 0,
        resize: int | None = None,
    ) -> None:
        super().__init__()
        if backbone not in IMAGE_BACKBONES:
            raise ValueError(f"image_backbone must be one of {', '.join(IMAGE_BACKBONES)}, got {backbone!r}")
        self.backbone = resnet18_stem() if backbone == "resnet18" else small_conv()
        self.shift = shift
        self.resize = resize
        if resize is not None:
            image_shape = (image_shape[0], resize, resize)
        with torch.no_grad():
            feature_shape = self.backbone(torch.zeros(1, *image_shape)).shape[1:]
        self.keypoints = SpatialSoftmax(tuple(feature_shape), num_kp=keypoints)
        self.proj = nn.Linear(2 * keypoints, embed_dim)

    def forward(self, image: Tensor) -> Tensor:
        if self.resize is not None:
            image = resize_images(image, self.resize)
        if self.training and self.shift > 0:
            image = random_shift(image, self.shift)
        return self.proj(self.keypoints(self.backbone(image)).flatten(1))


class ContextEncoder(nn.Module):
    """Batch → context (B, 2, dim): a learned task embedding and one fused observation token."""

    def __init__(
        self,
        input_features: dict[str, PolicyFeature],
        n_tasks: int,
        dim: int,
        image_keypoints: int,
        image_embed_dim: int,
        state_embed_dim: int,
        image_backbone: str = "resnet18",
        image_shift: int = 0,
        image_resize: int | None = None,
    ) -> None:
        super().__init__()
        self.image_keys = [k for k, ft in input_features.items() if ft.type is FeatureType.VISUAL]
        self.lowdim_keys = [k for k, ft in input_features.items() if ft.type is not FeatureType.VISUAL]
        self.images = nn.ModuleDict(
            {
                _module_key(k): ImageEncoder(
                    tuple(input_features[k].shape),
                    image_keypoints,
                    image_embed_dim,
                    image_backbone,
                    image_shift,
                    image_resize,
                )
                for k in self.image_keys
            }
        )
        self.lowdim = nn.ModuleDict(
            {_module_key(k): nn.Linear(input_features[k].shape[-1], state_embed_dim) for k in self.lowdim_keys}
        )
        fused = len(self.image_keys) * image_embed_dim + len(self.lowdim_keys) * state_embed_dim
        self.obs_proj = nn.Linear(fused, dim)
        self.task_embedding = nn.Embedding(max(1, n_tasks), dim)

    def forward(self, batch: dict[str, Tensor], task_ids: Tensor) -> Tensor:
        parts = [self.images[_module_key(k)](batch[k]) for k in self.image_keys]
        parts += [self.lowdim[_module_key(k)](batch[k].float()) for k in self.lowdim_keys]
        obs = self.obs_proj(torch.cat(parts, dim=-1))
        return torch.stack([self.task_embedding(task_ids), obs], dim=1)
