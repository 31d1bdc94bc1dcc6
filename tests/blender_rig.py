"""Run inside headless Blender by tests/test_rig.py: opens a .glb and a .bvh of `nmjax rig` with
Blender's own importers and writes what Blender made of them as JSON.

    blender -b --factory-startup --python tests/blender_rig.py -- RIG.glb RIG.bvh FPS OUT.json \
        FRAME [FRAME ...]

The scene's frame rate is set to the file's before importing: glTF keys are times, which
Blender's importer turns into frames at the scene's rate. Written (coordinates in Blender's
axes, +Z up, world space):

- "armatures": the armature objects' names; "meshes": every mesh object with its parent and its
  modifiers (type and the object an armature modifier deforms with);
- "action": the armature's action, its name, first and last frame;
- "rest": the mesh's vertices as imported (undeformed); "posed": {frame: its vertices deformed
  by the armature at that scene frame, evaluated by Blender's dependency graph};
- "bvh": the BVH's armature: its bones and its action's first and last frame.
"""

import json
import sys

import bpy


def vertices(obj) -> list:
    """World coordinates of an object's (evaluated) mesh vertices."""
    matrix = obj.matrix_world
    return [list(matrix @ v.co) for v in obj.data.vertices]


def main(argv: list[str]) -> None:
    glb, bvh, fps, out, *frames = argv
    fps = float(fps)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps = max(round(fps), 1)
    scene.render.fps_base = scene.render.fps / fps
    # Debian 12's Blender 3.4 guesses flat faces from the normals with `np.bool`, which its
    # NumPy (1.24) no longer has; flat shading skips that guess and changes no vertex.
    bpy.ops.import_scene.gltf(filepath=glb, import_shading="FLAT")
    armatures = [o for o in scene.objects if o.type == "ARMATURE"]
    meshes = [o for o in scene.objects if o.type == "MESH"]
    report = {
        "armatures": [o.name for o in armatures],
        "meshes": [
            {
                "name": o.name,
                "parent": o.parent.name if o.parent else None,
                "modifiers": [
                    {"type": m.type, "object": getattr(m.object, "name", None)} for m in o.modifiers
                ],
            }
            for o in meshes
        ],
    }
    action = armatures[0].animation_data.action if armatures else None
    if action is not None:
        report["action"] = {"name": action.name, "frame_range": list(action.frame_range)}
    if meshes:
        report["rest"] = vertices(meshes[0])
        report["posed"] = {}
        for frame in frames:
            scene.frame_set(int(frame))
            evaluated = meshes[0].evaluated_get(bpy.context.evaluated_depsgraph_get())
            report["posed"][frame] = vertices(evaluated)
    before = set(bpy.data.objects)
    # Debian 12's Blender 3.4 opens the file with mode "rU", which its Python (3.11) refuses;
    # the importer's own module reads it with "r" here, the same text.
    from io_anim_bvh import import_bvh

    import_bvh.open = lambda path, mode="r", *rest: open(path, mode.replace("U", ""), *rest)
    bpy.ops.import_anim.bvh(filepath=bvh, update_scene_fps=False, use_fps_scale=False)
    (skeleton,) = [o for o in bpy.data.objects if o not in before and o.type == "ARMATURE"]
    report["bvh"] = {
        "bones": [b.name for b in skeleton.data.bones],
        "frame_range": list(skeleton.animation_data.action.frame_range),
    }
    with open(out, "w") as f:
        json.dump(report, f)


main(sys.argv[sys.argv.index("--") + 1 :])
