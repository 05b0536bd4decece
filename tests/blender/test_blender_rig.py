"""The rigged USD in Blender (bpy, its own Python: fixture `bpy_python`): armature, skinned mesh,
colours, animation, Python posing, and a small Cycles render.

Blender's deformation is checked against UsdSkel's own skinning of the same file (pxr, in this
Python), and Python posing against anny's weights: vertices with no weight on the posed bone's
subtree stay put."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
from PIL import Image

from dlacli.body.builtin_motions import builtin_motion
from dlacli.body.model import get_body_model
from dlacli.io.usd_rig import joint_token
from dlacli.stages.rig import write_rigged_usd
from dlacli.types import Avatar, BodyParams, Motion

R = 64
RED, BLUE = (0.8, 0.1, 0.1), (0.1, 0.2, 0.8)
POSED_BONE = "lowerarm01.L"
RENDER_SIZE = 160

SCRIPT = r"""
import json, sys
import bpy
import numpy as np
from mathutils import Vector

path, out, mode = sys.argv[sys.argv.index("--") + 1:][:3]
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.wm.usd_import(filepath=path)
scene = bpy.context.scene
arm = next(o for o in scene.objects if o.type == "ARMATURE")
body = next(o for o in scene.objects if o.type == "MESH")

def world_vertices():
    bpy.context.view_layer.update()
    dg = bpy.context.evaluated_depsgraph_get()
    ev = body.evaluated_get(dg)
    me = ev.to_mesh()
    co = np.empty(len(me.vertices) * 3, np.float64)
    me.vertices.foreach_get("co", co)
    ev.to_mesh_clear()
    mw = np.array(ev.matrix_world)
    return co.reshape(-1, 3) @ mw[:3, :3].T + mw[:3, 3]

report = {
    "bones": [b.name for b in arm.data.bones],
    "modifiers": [[m.type, m.object.name if getattr(m, "object", None) else None] for m in body.modifiers],
    "armature": arm.name,
    "vertex_groups": len(body.vertex_groups),
    "color_attributes": [c.name for c in body.data.color_attributes],
    "uv_layers": [u.name for u in body.data.uv_layers],
    "vertices": len(body.data.vertices),
}
images = []
for slot in body.material_slots:
    tree = slot.material.node_tree
    for node in tree.nodes:
        if node.type == "BSDF_PRINCIPLED":
            link = node.inputs["Base Color"].links
            report["base_color_from"] = link[0].from_node.type if link else None
        if node.type == "TEX_IMAGE" and node.image is not None:
            images.append([list(node.image.size), node.image.colorspace_settings.name])
report["images"] = images
if mode == "animated":
    report["has_action"] = bool(arm.animation_data and arm.animation_data.action)
    last = int(sys.argv[sys.argv.index("--") + 4])
    scene.frame_set(0)
    np.save(out + "/frame_first.npy", world_vertices())
    scene.frame_set(last)
    np.save(out + "/frame_last.npy", world_vertices())
    scene.frame_set(0)
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    scene.collection.objects.link(cam)
    cam.data.lens = 50
    cam.location = (0.0, -3.5, -0.05)
    cam.rotation_euler = (Vector((0.0, 0.0, -0.05)) - cam.location).to_track_quat("-Z", "Y").to_euler()
    scene.camera = cam
    scene.world = bpy.data.worlds.new("world")
    scene.world.use_nodes = True
    scene.world.node_tree.nodes["Background"].inputs[0].default_value = (1.0, 1.0, 1.0, 1.0)
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 8
    scene.render.resolution_x = scene.render.resolution_y = int(sys.argv[sys.argv.index("--") + 5])
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = True
    scene.render.filepath = out + "/render.png"
    bpy.ops.render.render(write_still=True)
else:
    before = world_vertices()
    bone = arm.pose.bones[sys.argv[sys.argv.index("--") + 4]]
    bone.rotation_mode = "XYZ"
    bone.rotation_euler = (1.0, 0.3, 0.0)
    after = world_vertices()
    np.save(out + "/rest.npy", before)
    np.save(out + "/posed.npy", after)
print("DLA_JSON " + json.dumps(report))
"""


def two_colour_avatar() -> Avatar:
    """Red on the left half of the UV layout (u < 0.5), blue on the right; no offsets."""
    z = np.zeros((14, R, R), np.float32)
    z[0] = 4.0
    u = (np.arange(R) + 0.5) / R
    for c in range(3):
        z[1 + c] = np.where(u[None, :] < 0.5, RED[c], BLUE[c])
    z[7] = 1.0
    z[11:14] = -0.5
    return Avatar(z=z, encoder="unproject", decoder="identity", body=BodyParams(), uv_layout="anny")


def short_walk() -> Motion:
    m = builtin_motion("walk")
    sel = slice(0, 60, 20)  # 3 frames
    return Motion(list(m.bone_labels), m.rotations[sel], m.root_rotation[sel], m.root_translation[sel], m.fps)


def run_blender(bpy_python, tmp_path: Path, usd: Path, mode: str, *extra) -> dict:
    script = tmp_path / "blender_rig.py"
    script.write_text(SCRIPT)
    out = tmp_path / mode
    out.mkdir()
    proc = subprocess.run(
        [str(bpy_python), str(script), "--", str(usd), str(out), mode, *map(str, extra)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    lines = [line for line in proc.stdout.splitlines() if line.startswith("DLA_JSON ")]
    assert proc.returncode == 0 and lines, proc.stdout[-2000:] + proc.stderr[-2000:]
    return json.loads(lines[-1][len("DLA_JSON ") :])


def usd_skinned(path: Path, t: float) -> np.ndarray:
    """UsdSkel's own skinning of the mesh at time t (the oracle for Blender's armature)."""
    from pxr import Usd, UsdGeom, UsdSkel, Vt

    stage = Usd.Stage.Open(str(path))
    cache = UsdSkel.Cache()
    root = UsdSkel.Root(stage.GetPrimAtPath("/Avatar"))
    cache.Populate(root, Usd.PrimDefaultPredicate)
    (binding,) = cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate)
    (target,) = binding.GetSkinningTargets()
    points = Vt.Vec3fArray(UsdGeom.Mesh(target.GetPrim()).GetPointsAttr().Get())
    xforms = cache.GetSkelQuery(binding.GetSkeleton()).ComputeSkinningTransforms(Usd.TimeCode(t))
    assert target.ComputeSkinnedPoints(xforms, points, Usd.TimeCode(t))
    return np.asarray(points, np.float64)


def test_blender_imports_animates_and_renders_the_rig(bpy_python, tmp_path):
    model = get_body_model()
    motion = short_walk()
    usd = tmp_path / "walk.usdc"
    write_rigged_usd(two_colour_avatar(), usd, motion=motion)
    rep = run_blender(bpy_python, tmp_path, usd, "animated", motion.num_frames - 1, RENDER_SIZE)

    assert len(rep["bones"]) == model.num_bones
    assert set(rep["bones"]) == {joint_token(b) for b in model.bone_labels}
    assert ["ARMATURE", rep["armature"]] in rep["modifiers"]
    assert rep["vertex_groups"] == model.num_bones and rep["vertices"] == model.num_vertices
    assert "displayColor" in rep["color_attributes"] and rep["uv_layers"]
    assert rep["base_color_from"] == "TEX_IMAGE" and rep["images"] == [[[R, R], "sRGB"]]
    assert rep["has_action"]

    first, last = np.load(tmp_path / "animated" / "frame_first.npy"), np.load(tmp_path / "animated" / "frame_last.npy")
    assert np.abs(last - first).max() > 0.05  # the walk moves the mesh
    # Blender's armature deformation = UsdSkel's skinning (float32 both; measured ~1e-6 m)
    for t, verts in ((0, first), (motion.num_frames - 1, last)):
        np.testing.assert_allclose(verts, usd_skinned(usd, t), atol=2e-5)

    # a default-material Cycles render shows the texture's two colours on the body
    rgba = np.asarray(Image.open(tmp_path / "animated" / "render.png").convert("RGBA"), np.float64) / 255
    assert rgba.shape == (RENDER_SIZE, RENDER_SIZE, 4)
    body = rgba[..., 3] > 0.5
    assert body.sum() > 0.03 * RENDER_SIZE**2
    rgb = rgba[body, :3]
    reddish = (rgb[:, 0] > rgb[:, 2] + 0.1).sum()
    bluish = (rgb[:, 2] > rgb[:, 0] + 0.1).sum()
    assert reddish > 0.05 * body.sum() and bluish > 0.05 * body.sum(), (reddish, bluish, body.sum())


def test_posing_a_bone_in_blender_moves_its_vertices_only(bpy_python, tmp_path):
    model = get_body_model()
    usd = tmp_path / "rest.usdc"
    write_rigged_usd(two_colour_avatar(), usd)
    run_blender(bpy_python, tmp_path, usd, "posed", joint_token(POSED_BONE))
    rest, posed = np.load(tmp_path / "posed" / "rest.npy"), np.load(tmp_path / "posed" / "posed.npy")
    # at rest Blender shows the file's mesh as written
    np.testing.assert_allclose(rest, usd_skinned(usd, 0.0), atol=2e-5)
    # weight of each vertex on the posed bone and its descendants (anny's weights)
    j = model.bone_index(POSED_BONE)
    subtree = {j}
    for c, p in enumerate(model.bone_parents):
        if p in subtree:
            subtree.add(c)
    idx, w = model.vertex_bone_weights
    on = (w * np.isin(idx, list(subtree))).sum(axis=1)
    moved = np.linalg.norm(posed - rest, axis=1)
    assert moved[on == 0].max() < 1e-6
    assert np.median(moved[on > 0.9]) > 0.02  # the forearm and hand turn ~1 rad about the elbow
