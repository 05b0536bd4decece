"""The UV encoder: shapes and gradients, farthest point sampling against a plain-Python reference,
the KL term and the reparameterised sample, which inputs the output depends on (body vs learned
queries, the opacity filter, batch items), parameter counts, save/load."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from dlacli.avatar.checkpoint import load_checkpoint, save_checkpoint
from dlacli.errors import DlaInputError
from dlacli.nn.encoder import (
    PRESETS,
    EncoderConfig,
    UVEncoder,
    farthest_point_sample,
    fourier_features,
    kl_divergence,
    preset,
    sample_latent,
)


def tiny(**changes) -> EncoderConfig:
    return dataclasses.replace(preset("tiny"), **changes)


def inputs(cfg: EncoderConfig, b: int = 2, n: int = 600, seed: int = 0, transparent: int = 0):
    """Random Gaussians; the last `transparent` of each item have opacity 0.01 (below the threshold),
    the others opacities in (0.2, 1)."""
    g = torch.Generator().manual_seed(seed)
    r = cfg.uv_resolution
    params = torch.randn(b, n, cfg.gaussian_channels, generator=g)
    features = torch.randn(b, n, cfg.feature_channels, generator=g)
    positions = torch.rand(b, n, 3, generator=g) * 2.0 - 1.0
    opacities = 0.2 + 0.8 * torch.rand(b, n, generator=g)
    if transparent:
        opacities[:, n - transparent :] = 0.01
    uv = torch.rand(b, 3, r, r, generator=g) * 2.0 - 1.0
    return params, features, positions, opacities, uv


def make(cfg: EncoderConfig, seed: int = 0) -> UVEncoder:
    torch.manual_seed(seed)
    return UVEncoder(cfg).eval()


# ------------------------------------------------------------------------------------ shapes, gradients


@pytest.mark.parametrize("query", ["body", "learned"])
def test_shapes_and_finite_gradients(query):
    cfg = tiny(query=query)
    net = make(cfg)
    params, features, positions, opacities, uv = inputs(cfg)
    for t in (params, features, positions, uv):
        t.requires_grad_(True)
    mean, logvar = net(params, features, positions, opacities, uv)
    shape = (2, cfg.latent_channels, cfg.uv_resolution, cfg.uv_resolution)
    assert mean.shape == shape and logvar.shape == shape
    assert mean.dtype == logvar.dtype == torch.float32
    (mean.square().mean() + kl_divergence(mean, logvar)).backward()
    for name, p in net.named_parameters():
        assert p.grad is not None, name
        assert torch.isfinite(p.grad).all(), name
        assert p.grad.abs().max() > 0, name  # every parameter is on the path to Z
    carried = (params, features, positions) + ((uv,) if query == "body" else ())
    for t in carried:
        assert t.grad is not None and torch.isfinite(t.grad).all()
        assert t.grad.abs().max() > 0
    if query == "learned":
        assert uv.grad is None


def test_fourier_features_layout():
    x = torch.tensor([[0.25, -0.5, 1.0]], dtype=torch.float64)
    out = fourier_features(x, 2)
    expect = [0.25, -0.5, 1.0]
    expect += [math.sin(f * math.pi * v) for v in (0.25, -0.5, 1.0) for f in (1, 2)]
    expect += [math.cos(f * math.pi * v) for v in (0.25, -0.5, 1.0) for f in (1, 2)]
    torch.testing.assert_close(out[0], torch.tensor(expect, dtype=torch.float64), rtol=0, atol=1e-15)
    assert fourier_features(x, 0) is x


# ------------------------------------------------------------------------------------ farthest point sampling


def fps_reference(points: np.ndarray, k: int, valid: np.ndarray | None = None, start: int | None = None) -> list[int]:
    """Greedy FPS written as plain loops: each step recomputes every candidate's distance to the
    whole selected set; ties go to the lowest index; fewer candidates than k repeat in order."""
    n = len(points)
    cand = [i for i in range(n) if valid is None or valid[i]] or list(range(n))
    first = cand[0] if start is None else start
    if first not in cand:
        cand = sorted(cand + [first])
    chosen = [first]
    while len(chosen) < min(k, len(cand)):
        best_i, best_d = -1, -1.0
        for i in cand:
            if i in chosen:
                continue
            d = min(sum((float(points[i][c]) - float(points[j][c])) ** 2 for c in range(3)) for j in chosen)
            if d > best_d:
                best_i, best_d = i, d
        chosen.append(best_i)
    return [chosen[j % len(chosen)] for j in range(k)]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fps_matches_reference(dtype):
    rng = np.random.default_rng(3)
    b, n, k = 3, 40, 12
    pts = rng.normal(size=(b, n, 3))
    valid = rng.random((b, n)) < 0.6
    start = np.array([int(np.flatnonzero(v)[-1]) for v in valid])
    t = torch.tensor(pts, dtype=dtype)
    pts_t = t.numpy().astype(np.float64)  # the points as the sampler sees them
    got = farthest_point_sample(t, k, torch.tensor(valid))
    assert got.dtype == torch.long and got.shape == (b, k)
    for i in range(b):
        assert got[i].tolist() == fps_reference(pts_t[i], k, valid[i])
        assert valid[i][got[i].numpy()].all()
    got = farthest_point_sample(t, k, torch.tensor(valid), torch.tensor(start))
    for i in range(b):
        assert got[i].tolist() == fps_reference(pts_t[i], k, valid[i], int(start[i]))
    got = farthest_point_sample(t, k)  # no mask: all points
    for i in range(b):
        assert got[i].tolist() == fps_reference(pts_t[i], k)


def test_fps_ties_go_to_the_lowest_index():
    # a unit square's corners and its centre: from corner 0 the opposite corner 2 is farthest; then
    # corners 1 and 3 tie (distance 1 to both chosen corners) and 1 wins; then 3; then the centre
    square = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0]]])
    assert farthest_point_sample(square, 5).tolist() == [[0, 2, 1, 3, 4]]
    assert fps_reference(square[0].numpy(), 5) == [0, 2, 1, 3, 4]


def test_fps_few_valid_repeat_and_none_valid_uses_all():
    rng = np.random.default_rng(5)
    pts = torch.tensor(rng.normal(size=(2, 30, 3)), dtype=torch.float32)
    valid = torch.zeros(2, 30, dtype=torch.bool)
    valid[0, [4, 11, 25]] = True  # item 0: 3 valid points for k = 8; item 1: none
    got = farthest_point_sample(pts, 8, valid)
    first = got[0, :3].tolist()
    assert sorted(first) == [4, 11, 25] and first[0] == 4
    assert got[0].tolist() == [first[j % 3] for j in range(8)]
    assert got[1].tolist() == fps_reference(pts[1].numpy(), 8)  # no valid point: all are candidates
    assert len(set(got[1].tolist())) == 8
    # coincident points: duplicates of chosen points are still picked before any repeat
    dup = torch.zeros(1, 4, 3)
    assert sorted(farthest_point_sample(dup, 4)[0].tolist()) == [0, 1, 2, 3]


def test_fps_deterministic_and_without_gradient():
    pts = torch.randn(2, 50, 3, generator=torch.Generator().manual_seed(1), requires_grad=True)
    a = farthest_point_sample(pts, 16)
    b = farthest_point_sample(pts.detach().clone(), 16)
    assert torch.equal(a, b) and not a.requires_grad


# ------------------------------------------------------------------------------------ KL and the sample


def test_kl_analytic_values():
    zero = torch.zeros(2, 3, 4, 4)
    assert kl_divergence(zero, zero).item() == 0.0
    assert kl_divergence(torch.ones_like(zero), zero).item() == pytest.approx(0.5, rel=1e-7)
    # KL(N(0, 2) || N(0, 1)) = (2 - 1 - ln 2) / 2, averaged with zeros over half the elements
    logvar = torch.cat([torch.full((1, 8), math.log(2.0)), torch.zeros(1, 8)], dim=1)
    assert kl_divergence(torch.zeros(1, 16), logvar).item() == pytest.approx(0.25 * (1 - math.log(2.0)), rel=1e-6)


def test_kl_matches_torch_distributions():
    g = torch.Generator().manual_seed(2)
    mean = torch.randn(2, 4, 5, 5, generator=g, dtype=torch.float64)
    logvar = torch.randn(2, 4, 5, 5, generator=g, dtype=torch.float64)
    ref = torch.distributions.kl_divergence(
        torch.distributions.Normal(mean, torch.exp(0.5 * logvar)), torch.distributions.Normal(0.0, 1.0)
    ).mean()
    torch.testing.assert_close(kl_divergence(mean, logvar), ref, rtol=1e-12, atol=0)


def test_sample_latent_seeded_and_moments():
    mean = torch.full((4, 64, 32, 32), 3.0)
    logvar = torch.full_like(mean, math.log(4.0))  # std 2
    a = sample_latent(mean, logvar, torch.Generator().manual_seed(7))
    b = sample_latent(mean, logvar, torch.Generator().manual_seed(7))
    c = sample_latent(mean, logvar, torch.Generator().manual_seed(8))
    assert torch.equal(a, b) and not torch.equal(a, c)
    n = a.numel()  # 262,144 draws: the sample mean is within 5 standard errors, the std within 5 of its own
    assert abs(a.mean().item() - 3.0) < 5 * 2.0 / math.sqrt(n)
    assert abs(a.std().item() - 2.0) < 5 * 2.0 / math.sqrt(2 * n)
    # logvar -> -inf: the sample is the mean (std exp(-50) ~ 2e-22)
    m = torch.randn(3, 5, generator=torch.Generator().manual_seed(0))
    z = sample_latent(m, torch.full_like(m, -100.0), torch.Generator().manual_seed(1))
    torch.testing.assert_close(z, m, rtol=0, atol=1e-20)


# ------------------------------------------------------------------------------------ what the output depends on


def test_body_query_depends_on_uv_positions_learned_does_not():
    # logvar_init None: the log-variance head random like the mean's (the presets start it constant)
    body, learned = make(tiny(query="body", logvar_init=None)), make(tiny(query="learned"))
    params, features, positions, opacities, uv = inputs(tiny())
    uv2 = uv + 0.3
    with torch.no_grad():
        a, la = body(params, features, positions, opacities, uv)
        b, lb = body(params, features, positions, opacities, uv2)
        assert not torch.allclose(a, b) and not torch.allclose(la, lb)
        c, _ = learned(params, features, positions, opacities, uv)
        d, _ = learned(params, features, positions, opacities, uv2)
        e, _ = learned(params, features, positions, opacities, None)
    assert torch.equal(c, d) and torch.equal(c, e)


def test_transparent_gaussians_do_not_affect_the_output():
    cfg = tiny()
    net = make(cfg)
    params, features, positions, opacities, uv = inputs(cfg, n=600, transparent=200)  # 400 pass >= P = 256
    with torch.no_grad():
        ref = net(params, features, positions, opacities, uv)
        p2, f2, x2 = params.clone(), features.clone(), positions.clone()
        j = 550  # transparent: far away, other parameters and features
        x2[:, j] = torch.tensor([50.0, -40.0, 30.0])
        p2[:, j] += 5.0
        f2[:, j] -= 5.0
        moved = net(p2, f2, x2, opacities, uv)
        assert all(torch.equal(a, b) for a, b in zip(ref, moved))
        x3 = positions.clone()
        x3[:, 10] = torch.tensor([50.0, -40.0, 30.0])  # an opaque one moved far away is sampled and matters
        assert not torch.allclose(ref[0], net(params, features, x3, opacities, uv)[0])


def test_select_starts_at_the_most_opaque_and_falls_back_to_the_most_opaque():
    cfg = tiny()  # P = 256
    net = make(cfg)
    _, _, positions, opacities, _ = inputs(cfg, n=600, transparent=200)
    idx = net.select(positions, opacities)
    assert idx.shape == (2, cfg.points)
    assert torch.equal(idx[:, 0], opacities.argmax(dim=1))
    assert (opacities.gather(1, idx) > cfg.opacity_threshold).all()
    assert all(len(set(row.tolist())) == cfg.points for row in idx)
    # only 100 pass: the candidates are the 256 most opaque (all distinct opacities), each taken once
    op = torch.rand(2, 400, generator=torch.Generator().manual_seed(4)) * 0.04
    op[:, :100] += 0.5
    idx = net.select(positions[:, :400], op)
    for i in range(2):
        top = set(np.argsort(-op[i].numpy())[: cfg.points].tolist())
        assert set(idx[i].tolist()) == top
    # a generator draws the start among the candidates instead
    a = net.select(positions, opacities, torch.Generator().manual_seed(3))
    b = net.select(positions, opacities, torch.Generator().manual_seed(3))
    assert torch.equal(a, b) and (opacities.gather(1, a) > cfg.opacity_threshold).all()


def test_batch_items_are_independent(tol):
    cfg = tiny(logvar_init=None)  # both halves of the head depend on the inputs
    net = make(cfg)
    first = inputs(cfg, seed=0)
    other = inputs(cfg, seed=1)
    mixed = [torch.cat([a[:1], b[1:]]) for a, b in zip(first, other)]
    with torch.no_grad():
        ref = net(*first)
        out = net(*mixed)
    for a, b in zip(ref, out):
        # same arithmetic on item 0 in both calls; allow a few roundings per reduction of width terms
        torch.testing.assert_close(b[0], a[0], rtol=0, atol=tol(torch.float32, a[0].abs().max(), ops=cfg.width))
        assert not torch.allclose(b[1], a[1])


# ------------------------------------------------------------------------------------ presets, checkpoints


def count(cfg: EncoderConfig) -> int:
    with torch.device("meta"):
        return sum(p.numel() for p in UVEncoder(cfg).parameters())


def test_parameter_counts():
    counts = {name: count(preset(name)) for name in ("tiny", "small", "paper")}
    assert counts["tiny"] < counts["small"] < counts["paper"]
    assert abs(counts["paper"] - 19e6) <= 0.05 * 19e6  # the paper's encoder: 19 M
    p = preset("paper")
    assert (p.uv_resolution, p.latent_channels, p.points) == (64, 256, 2048)


def test_presets_and_config_validation():
    assert set(PRESETS) == {"tiny", "small", "paper"}
    a = preset("tiny")
    a.width = 8
    assert preset("tiny").width == 64  # preset() hands out copies
    with pytest.raises(DlaInputError, match="--preset"):
        preset("huge")
    with pytest.raises(ValueError, match="query"):
        EncoderConfig(query="random")
    with pytest.raises(ValueError, match="heads"):
        EncoderConfig(width=100, heads=16)


@pytest.mark.parametrize("query", ["body", "learned"])
def test_save_load_keeps_outputs(tmp_path, query):
    cfg = tiny(query=query)
    net = make(cfg, seed=5)
    data = inputs(cfg)
    save_checkpoint(tmp_path / "enc", net, cfg, step=3)
    loaded = load_checkpoint(tmp_path / "enc")
    assert isinstance(loaded.module, UVEncoder) and loaded.config == cfg and loaded.step == 3
    with torch.no_grad():
        for a, b in zip(net(*data), loaded.module(*data)):
            assert torch.equal(a, b)


# ------------------------------------------------------------------------ issue 22's diagnosis, fixed


def test_logvar_starts_at_its_init_value_everywhere():
    """The presets start Z's posterior narrow (std e^(-5/2) ~ 0.08, below the ~0.3 spread of the
    mean): the head's log-variance half is zero weights plus a constant bias."""
    cfg = tiny()
    assert cfg.logvar_init == -5.0
    with torch.no_grad():
        mean, logvar = make(cfg)(*inputs(cfg, b=1))
    assert torch.equal(logvar, torch.full_like(logvar, -5.0))
    assert float(mean.std()) > 0.05  # the mean half keeps its random init


def test_locality_lets_a_texel_ignore_far_gaussians():
    """With locality 0.05 m, a texel reads the Gaussians near its body point: changing a
    Gaussian 1 m away barely moves it, changing one 1 cm away does; with locality off (older
    checkpoints) the far one moves it as much as any."""
    n, r = 64, 4
    for locality, far_matters in ((0.05, False), (0.0, True)):
        cfg = tiny(points=n, uv_resolution=r, locality=locality)
        params, features, positions, opacities, _ = inputs(cfg, b=1, n=n)
        positions[0, :] = torch.tensor([5.0, 5.0, 5.0]) + torch.rand(n, 3)  # the rest far from everything
        uv = torch.zeros(1, 3, r, r) + torch.tensor([2.0, 2.0, 2.0])[None, :, None, None]
        uv[0, :, 0, 0] = 0.0  # texel (0, 0) at the origin
        positions[0, 0] = torch.tensor([0.01, 0.0, 0.0])  # near it
        positions[0, 1] = torch.tensor([1.0, 0.0, 0.0])  # far from it (but nearer than the rest)
        enc = make(cfg)
        with torch.no_grad():
            base = enc(params, features, positions, opacities, uv)[0][0, :, 0, 0]
            moved = []
            for i in (0, 1):
                p = params.clone()
                p[0, i] += 3.0
                moved.append(float((enc(p, features, positions, opacities, uv)[0][0, :, 0, 0] - base).abs().max()))
        near, far = moved
        assert near > 1e-3, locality
        if far_matters:
            assert far > 0.1 * near, (near, far)
        else:
            assert far < 1e-6 * max(near, 1.0), (near, far)


def test_the_person_masks_keep_background_out_of_the_keys():
    """An untrained U-Net's opacity is ~0.5 everywhere; with the input masks the encoder's keys
    are foreground pixel Gaussians only (nn/learned.pixel_mask keeps the Gaussians' order)."""
    from dlacli.nn.learned import pixel_mask

    b, v, s, h = 1, 4, 16, 8
    mask = torch.zeros(b, v, 1, s, s)
    mask[:, :, :, 4:12, 6:10] = 1.0  # a person in the middle of every view
    flat = pixel_mask(mask, v * h * h)
    assert flat.shape == (b, v * h * h)
    expect = torch.zeros(v, h, h)
    expect[:, 2:6, 3:5] = 1.0
    assert torch.equal(flat[0], expect.flatten())
    cfg = tiny(points=16)
    enc = make(cfg)
    opacities = torch.full((b, v * h * h), 0.5)
    positions = torch.rand(b, v * h * h, 3)
    keys = enc.select(positions, opacities * flat)
    assert bool((flat[0, keys[0]] > 0).all())
    assert not bool((flat[0, enc.select(positions, opacities)[0]] > 0).all())  # without: background too


def test_checkpoints_from_before_locality_load_as_they_were(tmp_path):
    import json

    cfg = tiny()
    save_checkpoint(tmp_path / "ck", make(cfg), cfg)
    rec = json.loads((tmp_path / "ck" / "config.json").read_text())
    for key in ("locality", "logvar_init"):
        del rec["config"][key]
    from dlacli.avatar.checkpoint import content_hash

    weights = (tmp_path / "ck" / "model.safetensors").read_bytes()
    rec["hash"] = content_hash(rec["class"], rec["config_class"], rec["config"], weights)
    (tmp_path / "ck" / "config.json").write_text(json.dumps(rec))
    loaded = load_checkpoint(tmp_path / "ck")
    assert loaded.config.locality == 0.0 and loaded.config.logvar_init is None
