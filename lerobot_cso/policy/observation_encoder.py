"""Observation and task encoders: they turn a batch into the prior's context tokens [task, observation]."""

from __future__ import annotations

import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.diffusion.modeling_diffusion import SpatialSoftmax
from torch import Tensor, nn
from torch.nn import functional as F  # noqa: N812
from torchvision.models import resnet18

IMAGE_BACKBONES = ("resnet18", "conv")
IMAGE_FITS = ("crop", "pad")


def auto_backbone(device: str) -> str:
    """What ``image_backbone: auto`` becomes on ``device``: QueST's ResNet-18 stem on an accelerator, the conv net
    on a CPU, where a training step with the stem at 128² costs 1.7× one with the conv net (docs/own-data.md)."""
    return "conv" if torch.device(device).type == "cpu" else "resnet18"


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


def fit_geometry(height: int, width: int, size: int, fit: str) -> tuple[tuple[int, int], tuple[int, int]]:
    """Where a ``height``×``width`` frame goes when fitted to ``size`` (:func:`fit_images`): the (h, w) it is
    scaled to, then the (h, w) the encoder reads."""
    scale = min(1.0, size / (min(height, width) if fit == "crop" else max(height, width)))
    scaled = (max(1, round(height * scale)), max(1, round(width * scale)))
    if fit == "crop":
        return scaled, (min(size, scaled[0]), min(size, scaled[1]))
    return scaled, (size, size) if scale < 1 else scaled


def fit_images(images: Tensor, size: int, fit: str = "crop") -> Tensor:
    """Images (N, C, H, W) fitted to ``size`` keeping their aspect, never enlarged. ``crop``: scaled (bilinear,
    antialiased: a 480² frame averages into each pixel of a 128² one rather than skipping most of it) until the
    shorter side is at most ``size``, then the centre ``size``² (or less, for a side already shorter) kept. ``pad``:
    scaled until the longer side is ``size``, then centred on a zero border (the dataset's mean colour once
    normalised) up to ``size``². A frame that already fits is returned as it is."""
    height, width = images.shape[-2:]
    (h, w), (out_h, out_w) = fit_geometry(height, width, size, fit)
    if (h, w) == (out_h, out_w) == (height, width):
        return images
    if (h, w) != (height, width):
        images = F.interpolate(images, size=(h, w), mode="bilinear", antialias=True, align_corners=False)
    if fit == "pad":
        top, left = (out_h - h) // 2, (out_w - w) // 2
        return F.pad(images, (left, out_w - w - left, top, out_h - h - top))
    top, left = (h - out_h) // 2, (w - out_w) // 2
    return images[..., top : top + out_h, left : left + out_w]


class ImageEncoder(nn.Module):
    """A conv backbone (``resnet18`` or ``conv``) → spatial-softmax keypoints → Linear; images fitted to
    ``resize`` by ``fit`` first when set (:func:`fit_images`); random shifts of ``shift`` pixels while training."""

    def __init__(
        self,
        image_shape: tuple[int, int, int],
        keypoints: int,
        embed_dim: int,
        backbone: str = "resnet18",
        shift: int = 0,
        resize: int | None = None,
        fit: str = "crop",
    ) -> None:
        super().__init__()
        if backbone not in IMAGE_BACKBONES:
            raise ValueError(f"image_backbone must be one of {', '.join(IMAGE_BACKBONES)}, got {backbone!r}")
        self.backbone = resnet18_stem() if backbone == "resnet18" else small_conv()
        self.shift = shift
        self.resize, self.fit = resize, fit
        channels, height, width = image_shape
        if resize is not None:
            height, width = fit_geometry(height, width, resize, fit)[1]
        with torch.no_grad():
            feature_shape = self.backbone(torch.zeros(1, channels, height, width)).shape[1:]
        self.keypoints = SpatialSoftmax(tuple(feature_shape), num_kp=keypoints)
        self.proj = nn.Linear(2 * keypoints, embed_dim)

    def forward(self, image: Tensor) -> Tensor:
        if self.resize is not None:
            image = fit_images(image, self.resize, self.fit)
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
        image_fit: str = "crop",
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
                    image_fit,
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

    def encode_images(self, batch: dict[str, Tensor]) -> list[Tensor]:
        """Each camera's embedding (B, image_embed_dim), in ``image_keys`` order."""
        return [self.images[_module_key(k)](batch[k]) for k in self.image_keys]

    def forward(self, batch: dict[str, Tensor], task_ids: Tensor) -> Tensor:
        parts = self.encode_images(batch)
        parts += [self.lowdim[_module_key(k)](batch[k].float()) for k in self.lowdim_keys]
        obs = self.obs_proj(torch.cat(parts, dim=-1))
        return torch.stack([self.task_embedding(task_ids), obs], dim=1)
