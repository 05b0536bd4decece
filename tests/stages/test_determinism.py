"""The same inputs give the same avatar, bit for bit, whatever the thread count.

numba fixes its thread pool at import (NUMBA_NUM_THREADS; `numba.set_num_threads` can only go
lower), so every check runs in subprocesses launched with a known pool: the splatting kernels'
forward image and backward gradients at (torch, numba) = 1/1 and 2/2 threads in one process
(`set_num_threads` at run time), and a whole lift run twice with the same pool (2 threads:
NUMBA_NUM_THREADS / OMP_NUM_THREADS / MKL_NUM_THREADS), whose avatar.npz arrays (and float32
map) must be equal. Across thread counts the whole lift is not promised the same bits: it also
runs torch's, MKL's, oneDNN's and OpenBLAS's kernels, which split work by the thread count and
on some machines round differently where a chunk ends (a fresh clone on another 2-core machine
gave maps 1e-6 apart between 1 and 2 threads; on the development machine they were equal under
every CPU capability torch, MKL, oneDNN and OpenBLAS can be told to use).
docs/rendering.md "Determinism" lists the thread-count dependences that were removed.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

# Renders a scene whose Gaussians span many tiles (so that tiles of one Gaussian go to different
# workers) with 1 and with 2 threads and prints which outputs and gradients differ.
_KERNEL_SCRIPT = r"""
import json, math, sys
import numba, numpy as np, torch
from dlacli.render.splat import render_gaussians
from dlacli.types import Cameras, Gaussians

dtype = getattr(torch, sys.argv[1])
g = torch.Generator().manual_seed(3)
n, w, h = 3000, 120, 88  # 8 x 6 tiles, the last column and row partial
f64 = torch.float64
means = (torch.rand(n, 3, generator=g, dtype=f64) - 0.5) * torch.tensor([0.8, 0.5, 1.2], dtype=f64)
quats = torch.randn(n, 4, generator=g, dtype=f64)
scales = torch.exp(torch.empty(n, 3, dtype=f64).uniform_(math.log(0.005), math.log(0.12), generator=g))
opac = torch.empty(n, dtype=f64).uniform_(0.05, 1.0, generator=g)
sh = torch.randn(n, 4, 3, generator=g, dtype=f64) * 0.4
params = [t.to(dtype).requires_grad_(True) for t in (means, quats, scales, opac, sh)]
c2ws = []
for a in (0.3, 2.1, 4.0):  # three cameras around the cloud, z up
    eye = np.array([2.5 * math.sin(a), -2.5 * math.cos(a), 0.4])
    fwd = -eye / np.linalg.norm(eye)
    right = np.cross(fwd, [0.0, 0.0, 1.0]); right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(right, fwd), -fwd, eye
    c2ws.append(c2w)
cams = Cameras.from_c2w_opengl(np.stack(c2ws), 110.0, 115.0, 61.0, 43.0, w, h)
cams = Cameras(cams.viewmats.to(dtype), cams.Ks.to(dtype), w, h)
weights = torch.randn((3, h, w, 5), generator=torch.Generator().manual_seed(4), dtype=f64).to(dtype)

def run(threads):
    torch.set_num_threads(threads)
    numba.set_num_threads(threads)
    out = render_gaussians(Gaussians(*params), cams)
    img = torch.cat([out.rgb, out.alpha[..., None], out.depth[..., None]], -1)
    grads = torch.autograd.grad((img * weights).sum(), params)
    return [img.detach().numpy()] + [t.numpy() for t in grads]

one, two = run(1), run(2)
names = ["image", "means", "quats", "scales", "opacities", "sh"]
print(json.dumps({
    "differ": [k for k, a, b in zip(names, one, two) if not np.array_equal(a, b)],
    "nonzero": [k for k, a in zip(names, one) if not np.abs(a).max() > 0],
}))
"""


# A lift as `dla lift` runs it (stages.lift.lift, then io.avatar.write_avatar), which also saves
# the float32 map before the writer stores it as float16.
_LIFT_SCRIPT = r"""
import sys
import numpy as np
from dlacli.io.avatar import write_avatar
from dlacli.io.views import read_views
from dlacli.stages.lift.methods.unproject import UnprojectConfig
from dlacli.stages.lift.unproject import lift

views, out, n, steps = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
# w_smooth: the roughness term (the default for dreamed views) takes part in the check too
result = lift(read_views(views), UnprojectConfig(steps=steps, gaussians=n, resolution=64, w_smooth=0.1))
np.save(out + ".z32.npy", result.avatar.z)
write_avatar(result.avatar, out)
"""


def _env(threads: int) -> dict:
    return dict(os.environ, NUMBA_NUM_THREADS=str(threads), OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_splat_forward_and_backward_do_not_depend_on_threads(dtype):
    # float64 is the sensitive case: with one gradient slab per worker summed at the end, the
    # Gaussians' gradients differed in the last bits between 1 and 2 threads (float32 storage
    # hid most of it, not all)
    r = subprocess.run([sys.executable, "-c", _KERNEL_SCRIPT, dtype], env=_env(2), capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["nonzero"] == []  # the scene renders and every gradient is non-trivial
    assert res["differ"] == []


def test_lift_writes_the_same_avatar_twice_with_the_same_threads(subject, tmp_path):
    # 40,030 Gaussians: above torch's 32,768-element grain, so element-wise ops on them are split
    # over the threads, in chunks of 20,015 at 2 threads, which end off the vector lanes' grid;
    # two processes at once, so that a race between workers (an output with two writers, a read
    # of memory nobody wrote) would show as a difference
    procs = {}
    for run in (1, 2):
        out = tmp_path / f"r{run}" / "avatar.npz"
        out.parent.mkdir()
        cmd = [sys.executable, "-c", _LIFT_SCRIPT, str(subject), str(out), "40030", "16"]
        procs[run] = (
            out,
            subprocess.Popen(cmd, env=_env(2), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True),
        )
    arrays, maps = {}, {}
    for run, (out, proc) in procs.items():
        _, err = proc.communicate()
        assert proc.returncode == 0, err
        with np.load(out) as npz:
            arrays[run] = {k: npz[k] for k in npz.files}
        maps[run] = np.load(str(out) + ".z32.npy")
    assert maps[1].dtype == np.float32 and np.array_equal(maps[1], maps[2])  # before float16 storage
    one, two = arrays[1], arrays[2]
    assert sorted(one) == sorted(two)
    assert one["z"].dtype == two["z"].dtype and np.array_equal(one["z"], two["z"])
    for key in one:  # extra included: the loss history is reduced in a fixed order (lift.fixed_order_mean)
        assert np.array_equal(one[key], two[key]), key
    assert isinstance(json.loads(str(one["extra"]))["lift"]["final_loss"], float)
