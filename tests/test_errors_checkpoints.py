"""Weight files that are truncated, pickled, of another architecture or without their card's hash end in one
clear ValueError / FileNotFoundError naming the file (vpr_nb.models.read_weights, load_state_checked,
vpr_nb.pretrain.course_backbone / card)."""
import hashlib
import json

import pytest
import torch

from vpr_nb import pretrain, results
from vpr_nb.models import SmallCNN, VGG16Backbone, build_model, load_state_checked, read_weights


class Payload:     # a class a pickle would import: never loaded
    pass


def _tiny_state(width=8):
    torch.manual_seed(0)
    return SmallCNN(width=width, out_channels=16).state_dict()


def test_read_weights_refuses_a_pickle_payload_without_torch_advice(tmp_path):
    path = tmp_path / "evil.pt"
    torch.save({"model": _tiny_state(), "extra": Payload()}, path)
    with pytest.raises(ValueError, match=r"evil\.pt is not a weights-only checkpoint: it holds pickled Python "
                                         r"objects \(class \S*Payload\), and vpr_nb will not unpickle it") as err:
        read_weights(path)
    assert "weights_only=False" not in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("cut", [50, 0.5, 0.9, -22])     # 0.5: OSError [Errno 22] on torch 2.x
def test_read_weights_names_a_truncated_file(tmp_path, cut):
    good = tmp_path / "good.pt"
    torch.save({"model": {f"w{i}": torch.randn(64, 64) for i in range(8)}}, good)
    data = good.read_bytes()
    n = int(cut * len(data)) if isinstance(cut, float) else cut % len(data) if cut < 0 else cut
    bad = tmp_path / "cut.pt"
    bad.write_bytes(data[:n])
    with pytest.raises(ValueError, match=r"cut\.pt is not a readable torch checkpoint \(\w+: .*\): the file is "
                                         r"truncated or corrupted"):
        read_weights(bad)


def test_read_weights_missing_junk_and_non_mapping(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"no checkpoint at .*none\.pt"):
        read_weights(tmp_path / "none.pt")
    (tmp_path / "empty.pt").write_bytes(b"")
    with pytest.raises(ValueError, match=r"empty\.pt is empty \(0 bytes\)"):
        read_weights(tmp_path / "empty.pt")
    (tmp_path / "junk.pt").write_bytes(b"hello world" * 20)
    with pytest.raises(ValueError, match=r"junk\.pt is not a"):
        read_weights(tmp_path / "junk.pt")
    torch.save(torch.zeros(3), tmp_path / "tensor.pt")
    with pytest.raises(ValueError, match=r"tensor\.pt holds a Tensor, not a state dict"):
        read_weights(tmp_path / "tensor.pt")


def test_a_state_dict_of_another_width_is_one_line_naming_shapes():
    model = build_model(SmallCNN(width=16, out_channels=16), "gem")
    other = build_model(SmallCNN(width=8, out_channels=16), "gem").state_dict()
    with pytest.raises(ValueError, match=r"^run/best\.pt does not fit this VPRModel: \d+ tensor\(s\) differ: "
                                         r"backbone\.features\.0\.weight is \(8, 3, 4, 4\) in the file but "
                                         r"\(16, 3, 4, 4\) in the model.*config\.json\)$") as err:
        load_state_checked(model, other, "run/best.pt")
    assert "\n" not in str(err.value)
    gem = build_model(SmallCNN(width=16, out_channels=16), "netvlad", num_clusters=4).state_dict()
    with pytest.raises(ValueError, match=r"key\(s\) of the model are missing: aggregator\.p.*key\(s\) are not in the "
                                         r"model: aggregator\."):
        load_state_checked(model, gem, "run/best.pt")
    ddp = {f"module.{k}": v for k, v in model.state_dict().items()}
    with pytest.raises(ValueError, match="DistributedDataParallel's 'module.' prefix"):
        load_state_checked(model, ddp, "ddp.pt")
    same = build_model(SmallCNN(width=16, out_channels=16), "gem").state_dict()
    assert load_state_checked(model, same, "ok.pt") is model
    assert torch.equal(model.state_dict()["backbone.features.0.weight"], same["backbone.features.0.weight"])


def test_vgg16_weights_with_a_pickle_payload_are_refused(tmp_path):
    path = tmp_path / "vgg16-397923af.pth"
    torch.save({"features.0.weight": Payload()}, path)
    with pytest.raises(ValueError, match=r"is not a weights-only VGG16 weights file"):
        VGG16Backbone(path)


def _course_pair(folder, state, drop=(), **card):
    folder.mkdir(exist_ok=True)
    path = folder / "cb.pt"
    torch.save(state, path)
    meta = {"sha256": hashlib.sha256(path.read_bytes()).hexdigest(), "command": "python -m vpr_nb.pretrain",
            "config": {"width": 8, "out_channels": 16}, **card}
    path.with_suffix(".json").write_text(json.dumps({k: v for k, v in meta.items() if k not in drop}))
    return path


def test_course_backbone_loads_a_good_pair_and_refuses_a_pickle_payload(tmp_path):
    assert isinstance(pretrain.course_backbone(_course_pair(tmp_path / "good", _tiny_state())), SmallCNN)
    evil = _course_pair(tmp_path / "evil", {**_tiny_state(), "x": Payload()})
    with pytest.raises(ValueError, match=r"cb\.pt is not a weights-only course backbone: it holds pickled") as err:
        pretrain.course_backbone(evil)
    assert "weights_only=False" not in str(err.value)


@pytest.mark.parametrize("drop, card, match", [
    (("sha256",), {}, r"cb\.json has no valid 'sha256' \(got None\)"),
    ((), {"sha256": "abc"}, r"cb\.json has no valid 'sha256' \(got 'abc'\)"),
    ((), {"config": {"width": 8}}, r"cb\.json: 'config' must hold the positive integers \['out_channels'\]"),
])
def test_course_backbone_card_without_its_fields_names_the_card(tmp_path, drop, card, match):
    with pytest.raises(ValueError, match=match):
        pretrain.course_backbone(_course_pair(tmp_path, _tiny_state(), drop, **card))


def test_course_backbone_card_that_is_not_json_or_of_another_width(tmp_path):
    path = _course_pair(tmp_path, _tiny_state())
    path.with_suffix(".json").write_text('{"sha256": ')
    with pytest.raises(ValueError, match=r"cb\.json is not a readable JSON card"):
        pretrain.course_backbone(path)
    path = _course_pair(tmp_path, _tiny_state(), config={"width": 12, "out_channels": 16})
    with pytest.raises(ValueError, match=r"cb\.pt does not fit this SmallCNN: .*its card says SmallCNN\(width=12"):
        pretrain.course_backbone(path)


def test_backbone_fingerprint_of_a_truncated_file_names_it(tmp_path):
    path = tmp_path / "cb.pt"
    torch.save(_tiny_state(), path)
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(ValueError, match=r"cb\.pt is not a readable torch course backbone"):
        results.backbone_fingerprint(path)
