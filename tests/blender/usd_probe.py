"""Run by a Python that has `bpy` (not the project's): import a USD file into an empty Blender
scene the way a user would (`bpy.ops.wm.usd_import`, default options) and print one JSON object
on stdout: the objects, each point cloud's attributes, the scene's frame range and fps, world
positions and colours of the first points of each point cloud at the requested frames; with
--render, also one small Cycles frame with the attribute material docs/animate.md describes.

    python usd_probe.py FILE.usdc --frames 0 5 [--first 64] [--render OUT.png --size 128]
"""

import argparse
import json
import sys

import bpy
import mathutils


def attribute_material(objects) -> None:
    """docs/animate.md, "Blender": colour and opacity from the imported point attributes."""
    mat = bpy.data.materials.new("GaussianColor")
    mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    bsdf = nodes["Principled BSDF"]
    color, alpha = nodes.new("ShaderNodeAttribute"), nodes.new("ShaderNodeAttribute")
    color.attribute_name, alpha.attribute_name = "displayColor", "displayOpacity"
    links.new(color.outputs["Color"], bsdf.inputs["Base Color"])
    links.new(alpha.outputs["Fac"], bsdf.inputs["Alpha"])
    for ob in objects:
        ob.data.materials.clear()
        ob.data.materials.append(mat)


def render(path: str, size: int, clouds) -> None:
    scene = bpy.context.scene
    attribute_material(clouds)
    corners = [ob.matrix_world @ mathutils.Vector(c) for ob in clouds for c in ob.bound_box]
    lo = [min(v[i] for v in corners) for i in range(3)]
    hi = [max(v[i] for v in corners) for i in range(3)]
    centre = [(a + b) / 2 for a, b in zip(lo, hi)]
    extent = max(b - a for a, b in zip(lo, hi))
    cam_data = bpy.data.cameras.new("cam")
    cam = bpy.data.objects.new("cam", cam_data)
    scene.collection.objects.link(cam)
    cam.location = (centre[0], centre[1] - 2.2 * extent, centre[2])  # in front: the body faces -Y
    cam.rotation_euler = (1.5708, 0.0, 0.0)  # looking along +Y, +Z up
    scene.camera = cam
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.rotation_euler = (0.9, 0.0, 0.3)
    scene.collection.objects.link(sun)
    world = bpy.data.worlds.new("w")
    world.color = (0.05, 0.05, 0.05)
    scene.world = world
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 8
    scene.render.resolution_x = scene.render.resolution_y = size
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)


def main() -> None:
    argv = sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else sys.argv[1:]
    ap = argparse.ArgumentParser()
    ap.add_argument("usd")
    ap.add_argument("--frames", type=int, nargs="*", default=[])
    ap.add_argument("--first", type=int, default=64)
    ap.add_argument("--render")
    ap.add_argument("--size", type=int, default=128)
    args = ap.parse_args(argv)

    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.usd_import(filepath=args.usd)
    scene = bpy.context.scene
    clouds = [ob for ob in bpy.data.objects if ob.type == "POINTCLOUD"]
    report = {
        "blender": bpy.app.version_string,
        "objects": [{"name": ob.name, "type": ob.type} for ob in bpy.data.objects],
        "fps": scene.render.fps / scene.render.fps_base,
        "frame_start": scene.frame_start,
        "frame_end": scene.frame_end,
        "clouds": {},
    }
    for ob in clouds:
        attrs = ob.data.attributes
        entry = {"points": len(ob.data.points), "attributes": sorted(a.name for a in attrs), "frames": {}}
        if "displayColor" in attrs:
            entry["colors"] = [list(v.color)[:3] for v in attrs["displayColor"].data[: args.first]]
        report["clouds"][ob.name] = entry
    for frame in args.frames:
        scene.frame_set(frame)
        graph = bpy.context.evaluated_depsgraph_get()
        for ob in clouds:
            ev = ob.evaluated_get(graph)
            world = ev.matrix_world
            co = [list(world @ p.co) for p in ev.data.points[: args.first]]
            report["clouds"][ob.name]["frames"][str(frame)] = co
    if args.render:
        scene.frame_set(args.frames[0] if args.frames else scene.frame_start)
        render(args.render, args.size, clouds)
        report["render"] = args.render
    print("DLA-PROBE " + json.dumps(report))


main()
