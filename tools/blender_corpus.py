#!/usr/bin/env python3
"""Motion files exported by Blender itself, for the retargeting corpus (crates/motion/tests/data/blender).

    python3 -m venv /tmp/bpy && /tmp/bpy/bin/pip install bpy==4.5.15   # Blender as a module (PyPI)
    /tmp/bpy/bin/python tools/blender_corpus.py crates/motion/tests/data/blender

Builds Rigify's basic human metarig (Blender's bundled add-on: 29 bones — `spine` …
`spine.006`, `shoulder.L`, `upper_arm.L`, `forearm.L`, `hand.L`, `pelvis.L`, `thigh.L`,
`shin.L`, `foot.L`, `toe.L`, `heel.02.L`, breasts; Z up, facing −Y, metres), poses it in four
frames — rest; upper arms hanging; forearms bent forward with the thighs swung forward; the
torso turned 60° with the arms hanging — and writes it with Blender's own exporters: FBX
(binary, `add_leaf_bones`, Blender's bone-axis conversion), glTF binary (a skin over a small
mesh weighted to the armature, as the exporter needs one; the FBX holds it too, as a character
is exported) and BVH. The scene stands at its last frame when exported, as after a user
scrubs the timeline: Blender writes that pose as the FBX bones' own transforms, the rest only
in the bind pose (which it writes for a skinned mesh). `expected.json` holds, per frame,
every limb bone's world direction as Blender evaluates it (Z up, facing −Y), for the test to
compare the retargeted body against.
"""

import json
import math
import sys
from pathlib import Path

import bpy  # first: it puts Blender's own modules on the path
import addon_utils
from mathutils import Matrix, Quaternion, Vector

# (bone, the next bone down its limb): the directions the test compares.
LIMBS = [
    (f"{b}.{s}", f"{c}.{s}")
    for s in ("L", "R")
    for b, c in (("upper_arm", "forearm"), ("forearm", "hand"), ("thigh", "shin"), ("shin", "foot"))
]
FRAMES = [1, 2, 3, 4]


def aim(arm, name, direction):
    """Turns pose bone `name` about its head so that it points along world `direction`."""
    pb = arm.pose.bones[name]
    world = arm.matrix_world @ pb.matrix
    head = world.to_translation()
    current = (arm.matrix_world @ pb.tail) - (arm.matrix_world @ pb.head)
    turn = current.normalized().rotation_difference(Vector(direction).normalized())
    new = Matrix.Translation(head) @ turn.to_matrix().to_4x4() @ Matrix.Translation(-head) @ world
    pb.matrix = arm.matrix_world.inverted() @ new
    bpy.context.view_layer.update()


def key(arm, frame):
    for pb in arm.pose.bones:
        pb.keyframe_insert("rotation_quaternion", frame=frame)
        pb.keyframe_insert("location", frame=frame)


def main() -> int:
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("blender_corpus")
    out.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon_utils.enable("rigify", default_set=True)
    bpy.ops.object.armature_basic_human_metarig_add()
    arm = bpy.context.object
    for pb in arm.pose.bones:
        pb.rotation_mode = "QUATERNION"
    scene = bpy.context.scene
    scene.render.fps = 10
    scene.frame_start, scene.frame_end = FRAMES[0], FRAMES[-1]
    bpy.ops.object.mode_set(mode="POSE")

    def rest():
        for pb in arm.pose.bones:
            pb.rotation_quaternion = Quaternion()
            pb.location = Vector()
        bpy.context.view_layer.update()

    down, forward = (0, 0, -1), (0, -1, 0)
    thigh = (0, -0.6, -0.8)
    rest()
    key(arm, FRAMES[0])
    for s in ("L", "R"):
        aim(arm, f"upper_arm.{s}", down)
        aim(arm, f"forearm.{s}", down)
    key(arm, FRAMES[1])
    rest()
    for s in ("L", "R"):
        aim(arm, f"upper_arm.{s}", down)
        aim(arm, f"forearm.{s}", forward)
        aim(arm, f"thigh.{s}", thigh)
        aim(arm, f"shin.{s}", down)
    key(arm, FRAMES[2])
    rest()
    spine = arm.pose.bones["spine.001"]
    spine.rotation_quaternion = Quaternion((0, 1, 0), math.radians(60))  # the bone's Y is up
    bpy.context.view_layer.update()
    for s in ("L", "R"):
        aim(arm, f"upper_arm.{s}", down)
        aim(arm, f"forearm.{s}", down)
    key(arm, FRAMES[3])

    expected = {}
    for f in FRAMES:
        scene.frame_set(f)
        bpy.context.view_layer.update()
        dirs = {}
        for b, c in LIMBS:
            head = arm.matrix_world @ arm.pose.bones[b].head
            tail = arm.matrix_world @ arm.pose.bones[c].head
            dirs[f"{b}>{c}"] = list((tail - head).normalized())
        expected[str(f - FRAMES[0])] = dirs
    bpy.ops.object.mode_set(mode="OBJECT")

    # A small mesh skinned to every deform bone, so that the glTF exporter writes a skin.
    bpy.ops.mesh.primitive_cube_add(size=0.1, location=(0, 0, 1))
    cube = bpy.context.object
    cube.select_set(True)
    arm.select_set(True)
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.parent_set(type="ARMATURE_NAME")
    group = cube.vertex_groups["spine"]
    group.add([v.index for v in cube.data.vertices], 1.0, "REPLACE")

    bpy.ops.object.select_all(action="DESELECT")
    arm.select_set(True)
    bpy.context.view_layer.objects.active = arm
    bpy.ops.export_anim.bvh(filepath=str(out / "metarig.bvh"), frame_start=FRAMES[0],
                            frame_end=FRAMES[-1])
    cube.select_set(True)
    # With the skinned mesh, as a character is exported: the file then has a bind pose.
    bpy.ops.export_scene.fbx(filepath=str(out / "metarig.fbx"), use_selection=True,
                             object_types={"ARMATURE", "MESH"}, bake_anim=True,
                             add_leaf_bones=True)
    bpy.ops.export_scene.gltf(filepath=str(out / "metarig.glb"), export_format="GLB",
                              use_selection=True, export_animations=True)
    (out / "expected.json").write_text(json.dumps(
        {"blender": bpy.app.version_string, "fps": scene.render.fps,
         "frames": [f - FRAMES[0] for f in FRAMES], "up": "Z", "forward": "-Y",
         "directions": expected}, indent=1))
    print(f"wrote {out}: metarig.fbx, metarig.glb, metarig.bvh, expected.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
