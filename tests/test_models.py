"""Tests for vpr_nb.models: SmallCNN, VGG16Backbone, DINOv2Backbone/load_dinov2, VPRModel, build_model."""
from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from vpr_nb.models import (BACKBONE_NAMES, DINOv2Backbone, SmallCNN, VGG16Backbone, VPRModel, build_model,
                           load_dinov2)


pytestmark = pytest.mark.usefixtures("one_thread")   # tests/conftest.py


def _images(b: int = 2, h: int = 32, w: int = 48, seed: int = 0) -> torch.Tensor:
    return torch.randn(b, 3, h, w, generator=torch.Generator().manual_seed(seed))


BAD_IMAGES = [
    (torch.zeros(3, 32, 48), "dimensions"),
    (torch.zeros(2, 1, 32, 48), "channels"),
    (torch.zeros(2, 3, 32, 48, dtype=torch.uint8), "floating"),
    (torch.full((2, 3, 32, 48), float("nan")), "NaN"),
    (torch.zeros(0, 3, 32, 48), "empty"),
    (torch.zeros(2, 3, 2, 2), "at least"),
    ([[0.0]], "torch.Tensor"),
]


# ------------------------------------------------------------------------------------------ SmallCNN


def test_small_cnn_shapes_and_attributes():
    torch.manual_seed(0)
    net = SmallCNN()
    fmap = net(_images())
    assert (net.out_channels, net.stride) == (128, 4)
    assert fmap.shape == (2, 128, 8, 12)  # 32×48 / 4 = 8×12 = 96 positions
    assert (fmap >= 0).all()  # post-ReLU, as GeM assumes
    assert sum(isinstance(m, nn.Conv2d) for m in net.modules()) == 4


def test_small_cnn_custom_sizes():
    torch.manual_seed(0)
    net = SmallCNN(in_channels=1, width=12, out_channels=20)
    fmap, token = net.forward_with_token(torch.randn(3, 1, 36, 52))
    assert fmap.shape == (3, 20, 9, 13) and token.shape == (3, 20)
    # GroupNorm uses gcd(8, C) groups: 4 groups for 12 and 24 channels
    assert [m.num_groups for m in net.modules() if isinstance(m, nn.GroupNorm)] == [4, 4, 8]


def test_small_cnn_token_is_linear_of_spatial_mean():
    torch.manual_seed(0)
    net = SmallCNN(width=8, out_channels=16)
    x = _images(3)
    fmap, token = net.forward_with_token(x)
    torch.testing.assert_close(fmap, net(x))
    mean = fmap.sum(dim=(2, 3)) / (fmap.shape[2] * fmap.shape[3])
    torch.testing.assert_close(token, mean @ net.token.weight.T + net.token.bias)


def test_small_cnn_images_are_normalised_independently():
    # GroupNorm: an image's features do not depend on the rest of its batch, in train mode too
    torch.manual_seed(0)
    net = SmallCNN(width=8, out_channels=16).train()
    x = _images(4)
    torch.testing.assert_close(net(x)[:1], net(x[:1]))
    torch.testing.assert_close(net(x), net.eval()(x))


def test_small_cnn_all_parameters_get_gradients():
    torch.manual_seed(0)
    net = SmallCNN(width=8, out_channels=16)
    fmap, token = net.forward_with_token(_images())
    (fmap.sum() + token.sum()).backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())


@pytest.mark.parametrize("x, match", BAD_IMAGES)
def test_small_cnn_rejects_bad_images(x, match):
    with pytest.raises(ValueError, match=match):
        SmallCNN(width=8, out_channels=16)(x)


@pytest.mark.parametrize("kwargs", [{"width": 0}, {"out_channels": 2.5}, {"in_channels": True}, {"norm_groups": -1}])
def test_small_cnn_rejects_bad_arguments(kwargs):
    with pytest.raises(ValueError):
        SmallCNN(**kwargs)


# --------------------------------------------------------------------------------------------- VGG16

# torchvision vgg16().features: (index, in, out) of each conv; ReLU after each, max-pool at 4, 9, 16, 23, 30
VGG16_CONVS = [(0, 3, 64), (2, 64, 64), (5, 64, 128), (7, 128, 128), (10, 128, 256), (12, 256, 256),
               (14, 256, 256), (17, 256, 512), (19, 512, 512), (21, 512, 512), (24, 512, 512),
               (26, 512, 512), (28, 512, 512)]
POOLS_BEFORE = {5, 10, 17, 24}


@pytest.fixture(scope="module")
def vgg_state():
    g = torch.Generator().manual_seed(0)
    state = {}
    for i, cin, cout in VGG16_CONVS:
        state[f"features.{i}.weight"] = torch.randn(cout, cin, 3, 3, generator=g) * math.sqrt(2 / (9 * cin))
        state[f"features.{i}.bias"] = torch.randn(cout, generator=g) * 0.01
    # classifier.* is ignored by the loader; tiny tensors stand in for the 4096-wide real ones
    for i in (0, 3, 6):
        state[f"classifier.{i}.weight"] = torch.zeros(2, 2)
        state[f"classifier.{i}.bias"] = torch.zeros(2)
    return state


@pytest.fixture(scope="module")
def vgg_file(vgg_state, tmp_path_factory):
    path = tmp_path_factory.mktemp("vgg") / "vgg16-397923af.pth"
    torch.save(vgg_state, path)
    return path


def _vgg_reference(state, x):
    """conv5_3 output computed functionally from the state dict (last ReLU and pool cut)."""
    for n, (i, _, _) in enumerate(VGG16_CONVS):
        if i in POOLS_BEFORE:
            x = F.max_pool2d(x, 2)
        x = F.conv2d(x, state[f"features.{i}.weight"], state[f"features.{i}.bias"], padding=1)
        if n < len(VGG16_CONVS) - 1:
            x = F.relu(x)
    return x


def test_vgg16_loads_torchvision_file_and_matches_reference(vgg_state, vgg_file):
    net = VGG16Backbone(vgg_file)
    conv_ids = [i for i, m in enumerate(net.features) if isinstance(m, nn.Conv2d)]
    assert conv_ids == [i for i, _, _ in VGG16_CONVS] and len(net.features) == 29
    assert (net.out_channels, net.stride) == (512, 16)
    x = _images(1)
    out = net(x)
    assert out.shape == (1, 512, 2, 3)
    torch.testing.assert_close(out, _vgg_reference(vgg_state, x), rtol=1e-4, atol=1e-4)
    assert (out < 0).any()  # no final ReLU (NetVLAD convention)


def test_vgg16_accepts_state_dict_directly(vgg_state):
    net = VGG16Backbone(vgg_state)
    torch.testing.assert_close(net.features[28].weight, vgg_state["features.28.weight"])


@pytest.mark.parametrize("trainable_from, first_trainable", [("conv5", 24), ("conv3", 10), ("conv1", 0), ("none", 29)])
def test_vgg16_freezing(vgg_state, trainable_from, first_trainable):
    net = VGG16Backbone(vgg_state, trainable_from=trainable_from)
    for i, cin, cout in VGG16_CONVS:
        assert net.features[i].weight.requires_grad == (i >= first_trainable)
    if first_trainable < 29:
        net(_images(1, 16, 16)).sum().backward()
        for i, _, _ in VGG16_CONVS:
            assert (net.features[i].weight.grad is not None) == (i >= first_trainable)


def test_vgg16_missing_file_says_how_to_get_one(tmp_path):
    with pytest.raises(FileNotFoundError, match="vgg16-397923af.pth"):
        VGG16Backbone(tmp_path / "nope.pth")


def test_vgg16_rejects_bad_state_dicts(vgg_state, tmp_path):
    with pytest.raises(ValueError, match="unexpected keys"):
        VGG16Backbone({**vgg_state, "fc.weight": torch.zeros(1)})
    with pytest.raises(ValueError, match="missing"):
        VGG16Backbone({k: v for k, v in vgg_state.items() if k != "features.24.bias"})
    with pytest.raises(ValueError, match="vgg16_bn"):  # a vgg16_bn dict has norm layers at odd indices
        VGG16Backbone({**vgg_state, "features.1.running_mean": torch.zeros(64)})
    with pytest.raises(ValueError, match="shape"):
        VGG16Backbone({**vgg_state, "features.0.weight": torch.zeros(64, 3, 5, 5)})
    with pytest.raises(ValueError, match="state dict"):
        VGG16Backbone(42)
    path = tmp_path / "tensor.pth"
    torch.save(torch.zeros(3), path)
    with pytest.raises(ValueError, match="not a state dict"):
        VGG16Backbone(path)


def test_vgg16_rejects_bad_arguments_and_inputs():
    with pytest.raises(ValueError, match="trainable_from"):
        VGG16Backbone(trainable_from="conv6")
    net = VGG16Backbone()
    with pytest.raises(ValueError, match="at least 16x16"):
        net(torch.zeros(1, 3, 8, 48))
    with pytest.raises(ValueError, match="channels"):
        net(torch.zeros(1, 4, 32, 48))


# -------------------------------------------------------------------------------------------- DINOv2

# A tiny stand-in with DINOv2's DinoVisionTransformer interface; also written as a fake hubconf.py.
TINY_VIT_SRC = '''
import torch
from torch import nn


class TinyBlock(nn.Module):
    def __init__(self, dim):
        super().__init__()
        self.fc = nn.Linear(dim, dim)

    def forward(self, x):
        return x + torch.tanh(self.fc(x))


class TinyViT(nn.Module):
    def __init__(self, dim=8, depth=3, patch_size=14, num_register_tokens=0):
        super().__init__()
        self.embed_dim, self.patch_size, self.num_register_tokens = dim, patch_size, num_register_tokens
        self.patch_embed = nn.Conv2d(3, dim, patch_size, patch_size)
        self.cls_token = nn.Parameter(torch.randn(1, 1, dim))
        self.register_tokens = nn.Parameter(torch.randn(1, num_register_tokens, dim))
        self.blocks = nn.ModuleList(TinyBlock(dim) for _ in range(depth))
        self.norm = nn.LayerNorm(dim)

    def prepare_tokens_with_masks(self, x, masks=None):
        b = x.shape[0]
        patches = self.patch_embed(x).flatten(2).transpose(1, 2)
        return torch.cat([self.cls_token.expand(b, -1, -1), self.register_tokens.expand(b, -1, -1), patches], 1)


def dinov2_vitb14(**kwargs):
    return TinyViT(dim=6, depth=5)
'''
_ns: dict = {}
exec(TINY_VIT_SRC, _ns)
TinyViT = _ns["TinyViT"]


@pytest.mark.parametrize("registers", [0, 2])
def test_dinov2_backbone_matches_reference_layout(registers):
    torch.manual_seed(0)
    vit = TinyViT(dim=8, depth=3, num_register_tokens=registers)
    net = DINOv2Backbone(vit, num_trainable_blocks=2)
    assert (net.out_channels, net.stride) == (8, 14)
    x = _images(2, 28, 42)
    fmap, cls = net.forward_with_token(x)
    assert fmap.shape == (2, 8, 2, 3) and cls.shape == (2, 8)
    with torch.no_grad():
        tokens = vit.prepare_tokens_with_masks(x)
        for block in vit.blocks:
            tokens = block(tokens)
        tokens = vit.norm(tokens)
    torch.testing.assert_close(cls, tokens[:, 0])
    for i in range(2):
        for j in range(3):  # patch (i, j) is token 1 + registers + i·w + j (row-major)
            torch.testing.assert_close(fmap[:, :, i, j], tokens[:, 1 + registers + 3 * i + j])
    torch.testing.assert_close(net(x), fmap)


def test_dinov2_backbone_freezes_first_blocks():
    torch.manual_seed(0)
    vit = TinyViT(dim=8, depth=4)
    net = DINOv2Backbone(vit, num_trainable_blocks=1)
    grad_enabled = []
    for block in vit.blocks:
        block.register_forward_hook(lambda *_: grad_enabled.append(torch.is_grad_enabled()))
    fmap, cls = net.forward_with_token(_images(2, 28, 28))
    (fmap.sum() + cls.sum()).backward()
    assert grad_enabled == [False, False, False, True]
    trainable = {n for n, p in vit.named_parameters() if p.requires_grad}
    assert trainable == {"blocks.3.fc.weight", "blocks.3.fc.bias", "norm.weight", "norm.bias"}
    assert {n for n, p in vit.named_parameters() if p.grad is not None} == trainable


@pytest.mark.parametrize("k", [-1, 4, 1.0])
def test_dinov2_backbone_rejects_bad_block_count(k):
    with pytest.raises(ValueError, match="num_trainable_blocks"):
        DINOv2Backbone(TinyViT(depth=3), num_trainable_blocks=k)


def test_dinov2_backbone_rejects_non_vit_and_bad_sizes():
    with pytest.raises(ValueError, match="prepare_tokens_with_masks"):
        DINOv2Backbone(nn.Linear(2, 2))
    net = DINOv2Backbone(TinyViT(), num_trainable_blocks=1)
    with pytest.raises(ValueError, match="multiples of the patch size 14"):
        net(_images(1, 32, 48))


@pytest.fixture
def fake_hub(tmp_path, monkeypatch):
    """A local 'clone' whose hubconf builds a TinyViT, and a fake weight file in the torch hub cache."""
    repo = tmp_path / "dinov2"
    repo.mkdir()
    (repo / "hubconf.py").write_text(TINY_VIT_SRC)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    monkeypatch.delenv("VPR_NB_DINOV2_HUB", raising=False)
    weights = tmp_path / "torch_home" / "hub" / "checkpoints" / "dinov2_vitb14_pretrain.pth"
    weights.parent.mkdir(parents=True)
    weights.write_bytes(b"")
    return repo, weights


def test_load_dinov2_wraps_local_hub_model(fake_hub, monkeypatch):
    repo, _ = fake_hub
    net = load_dinov2(repo, num_trainable_blocks=2)
    assert isinstance(net, DINOv2Backbone) and isinstance(net.vit, nn.Module)
    assert (len(net.vit.blocks), net.num_frozen, net.out_channels) == (5, 3, 6)
    monkeypatch.setenv("VPR_NB_DINOV2_HUB", str(repo))
    assert load_dinov2().num_trainable_blocks == 4
    fmap, cls = build_model("dinov2", "gem", backbone_kwargs={"hub_dir": repo}).backbone.forward_with_token(
        _images(1, 14, 28))
    assert fmap.shape == (1, 6, 1, 2) and cls.shape == (1, 6)


def test_load_dinov2_missing_code_or_weights(fake_hub, tmp_path):
    repo, weights = fake_hub
    with pytest.raises(FileNotFoundError, match="git clone https://github.com/facebookresearch/dinov2"):
        load_dinov2()
    with pytest.raises(FileNotFoundError, match="no hubconf.py"):
        load_dinov2(tmp_path)
    weights.unlink()
    with pytest.raises(FileNotFoundError, match="dinov2_vitb14_pretrain.pth"):
        load_dinov2(repo)
    with pytest.raises(FileNotFoundError, match="dinov2_vitb14_reg4_pretrain.pth"):
        load_dinov2(repo, model="dinov2_vitb14_reg")
    with pytest.raises(ValueError, match="dinov2_vitb14_reg"):
        load_dinov2(repo, model="dinov2_vitb14_lc")


# ------------------------------------------------------------------------------- VPRModel, build_model


class _RecordingAggregator(nn.Module):
    """Sum-pool aggregator that records what it received; ``needs_token`` set per instance."""

    def __init__(self, dim: int, needs_token: bool) -> None:
        super().__init__()
        self.out_dim, self.needs_token, self.received = dim, needs_token, None

    def forward(self, x):
        self.received = x
        fmap, token = x if self.needs_token else (x, 0)
        return fmap.sum(dim=(2, 3)) + token


@pytest.mark.parametrize("needs_token", [False, True])
def test_vpr_model_passes_token_only_when_needed(needs_token):
    torch.manual_seed(0)
    backbone = SmallCNN(width=8, out_channels=16)
    agg = _RecordingAggregator(16, needs_token)
    model = VPRModel(backbone, agg)
    x = _images(3)
    desc = model(x)
    fmap, token = backbone.forward_with_token(x)
    raw = fmap.sum(dim=(2, 3)) + (token if needs_token else 0)
    torch.testing.assert_close(desc, raw / raw.norm(dim=1, keepdim=True))
    assert isinstance(agg.received, tuple) == needs_token
    assert model.out_dim == 16


def test_build_model_default_is_small_cnn_gem():
    torch.manual_seed(0)
    model = build_model()
    assert isinstance(model.backbone, SmallCNN) and model.out_dim == 128
    desc = model(_images(4))
    assert desc.shape == (4, 128)
    torch.testing.assert_close(desc.norm(dim=1), torch.ones(4))
    desc.sum().backward()
    assert model.backbone.features[0].weight.grad is not None


@pytest.mark.parametrize("aggregator, kwargs, dim", [
    ("netvlad", {"num_clusters": 4}, 4 * 16),
    ("salad", {"num_clusters": 8, "cluster_dim": 4, "token_dim": 5}, 5 + 8 * 4),
    ("max", {}, 16),
])
def test_build_model_with_each_aggregator(aggregator, kwargs, dim):
    torch.manual_seed(0)
    model = build_model("small_cnn", aggregator, backbone_kwargs={"width": 8, "out_channels": 16}, **kwargs)
    desc = model(_images(3))
    assert model.out_dim == dim and desc.shape == (3, dim)
    torch.testing.assert_close(desc.norm(dim=1), torch.ones(3))


def test_vpr_model_uses_backbone_in_channels():
    torch.manual_seed(0)
    model = build_model(SmallCNN(in_channels=1, width=8, out_channels=16), "gem")
    assert model(torch.rand(2, 1, 32, 48)).shape == (2, 16)
    with pytest.raises(ValueError, match="1 channels"):
        model(_images(2))


def test_build_model_accepts_a_backbone_module():
    torch.manual_seed(0)
    backbone = SmallCNN(width=8, out_channels=24)
    model = build_model(backbone, "mean")
    assert model.backbone is backbone and model.out_dim == 24


def test_vpr_model_rejects_token_aggregator_on_vgg():
    with pytest.raises(ValueError, match="forward_with_token"):
        VPRModel(VGG16Backbone(), _RecordingAggregator(512, needs_token=True))


def test_build_model_rejects_bad_arguments():
    with pytest.raises(ValueError, match=", ".join(BACKBONE_NAMES)):
        build_model("resnet50")
    with pytest.raises(ValueError, match="netvlad"):
        build_model("small_cnn", "vlad")
    with pytest.raises(ValueError, match="by name"):
        build_model(SmallCNN(width=8), "gem", backbone_kwargs={"width": 4})
    with pytest.raises(ValueError, match="backbone_kwargs"):
        build_model("small_cnn", backbone_kwargs=[("width", 4)])
    with pytest.raises(ValueError, match="out_channels"):
        build_model(nn.Linear(3, 8))


def test_vpr_model_rejects_bad_parts():
    with pytest.raises(ValueError, match="nn.Module"):
        VPRModel(SmallCNN(), lambda x: x)
    with pytest.raises(ValueError, match="out_dim"):
        VPRModel(SmallCNN(), nn.Identity())


@pytest.mark.parametrize("x, match", BAD_IMAGES[:5])
def test_vpr_model_rejects_bad_images(x, match):
    model = VPRModel(SmallCNN(width=8, out_channels=16), _RecordingAggregator(16, needs_token=False))
    with pytest.raises(ValueError, match=match):
        model(x)


def test_init_netvlad_from_images_is_deterministic_and_checked():
    import numpy as np

    from vpr_nb.models import init_netvlad
    imgs = np.random.default_rng(0).integers(0, 256, (12, 16, 24, 3), dtype=np.uint8)
    outs = []
    for _ in range(2):
        torch.manual_seed(0)
        model = build_model("small_cnn", "netvlad", num_clusters=4)
        descs, cents = init_netvlad(model, imgs, per_image=10, niter=10, seed=3, max_images=8)
        outs.append(model.aggregator.conv.weight.detach().clone())
        assert descs.shape == (80, model.backbone.out_channels) and cents.shape == (4, model.backbone.out_channels)
        np.testing.assert_allclose(model.aggregator.centroids.detach().numpy(), cents, rtol=1e-6)
    assert torch.equal(outs[0], outs[1])
    with pytest.raises(ValueError, match="NetVLAD"):
        init_netvlad(build_model("small_cnn", "gem"), imgs)


def test_init_netvlad_skips_exactly_zero_local_features():
    # a trained backbone whose final ReLU switches some positions off entirely (all channels 0):
    # before the fix init_netvlad sampled them and init_from_clusters raised "all-zero row"
    import numpy as np

    from vpr_nb.aggregation import NetVLAD
    from vpr_nb.models import init_netvlad

    class HalfDead(nn.Module):
        def __init__(self):
            super().__init__()
            self.cnn = SmallCNN(width=8, out_channels=16)
            self.out_channels, self.stride = 16, 4

        def forward(self, x):
            fmap = self.cnn(x).clone()
            fmap[:, :, ::2] = 0.0                  # every other row of positions is dead
            return fmap

    imgs = np.random.default_rng(0).integers(0, 256, (10, 16, 24, 3), dtype=np.uint8)
    torch.manual_seed(0)
    model = VPRModel(HalfDead(), NetVLAD(num_clusters=4, dim=16))
    descs, cents = init_netvlad(model, imgs, per_image=12, niter=10, seed=0)
    assert len(descs) == 10 * 12 and np.allclose(np.linalg.norm(descs, axis=1), 1.0, atol=1e-5)
    assert model.aggregator.alpha > 0 and np.isfinite(model.aggregator.alpha)
    assert torch.isfinite(model(torch.randn(2, 3, 16, 24))).all()
