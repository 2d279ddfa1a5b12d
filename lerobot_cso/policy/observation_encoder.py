"""Observation and task encoders: they turn a batch into the prior's context tokens [task, observation]."""

from __future__ import annotations

import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.diffusion.modeling_diffusion import SpatialSoftmax
from torch import Tensor, nn
from torchvision.models import resnet18


def _module_key(feature_key: str) -> str:
    return feature_key.replace(".", "__")


class ImageEncoder(nn.Module):
    """ResNet-18 stem + layer1 + layer2 (random init, nothing downloaded) → spatial-softmax keypoints → Linear."""

    def __init__(self, image_shape: tuple[int, int, int], keypoints: int, embed_dim: int) -> None:
        super().__init__()
        net = resnet18(weights=None)
        self.backbone = nn.Sequential(net.conv1, net.bn1, net.relu, net.maxpool, net.layer1, net.layer2)
        with torch.no_grad():
            feature_shape = self.backbone(torch.zeros(1, *image_shape)).shape[1:]
        self.keypoints = SpatialSoftmax(tuple(feature_shape), num_kp=keypoints)
        self.proj = nn.Linear(2 * keypoints, embed_dim)

    def forward(self, image: Tensor) -> Tensor:
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
    ) -> None:
        super().__init__()
        self.image_keys = [k for k, ft in input_features.items() if ft.type is FeatureType.VISUAL]
        self.lowdim_keys = [k for k, ft in input_features.items() if ft.type is not FeatureType.VISUAL]
        self.images = nn.ModuleDict(
            {
                _module_key(k): ImageEncoder(tuple(input_features[k].shape), image_keypoints, image_embed_dim)
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
