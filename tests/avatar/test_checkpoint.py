"""Checkpoints: save -> load keeps outputs and weights; the content hash; every damaged file is a
one-line DlaInputError; class paths outside dlacli are refused; the resolver and the cache."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest
import torch
from torch import nn

from dlacli.avatar import checkpoint as ck
from dlacli.errors import DlaInputError


@dataclasses.dataclass
class Inner:
    gain: float = 1.5
    names: tuple[str, ...] = ("a", "b")


@dataclasses.dataclass
class ToyConfig:
    width: int = 8
    depth: int = 2
    act: str = "tanh"
    norm: bool = True
    kernel: tuple[int, int] = (3, 3)
    dropout: float | None = None
    inner: Inner = dataclasses.field(default_factory=Inner)


class ToyNet(nn.Module):
    """Linear layers, a BatchNorm (buffers, int64 counter, eval-mode behaviour) and a plain buffer."""

    def __init__(self, config: ToyConfig):
        super().__init__()
        self.config = config
        self.inp = nn.Linear(4, config.width)
        self.hidden = nn.ModuleList(nn.Linear(config.width, config.width) for _ in range(config.depth))
        self.norm = nn.BatchNorm1d(config.width) if config.norm else nn.Identity()
        self.out = nn.Linear(config.width, 2)
        self.register_buffer("offset", torch.linspace(-1, 1, 2))

    def forward(self, x):  # [B, 4] -> [B, 2]
        act = getattr(torch, self.config.act)
        h = self.norm(act(self.inp(x)))
        for layer in self.hidden:
            h = act(layer(h)) * self.config.inner.gain
        return self.out(h) + self.offset


@dataclasses.dataclass
class TiedConfig:
    vocab: int = 5
    dim: int = 3


class TiedNet(nn.Module):
    def __init__(self, config: TiedConfig):
        super().__init__()
        self.emb = nn.Embedding(config.vocab, config.dim)
        self.head = nn.Linear(config.dim, config.vocab, bias=False)
        self.head.weight = self.emb.weight  # nanoGPT's weight tying

    def forward(self, idx):
        return self.head(self.emb(idx))


@dataclasses.dataclass
class DictConfig:
    table: dict = dataclasses.field(default_factory=dict)  # not a type checkpoints hold


HERE = (ToyNet.__module__ + ".",)  # the toy lives here, outside dlacli: tests allow this module


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch) -> Path:
    monkeypatch.setenv("DLA_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache" / "checkpoints"


def _trained(config=None, seed=0) -> ToyNet:
    torch.manual_seed(seed)
    net = ToyNet(config or ToyConfig())
    net.train()
    net(torch.randn(16, 4))  # moves the BatchNorm running statistics off their defaults
    return net.eval()


def _load(path, **kw):
    return ck.load_checkpoint(path, allowed_prefixes=HERE, **kw)


def _edit_config(folder: Path, change) -> None:
    rec = json.loads((folder / "config.json").read_text())
    change(rec)
    (folder / "config.json").write_text(json.dumps(rec))


def test_round_trip_outputs_weights_and_config(tmp_path):
    net = _trained()
    cfg = net.config
    digest = ck.save_checkpoint(tmp_path / "ck", net, cfg, step=7, extra={"loss": 0.25})
    assert sorted(p.name for p in (tmp_path / "ck").iterdir()) == ["config.json", "model.safetensors"]
    got = _load(tmp_path / "ck")
    assert got.hash == digest and len(digest) == 64 and got.step == 7 and got.extra == {"loss": 0.25}
    assert got.config == cfg and isinstance(got.config.kernel, tuple) and isinstance(got.config.inner, Inner)
    assert type(got.module) is ToyNet and not got.module.training and got.optimizer_state is None
    x = torch.randn(5, 4)
    with torch.no_grad():
        assert torch.equal(got.module(x), net(x))
    a, b = net.state_dict(), got.module.state_dict()
    assert list(a) == list(b)
    assert all(torch.equal(a[k], b[k]) and a[k].dtype == b[k].dtype for k in a)
    rec = json.loads((tmp_path / "ck" / "config.json").read_text())
    assert rec["format"] == "dla.checkpoint/1" and rec["class"] == f"{ToyNet.__module__}.ToyNet"
    assert rec["config"]["inner"] == {"gain": 1.5, "names": ["a", "b"]}
    assert _load(tmp_path / "ck" / "config.json").hash == digest  # a file of the folder names it too


def test_hash_ignores_step_and_training_state_but_not_weights_or_config(tmp_path):
    net = _trained()
    opt = torch.optim.Adam(net.parameters())
    h1 = ck.save_checkpoint(tmp_path / "a", net, net.config, step=1)
    h2 = ck.save_checkpoint(tmp_path / "b", net, net.config, step=900, optimizer=opt, extra={"x": 1})
    assert h1 == h2
    assert (tmp_path / "a" / "model.safetensors").read_bytes() == (tmp_path / "b" / "model.safetensors").read_bytes()
    # an int in a float field is stored as the float it means: same hash as the float
    assert ck.save_checkpoint(
        tmp_path / "c", net, dataclasses.replace(net.config, inner=Inner(gain=2))
    ) == ck.save_checkpoint(tmp_path / "d", net, dataclasses.replace(net.config, inner=Inner(gain=2.0)))
    assert ck.save_checkpoint(tmp_path / "e", net, dataclasses.replace(net.config, act="relu")) != h1
    with torch.no_grad():
        net.out.bias[0] += 1e-3
    assert ck.save_checkpoint(tmp_path / "f", net, net.config) != h1


def test_tied_weights_stored_once_and_rebuilt(tmp_path):
    torch.manual_seed(1)
    net = TiedNet(TiedConfig())
    ck.save_checkpoint(tmp_path / "t", net, TiedConfig())
    from safetensors.torch import load_file

    assert list(load_file(tmp_path / "t" / "model.safetensors")) == ["emb.weight"]
    got = _load(tmp_path / "t").module
    assert got.head.weight is got.emb.weight and torch.equal(got.emb.weight, net.emb.weight)


def test_tampered_truncated_and_broken_files(tmp_path):
    net = _trained()
    ck.save_checkpoint(tmp_path / "ck", net, net.config)
    weights = tmp_path / "ck" / "model.safetensors"
    good = weights.read_bytes()
    weights.write_bytes(good[:-1] + bytes([good[-1] ^ 1]))  # one bit of one weight
    with pytest.raises(DlaInputError, match="hash .* differs"):
        _load(tmp_path / "ck")
    weights.write_bytes(good[: len(good) // 2])
    with pytest.raises(DlaInputError, match="model.safetensors: truncated"):
        _load(tmp_path / "ck")
    weights.write_bytes(good[:5])
    with pytest.raises(DlaInputError, match="truncated"):
        _load(tmp_path / "ck")
    weights.unlink()
    with pytest.raises(DlaInputError, match="model.safetensors: no such file"):
        _load(tmp_path / "ck")
    weights.write_bytes(good)
    _edit_config(tmp_path / "ck", lambda r: r["config"].update(act="relu"))  # config edited, hash not
    with pytest.raises(DlaInputError, match="differs from the recorded"):
        _load(tmp_path / "ck")
    (tmp_path / "ck" / "config.json").write_text('{"format": "dla.checkpoint/1", ')
    with pytest.raises(DlaInputError, match="config.json: not valid JSON"):
        _load(tmp_path / "ck")
    with pytest.raises(DlaInputError, match="no such checkpoint folder"):
        _load(tmp_path / "nowhere")


def test_every_error_is_one_line(tmp_path):
    net = _trained()
    ck.save_checkpoint(tmp_path / "ck", net, net.config)
    (tmp_path / "ck" / "model.safetensors").write_bytes(b"\xff" * 64)
    with pytest.raises(DlaInputError) as info:
        _load(tmp_path / "ck")
    assert "\n" not in str(info.value) and str(tmp_path / "ck") in str(info.value)


@pytest.mark.parametrize("version", ["dla.checkpoint/2", "dla.avatar/1", None])
def test_wrong_format_version(tmp_path, version):
    net = _trained()
    ck.save_checkpoint(tmp_path / "ck", net, net.config)
    _edit_config(tmp_path / "ck", lambda r: r.update(format=version) if version else r.pop("format"))
    with pytest.raises(DlaInputError, match="config.json: .*dla reads 'dla.checkpoint/1'"):
        _load(tmp_path / "ck")


def test_classes_outside_dlacli_are_refused_before_import(tmp_path):
    net = _trained()
    ck.save_checkpoint(tmp_path / "ck", net, net.config)
    with pytest.raises(DlaInputError, match="outside dlacli.; dla imports checkpoint classes only from there"):
        ck.load_checkpoint(tmp_path / "ck")  # the default: only dlacli.
    _edit_config(tmp_path / "ck", lambda r: r.update({"class": "evil_module_that_runs_code.Net"}))
    with pytest.raises(DlaInputError, match="outside dlacli"):
        ck.load_checkpoint(tmp_path / "ck")
    for dotted, problem in [
        ("dlacli.nn.no_such_net.Net", "cannot be imported"),
        ("dlacli.avatar.checkpoint.NoSuchNet", "does not exist"),
        ("dlacli.errors.DlaInputError", "not a torch nn.Module"),
        ("dlacli.avatar.checkpoint.Path", "defined in pathlib, outside"),
        ("dlacliX.Net", "outside dlacli"),
        ("os.system", "outside"),
        ("x; rm", "not a dotted"),
    ]:
        _edit_config(tmp_path / "ck", lambda r, d=dotted: r.update({"class": d}))
        with pytest.raises(DlaInputError, match=problem):
            ck.load_checkpoint(tmp_path / "ck", allowed_prefixes=("dlacli.",) + HERE)
    _edit_config(
        tmp_path / "ck", lambda r: r.update({"class": f"{ToyNet.__module__}.ToyNet", "config_class": "os.Cfg"})
    )
    with pytest.raises(DlaInputError, match="config_class 'os.Cfg' is outside"):
        _load(tmp_path / "ck")


def test_config_fields_are_checked(tmp_path):
    net = _trained()
    ck.save_checkpoint(tmp_path / "ck", net, net.config)
    cases = [
        (lambda c: c.update(colour="red"), "unknown field.* colour"),
        (lambda c: c.pop("depth"), "lacks field.* depth"),
        (lambda c: c.update(width=8.0), "width is 8.0, expected int"),
        (lambda c: c.update(norm=1), "norm is 1"),
        (lambda c: c.update(kernel=[3]), "kernel has 1 items, expected 2"),
        (lambda c: c["inner"].update(extra=1), "unknown field.* inner.extra"),
    ]
    pristine = (tmp_path / "ck" / "config.json").read_text()
    for change, problem in cases:
        (tmp_path / "ck" / "config.json").write_text(pristine)
        _edit_config(tmp_path / "ck", lambda r, ch=change: ch(r["config"]))
        with pytest.raises(DlaInputError, match=r"config.json: config .*" + problem):
            _load(tmp_path / "ck")


def test_shape_mismatch_with_a_consistent_hash(tmp_path):
    net = _trained()
    ck.save_checkpoint(tmp_path / "ck", net, net.config)

    def rehash(r, **changes):
        r["config"].update(changes)
        weights = (tmp_path / "ck" / "model.safetensors").read_bytes()
        r["hash"] = ck.content_hash(r["class"], r["config_class"], r["config"], weights)

    _edit_config(tmp_path / "ck", lambda r: rehash(r, width=4))
    with pytest.raises(DlaInputError, match=r"model.safetensors: has wrong shapes .*inp.weight \(8, 4\) vs \(4, 4\)"):
        _load(tmp_path / "ck")
    _edit_config(tmp_path / "ck", lambda r: rehash(r, width=8, depth=1))
    with pytest.raises(DlaInputError, match="has unexpected tensors for ToyNet: hidden.1.bias"):
        _load(tmp_path / "ck")
    _edit_config(tmp_path / "ck", lambda r: rehash(r, depth=3))
    with pytest.raises(DlaInputError, match="lacks tensors for ToyNet: hidden.2.bias, hidden.2.weight"):
        _load(tmp_path / "ck")


def test_save_refuses_what_cannot_be_loaded(tmp_path):
    net = _trained()

    @dataclasses.dataclass
    class Local:
        a: int = 1

    with pytest.raises(ValueError, match="not importable"):
        ck.save_checkpoint(tmp_path / "x", net, Local())

    with pytest.raises(ValueError, match="cannot be stored as JSON"):
        ck.save_checkpoint(tmp_path / "x", net, DictConfig())
    with pytest.raises(ValueError, match="does not survive a JSON round trip"):
        ck.save_checkpoint(tmp_path / "x", net, dataclasses.replace(net.config, kernel=[3, 3]))  # list, not tuple
    with pytest.raises(ValueError, match="extra is not plain JSON"):
        ck.save_checkpoint(tmp_path / "x", net, net.config, extra={"t": torch.zeros(1)})
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    with pytest.raises(DlaInputError, match="holds files dla did not write"):
        ck.save_checkpoint(tmp_path / "mine", net, net.config)
    assert not (tmp_path / "x").exists() and (tmp_path / "mine" / "notes.txt").exists()


def test_optimizer_state_round_trip_resumes_exactly(tmp_path):
    torch.manual_seed(2)
    cfg = ToyConfig(norm=False)
    net = ToyNet(cfg)
    opt = torch.optim.Adam(net.parameters(), lr=1e-2, betas=(0.5, 0.9))
    data = [(torch.randn(8, 4), torch.randn(8, 2)) for _ in range(3)]

    def step(model, optim, batch):
        optim.zero_grad()
        nn.functional.mse_loss(model(batch[0]), batch[1]).backward()
        optim.step()

    for batch in data[:2]:
        step(net, opt, batch)
    ck.save_checkpoint(tmp_path / "ck", net, cfg, step=2, optimizer=opt)
    assert (tmp_path / "ck" / "optimizer.safetensors").is_file()
    got = _load(tmp_path / "ck")
    assert got.step == 2
    net2 = got.module.train()
    opt2 = torch.optim.Adam(net2.parameters(), lr=0.5)
    opt2.load_state_dict(got.optimizer_state)
    assert opt2.param_groups[0]["betas"] == (0.5, 0.9) and opt2.param_groups[0]["lr"] == 1e-2
    step(net, opt, data[2])
    step(net2, opt2, data[2])
    for (name, a), b in zip(net.named_parameters(), net2.parameters()):
        assert torch.equal(a, b), name
    s1, s2 = opt.state_dict()["state"], opt2.state_dict()["state"]
    assert s1.keys() == s2.keys() and all(torch.equal(s1[k][n], s2[k][n]) for k in s1 for n in s1[k])
    # the optimizer file is checked too
    p = tmp_path / "ck" / "optimizer.safetensors"
    p.write_bytes(p.read_bytes()[:-4])
    with pytest.raises(DlaInputError, match="optimizer.safetensors: sha256 differs"):
        _load(tmp_path / "ck")


def test_optimizer_state_encoding_keeps_types():
    state = {
        "state": {0: {"step": torch.tensor(3.0), "v": [1, (2.0, float("inf"))]}},
        "param_groups": [{"betas": (0.5, 0.9), "params": [0], "$odd": None, "foreach": None}],
    }
    tensors = {}
    enc = ck._encode_state(state, tensors, "opt")
    back = ck._decode_state(json.loads(json.dumps(enc, allow_nan=False)), tensors, "x")
    assert back["state"][0]["v"] == [1, (2.0, float("inf"))] and back["param_groups"] == state["param_groups"]
    assert torch.equal(back["state"][0]["step"], state["state"][0]["step"])


# --------------------------------------------------------------------------------------------
# resolver and cache


def _fake(folder: Path, digest: str) -> Path:
    """A checkpoint folder whose config.json records `digest` (the resolver reads only that)."""
    folder.mkdir(parents=True)
    rec = {
        "format": "dla.checkpoint/1",
        "class": "dlacli.x.X",
        "config_class": "dlacli.x.C",
        "config": {},
        "step": 0,
        "hash": digest,
        "optimizer": None,
        "extra": {},
    }
    (folder / "config.json").write_text(json.dumps(rec))
    return folder


def test_install_and_resolve_by_full_hash_and_prefix(tmp_path, cache):
    net = _trained()
    digest = ck.save_checkpoint(tmp_path / "ck", net, net.config, step=3)
    installed = ck.install_checkpoint(tmp_path / "ck")
    assert installed == cache / digest and (installed / "model.safetensors").is_file()
    assert ck.install_checkpoint(tmp_path / "ck") == installed  # idempotent
    assert ck.resolve_checkpoint(digest) == installed
    assert ck.resolve_checkpoint(digest[:8].upper()) == installed
    assert ck.resolve_checkpoint(ck.short_id(digest)) == installed
    got = _load(ck.resolve_checkpoint(digest[:10]))
    assert got.hash == digest and got.step == 3
    # a folder copied into the cache under any name is found by its recorded hash
    other = ck.save_checkpoint(tmp_path / "ck2", _trained(seed=5), ToyConfig())
    shutil.copytree(tmp_path / "ck2", cache / "my-copy")
    assert ck.resolve_checkpoint(other[:12]) == cache / "my-copy"


def test_resolve_explicit_path_and_search_folders(tmp_path):
    net = _trained()
    digest = ck.save_checkpoint(tmp_path / "runs" / "unet", net, net.config)
    assert ck.resolve_checkpoint(tmp_path / "runs" / "unet") == tmp_path / "runs" / "unet"
    assert ck.resolve_checkpoint(str(tmp_path / "runs" / "unet")) == tmp_path / "runs" / "unet"
    assert ck.resolve_checkpoint(digest[:8], search=[tmp_path / "runs"]) == tmp_path / "runs" / "unet"
    assert ck.resolve_checkpoint(digest, search=[tmp_path / "runs" / "unet"]) == tmp_path / "runs" / "unet"


def test_resolve_ambiguous_prefix_lists_matches(tmp_path, cache):
    a, b = "abcdef01" + "0" * 56, "abcdef02" + "1" * 56
    _fake(cache / a, a)
    _fake(cache / b, b)
    _fake(tmp_path / "elsewhere" / "same", a)  # the same hash twice is not ambiguous
    assert ck.resolve_checkpoint("abcdef01", search=[tmp_path / "elsewhere"]) == tmp_path / "elsewhere" / "same"
    with pytest.raises(
        DlaInputError, match=r"prefix is ambiguous, it matches 2: abcdef0100000000 .*; abcdef0211111111"
    ):
        ck.resolve_checkpoint("abcdef", search=[tmp_path / "elsewhere"])
    with pytest.raises(DlaInputError, match="not a checkpoint hash"):
        ck.resolve_checkpoint("abc")  # too short a prefix, and no such file


def test_resolve_missing_names_the_cache_and_the_fix(tmp_path, cache):
    _fake(cache / "broken", "not-a-hash")  # damaged checkpoints are skipped, not fatal
    with pytest.raises(DlaInputError) as info:
        ck.resolve_checkpoint("0123456789abcdef", search=[tmp_path / "runs"])
    msg = str(info.value)
    assert msg.startswith("checkpoint 0123456789abcdef: not found in ") and "\n" not in msg
    assert str(cache) in msg and str(tmp_path / "runs") in msg and "--checkpoint PATH" in msg
    assert f"copy the checkpoint folder into {cache}" in msg
