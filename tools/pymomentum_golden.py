#!/usr/bin/env python3
"""Golden data for f3g-rig's Momentum implementation, produced by pymomentum itself.

Builds random characters (skeletons with pre-rotations, meshes, skin weights, parameter
transforms using every channel, constants and joint references), saves each as glTF plus a
`.model` file, and records pymomentum's skinned vertices and joint positions for random model
parameters. The Rust test `crates/rig/tests/pymomentum.rs` loads the same files and must match.

Run (pymomentum-cpu has wheels for Python >= 3.12 only):

    python3.12 -m pip install pymomentum-cpu numpy
    python3.12 tools/pymomentum_golden.py crates/rig/tests/data/pymomentum

Units: Momentum works in centimetres; the glTF files are in metres and the golden positions are
converted to metres. Model-parameter translations (`tx`, `ty`, `tz`) stay in centimetres, as in
Momentum's `.model` files.
"""

import os
import sys

import numpy as np
import pymomentum.geometry as g

MODEL_A = """Momentum Model Definition V1.0
# every channel type, a constant offset, and a joint reference
[ParameterTransform]
root.tx = 1.0*root_tx
root.ty = 1.0*root_ty
root.tz = 1.0*root_tz
root.rx = 1.0*root_rx
root.ry = 1.0*root_ry
root.rz = 1.0*root_rz
spine.rx = 1.0*spine_bend + 0.05
spine.ry = 0.5*spine_bend + 1.0*spine_twist
spine.sc = 1.0*body_scale
l_arm.rz = 1.0*l_arm_raise
l_arm.ry = 1.0*l_arm_swing
l_arm.tx = 0.5*l_arm_stretch
r_arm.rz = -1.0*l_arm.rz + 1.0*r_arm_raise
l_hand.rx = 1.0*l_hand_flex
l_hand.sc = 1.0*hand_scale
r_hand.sc = 1.0*r_hand.sc + 1.0*hand_scale
head.ry = 1.0*head_turn
head.rx = 1.0*head_nod
[ParameterSets]
parameterset arms l_arm_raise l_arm_swing r_arm_raise
"""

PARENTS_A = {"root": None, "spine": "root", "head": "spine", "l_arm": "spine", "l_hand": "l_arm", "r_arm": "spine", "r_hand": "r_arm"}


def random_quat(rng, spread):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(-spread, spread)
    # pymomentum takes quaternions as (x, y, z, w).
    return np.concatenate([axis * np.sin(angle / 2), [np.cos(angle / 2)]]).astype(np.float32)


def build(name, parents, model, seed, vertices=80):
    rng = np.random.default_rng(seed)
    names = list(parents)
    joints = []
    for n in names:
        parent = -1 if parents[n] is None else names.index(parents[n])
        offset = rng.uniform(-20, 20, size=3).astype(np.float32) if parent >= 0 else np.array([0, 90, 0], np.float32)
        joints.append(g.Joint(n, parent, random_quat(rng, 1.0), offset))
    skeleton = g.Skeleton(joints)
    identity = g.ParameterTransform(["unused"], skeleton, np.zeros((7 * len(names), 1), np.float32))
    character = g.Character(name, skeleton, identity).load_model_definition_from_bytes(model.encode())
    # A cloud of vertices around the rest joints, each skinned to up to four joints.
    rest = g.model_parameters_to_skeleton_state(character, np.zeros(len(character.parameter_transform.names), np.float32))
    centres = rest[:, :3]
    owner = rng.integers(0, len(names), size=vertices)
    points = (centres[owner] + rng.normal(scale=6.0, size=(vertices, 3))).astype(np.float32)
    faces = np.array([[i, i + 1, i + 2] for i in range(vertices - 2)], np.int32)
    index = np.zeros((vertices, 4), np.int32)
    weight = np.zeros((vertices, 4), np.float32)
    for v in range(vertices):
        chosen = rng.choice(len(names), size=rng.integers(1, 5), replace=False)
        chosen[0] = owner[v]
        w = rng.uniform(0.1, 1.0, size=len(chosen))
        index[v, : len(chosen)] = chosen
        weight[v, : len(chosen)] = w / w.sum()
    return character.with_mesh_and_skin_weights(g.Mesh(points, faces), g.SkinWeights(index, weight))


def main(out):
    os.makedirs(out, exist_ok=True)
    for name, seed in [("char_a", 1), ("char_b", 2)]:
        character = build(name, PARENTS_A, MODEL_A, seed)
        g.Character.save_gltf(os.path.join(out, f"{name}.glb"), character)
        with open(os.path.join(out, f"{name}.model"), "w") as f:
            f.write(MODEL_A)
        rng = np.random.default_rng(seed + 100)
        names = character.parameter_transform.names
        params = []
        for _ in range(8):
            p = np.zeros(len(names), np.float32)
            for i, n in enumerate(names):
                if n in ("root_tx", "root_ty", "root_tz", "l_arm_stretch"):
                    p[i] = rng.uniform(-10, 10)
                elif n.endswith("scale"):
                    p[i] = rng.uniform(-0.4, 0.4)
                else:
                    p[i] = rng.uniform(-1.2, 1.2)
            params.append(p)
        params = np.stack(params)
        states = np.stack([g.model_parameters_to_skeleton_state(character, p) for p in params])
        vertices = np.stack([character.skin_points(s) for s in states])
        np.savez(
            os.path.join(out, f"{name}_golden.npz"),
            parameter_names=np.frombuffer("\n".join(names).encode(), np.uint8),
            params=params,
            joint_positions=(states[:, :, :3] * 0.01).astype(np.float32),
            vertices=(vertices * 0.01).astype(np.float32),
        )
        print(name, len(names), "parameters", vertices.shape)


if __name__ == "__main__":
    main(sys.argv[1])
