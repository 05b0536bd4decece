"""MovingRig against PointRig (the oracle: anny's own 104-bone kinematics) for random poses of the
moving bones, with the phenotype at and away from the reference, and its gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dlacli.body.keypoints import PointRig
from dlacli.body.moving_rig import MovingRig

BONES = ("spine03", "upperarm01.L", "lowerarm01.L", "clavicle.R", "upperleg01.R", "lowerleg01.R", "neck02", "head")
KEYS = ("height", "weight")


@pytest.fixture(scope="module")
def rigs():
    rig = PointRig(free_keys=KEYS)
    return rig, MovingRig(rig, BONES, num_points=17)


def _pose(rig, seed, s=4):
    g = torch.Generator().manual_seed(seed)
    rot = 0.6 * torch.randn(s, len(BONES), 3, generator=g)
    rr = 0.8 * torch.randn(s, 3, generator=g)
    rt = torch.randn(s, 3, generator=g)
    full = torch.zeros(s, rig.model.num_bones, 3)
    full[:, [rig.model.bone_index(b) for b in BONES]] = rot
    return rot, rr, rt, full


def test_matches_point_rig(rigs):
    rig, moving = rigs
    rot, rr, rt, full = _pose(rig, 1)
    with torch.no_grad():
        want = rig(None, full, rr, rt, keypoints_only=True)[0]  # [S, 17, 3]
        got = moving(None, rot, rr, rt)
    # float32 chains of ~10 4x4 products on metre-sized values
    np.testing.assert_allclose(got.numpy(), want.numpy(), atol=2e-5)


def test_linearised_phenotype():
    """Away from the reference phenotype both rigs are linearisations: each is compared with the
    exact points (a rig linearised at that phenotype); the moving rig's error stays at the point
    rig's size (a few mm for a 0.2 step in two keys)."""
    rig = PointRig(free_keys=KEYS)
    moving = MovingRig(rig, BONES, num_points=17)
    rot, rr, rt, full = _pose(rig, 1)
    p = torch.tensor([0.3, 0.7])
    exact_rig = PointRig(free_keys=KEYS)
    exact_rig.linearise({"height": 0.3, "weight": 0.7})
    with torch.no_grad():
        exact = exact_rig(None, full, rr, rt, keypoints_only=True)[0].numpy()
        err_point = np.abs(rig(p, full, rr, rt, keypoints_only=True)[0].numpy() - exact).max()
        err_moving = np.abs(moving(p, rot, rr, rt).numpy() - exact).max()
    assert err_moving <= max(2.0 * err_point, 1e-3), (err_moving, err_point)
    moving.linearise({"height": 0.3, "weight": 0.7})
    with torch.no_grad():
        np.testing.assert_allclose(moving(None, rot, rr, rt).numpy(), exact, atol=2e-5)


def test_gradients_match(rigs):
    rig, moving = rigs
    rot, rr, rt, _ = _pose(rig, 2, s=2)
    ids = [rig.model.bone_index(b) for b in BONES]
    weights = torch.randn(2, 17, 3, generator=torch.Generator().manual_seed(3))

    def grads(fn):
        r = rot.clone().requires_grad_(True)
        (fn(r) * weights).sum().backward()
        return r.grad.numpy()

    def full_fn(r):
        full = torch.zeros(2, rig.model.num_bones, 3).index_copy(1, torch.tensor(ids), r)
        return rig(None, full, rr, rt, keypoints_only=True)[0]

    np.testing.assert_allclose(grads(lambda r: moving(None, r, rr, rt)), grads(full_fn), atol=1e-4)
