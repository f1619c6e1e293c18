"""The frozen-block cache: refused where it would be wrong, exact where it is used (vpr_nb.feature_cache)."""

import numpy as np
import pytest
import torch
from torch import nn

from vpr_nb.evaluation import compute_descriptors, images_to_tensor
from vpr_nb.feature_cache import FrozenFeatureCache, attach, check_cacheable, detach, image_keys, input_signature
from vpr_nb.losses import MultiSimilarityLoss, TripletLoss
from vpr_nb.models import SmallCNN, build_model
from vpr_nb.pretrain import course_backbone
from vpr_nb.samplers import random_place_batches
from vpr_nb.synthetic import make_dataset
from vpr_nb.training import PlaceBatchSource, TrainConfig, TripletSource, train

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def world():
    return make_dataset("city", seed=0, blocks=(5, 2))


def _images(n=12, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (n, 32, 48, 3), dtype=np.uint8)


def test_check_cacheable_accepts_the_small_cnn_and_refuses_random_or_batch_dependent_layers():
    net = SmallCNN(width=8).set_trainable_blocks(1)
    check_cacheable(net.features[:net.num_frozen])                 # conv, GroupNorm, ReLU: fine
    with pytest.raises(ValueError, match="batch statistics"):
        check_cacheable(nn.Sequential(nn.Conv2d(3, 4, 1), nn.BatchNorm2d(4)))
    with pytest.raises(ValueError, match="random in train mode"):
        check_cacheable(nn.Sequential(nn.Conv2d(3, 4, 1), nn.Dropout(0.1)))
    with pytest.raises(ValueError, match="running statistics"):
        check_cacheable(nn.InstanceNorm2d(4, track_running_stats=True))

    class Noise(nn.Module):
        def forward(self, x):
            return x + torch.randn_like(x)
    with pytest.raises(ValueError, match="not a layer known to be deterministic"):
        check_cacheable(nn.Sequential(nn.Conv2d(3, 4, 1), Noise()))


def test_attach_refuses_other_backbones_and_bad_caches():
    with pytest.raises(ValueError, match="SmallCNN"):
        attach(nn.Conv2d(3, 4, 1), FrozenFeatureCache())
    with pytest.raises(ValueError, match="FrozenFeatureCache"):
        attach(SmallCNN(width=8), object())
    with pytest.raises(ValueError, match="dtype"):
        FrozenFeatureCache(dtype="int8")


def test_cached_forward_equals_uncached_and_counts_hits():
    torch.manual_seed(0)
    net = SmallCNN(width=8, out_channels=16).set_trainable_blocks(1).train()
    x = images_to_tensor(_images())                   # channels-last strides, as every caller passes them
    want = net(x)
    cache = FrozenFeatureCache()
    with cache.attached(net):
        first, second, part = net(x), net(x), net(x[[3, 1, 7]])
        mixed = net(torch.cat([x[:4], images_to_tensor(_images(3, seed=1))]))
    assert net.frozen_cache is None                   # detached after the block
    for got in (first, second):
        assert torch.equal(got, want)
        assert got.stride() == want.stride()          # same memory layout (a later dropout draws in memory order)
    assert torch.equal(part, want[[3, 1, 7]])
    assert torch.allclose(mixed[:4], want[:4], atol=1e-6)
    assert cache.stats()["images"] == 15 and cache.hits == 12 + 3 + 4 and cache.misses == 12 + 3
    assert cache.nbytes == 15 * (16 * 8 * 12 * 4 + 3 * 32 * 48 * 4)     # the maps and their keys (the inputs)


def test_a_batch_with_one_image_twice_stores_it_once():
    net = SmallCNN(width=8).set_trainable_blocks(1)
    x = images_to_tensor(_images(4))
    cache = FrozenFeatureCache()
    with cache.attached(net):
        out = net(torch.cat([x, x[:2]]))
    assert len(cache) == 4 and torch.allclose(out[4:], out[:2])
    assert len(set(image_keys(torch.cat([x, x[:2]])))) == 4


def test_keys_are_the_exact_bytes_and_a_reshaped_input_is_another_input():
    x = images_to_tensor(_images(3))
    keys = image_keys(x)
    assert keys[0] == x[0].contiguous().numpy().tobytes() and len(set(keys)) == 3
    nudged = x.clone()
    nudged[1, 2, 31, 47] = torch.nextafter(nudged[1, 2, 31, 47], torch.tensor(10.0))   # one float, one ulp
    assert image_keys(nudged)[1] != keys[1] and image_keys(nudged)[0] == keys[0]
    other = x.reshape(3, 3, 48, 32)                   # the same bytes as another image size
    assert image_keys(other) == keys and input_signature(other) != input_signature(x)
    net = SmallCNN(width=8).set_trainable_blocks(1)
    cache = FrozenFeatureCache()
    with cache.attached(net):
        net(x)
        with pytest.raises(ValueError, match="one cache per image size"):
            net(other)                                # not a hit: looked up among 3x48x32 inputs


def test_changed_frozen_weights_drop_the_stored_maps():
    torch.manual_seed(0)
    net = SmallCNN(width=8).set_trainable_blocks(1)
    x = images_to_tensor(_images())
    cache = FrozenFeatureCache()
    with cache.attached(net):
        net(x)
        net.load_state_dict(net.state_dict())         # same values: the maps stay
        net(x)
        assert cache.resets == 0 and cache.hits == 12
        with torch.no_grad():
            net.features[0].weight.mul_(2.0)          # other frozen weights: the maps are recomputed
        got = net(x)
    assert cache.resets == 1
    assert torch.equal(got, net(x))


def test_full_cache_bypasses_and_stays_exact():
    net = SmallCNN(width=8).set_trainable_blocks(1)
    x = images_to_tensor(_images())
    cache = FrozenFeatureCache(max_bytes=0)
    with cache.attached(net):
        got = net(x)
        got2 = net(x)
    assert torch.equal(got, net(x)) and torch.equal(got2, got)
    assert len(cache) == 0 and cache.bypassed == 24


def test_float16_storage_is_close_but_not_exact():
    net = SmallCNN(width=8).set_trainable_blocks(1)
    x = images_to_tensor(_images())
    cache = FrozenFeatureCache(dtype="float16")
    with cache.attached(net):
        net(x)
        half = net(x)
    assert torch.allclose(half, net(x), atol=5e-2)
    assert cache.nbytes == 12 * (16 * 8 * 12 * 2 + 3 * 32 * 48 * 4)     # 2 bytes per map value; float32 keys


def _train_pair(make_model, make_source, val, epochs=1):
    """Same run without and with the cache: (history, final test descriptors) of each."""
    out = []
    for cached in (False, True):
        model = make_model()
        if cached:
            attach(model.backbone, FrozenFeatureCache())
        hist = train(model, make_source(), val, TrainConfig(epochs=epochs, optimizer="adam", lr=1e-3, seed=0,
                                                            ns=(1,), initial_candidate=True), progress=False)
        detach(model.backbone)
        out.append((hist, compute_descriptors(model, val.q_images)))
    return out


def test_triplet_training_is_the_same_with_the_cache(world):
    tr = world.train
    tr = tr.take_queries(np.arange(48))                      # 3 steps of 16 queries

    def model():
        torch.manual_seed(0)
        return build_model(course_backbone(trainable_blocks=1, final_relu=False), "gem")

    (h0, d0), (h1, d1) = _train_pair(model, lambda: TripletSource(tr, TripletLoss(), max_heading_diff=45.0), world.val)
    assert np.allclose(h0.losses, h1.losses, atol=1e-5) and h0.losses[0] > 0
    assert h0.recalls(1) == h1.recalls(1) and h0.initial == h1.initial
    assert np.abs(d0 - d1).max() < 1e-5


def test_place_batch_training_with_dropout_is_the_same_with_the_cache(world):
    tr = world.train
    images = np.concatenate([tr.db_images, tr.q_images])
    labels = np.concatenate([tr.db_place, tr.q_place])

    def model():
        torch.manual_seed(0)                                   # SALAD's heads have dropout 0.3
        return build_model(course_backbone(trainable_blocks=1, final_relu=False), "salad", num_clusters=8,
                           cluster_dim=8, token_dim=8, hidden_dim=16)

    def source():
        return PlaceBatchSource(images, lambda m, e, rng: random_place_batches(labels, 8, 4, num_batches=3, seed=rng),
                                loss=MultiSimilarityLoss())

    (h0, d0), (h1, d1) = _train_pair(model, source, world.val, epochs=2)
    assert np.allclose(h0.losses, h1.losses, atol=1e-5)
    assert np.abs(d0 - d1).max() < 1e-5
