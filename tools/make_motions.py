#!/usr/bin/env python3
"""Motion files of the formats `f3g motion` reads, made here from scratch (numpy only), for the
README's pictures and BENCHMARKS (no third-party motion data is redistributed):

- `walk_mixamo.bvh`: a walk on a Mixamo-named skeleton (`mixamorig:` prefixes), centimetres,
  T-pose rest, Y up, 30 fps;
- `walk_cmu.bvh`: the same walk under CMU names (`LHipJoint`, `LowerBack`, ...), ZXY channels;
- `walk_mixamo.fbx`: the Mixamo walk as an ASCII FBX 7.4 file (bones, one animation stack);
- `walk_amass.npz`: an AMASS SMPL-H layout walk (`poses` F×156, `trans`, `betas`,
  `mocap_framerate`, `gender` as a string array), Z up, 120 fps;
- `walk.smpl`: the same walk in the `smplcodec` layout (`bodyPose` F×22×3, ...), Y up, 30 fps;
- `amass_10k.npz` and `walk_mixamo_7k.bvh` (with `--long`): 10 000 frames of the AMASS walk
  and 7 000 of the Mixamo one, for `f3g motion convert`'s timing;
- `kneel.bvh`, `arms_overhead.bvh`, `head_turn.bvh` (with `--unseen`): one-second motions on
  the Mixamo skeleton far from the synthetic capture's choreography (a lunge down onto the
  right knee, both arms raised overhead, the head turned left and right and tilted), each
  easing from standing with the arms down, for `f3g synth --motion` captures that measure how
  an avatar does on poses it never saw (issue #43).

Usage: python3 tools/make_motions.py OUT_DIR [--long] [--unseen]
(The README's motion pictures: `f3g animate runs/demo/run --motion OUT_DIR/FILE --out DIR
--size 288x384 --fps 8 --turns 0.25` for each file, one frame of each.)
"""

import sys
from pathlib import Path

import numpy as np


def quat_axis(axis, angle):
    axis = np.asarray(axis, float)
    h = 0.5 * angle
    return np.concatenate([[np.cos(h)], np.sin(h) * axis])


def quat_mul(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ])


def axis_angle(q):
    q = q if q[0] >= 0 else -q
    s = np.linalg.norm(q[1:])
    if s < 1e-12:
        return np.zeros(3)
    return q[1:] / s * 2 * np.arctan2(s, q[0])


def euler_zyx_degrees(q):
    """(z, y, x) in degrees with R = Rz·Ry·Rx."""
    w, x, y, z = q
    ez = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    ey = np.arcsin(np.clip(2 * (w * y - z * x), -1, 1))
    ex = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    return np.degrees([ez, ey, ex])


X, Y, Z = [1, 0, 0], [0, 1, 0], [0, 0, 1]


def walk_rotations(t):
    """Local rotations (quaternions) of a walk at time t, by generic joint, T-pose rest."""
    s = np.sin(2 * np.pi * 0.9 * t)
    c = np.cos(2 * np.pi * 0.9 * t)
    return {
        "hips": quat_axis(Y, 0.08 * s),
        "chest": quat_axis(X, 0.05 + 0.03 * c),
        "neck": quat_axis(Y, -0.1 * s),
        "l_arm": quat_mul(quat_axis(Z, -1.25), quat_axis(Y, -0.45 * s)),
        "r_arm": quat_mul(quat_axis(Z, 1.25), quat_axis(Y, -0.45 * s)),
        "l_forearm": quat_axis(Y, 0.35 + 0.15 * max(0, -s)),
        "r_forearm": quat_axis(Y, -0.35 - 0.15 * max(0, s)),
        "l_upleg": quat_axis(X, -0.45 * s),
        "r_upleg": quat_axis(X, 0.45 * s),
        "l_leg": quat_axis(X, 0.8 * max(0, c)),
        "r_leg": quat_axis(X, 0.8 * max(0, -c)),
    }


def walk_root(t):
    """Pelvis offset from standing, metres (Y up, walking toward +Z)."""
    return np.array([0.0, 0.02 * abs(np.sin(2 * np.pi * 0.9 * t)), 1.1 * t])


# The BVH layout: key, parent key, position (cm, T-pose, Y up, facing +Z, left +X).
LAYOUT = [
    ("hips", None, (0, 95, 0)), ("spine", "hips", (0, 105, -1)), ("spine1", "spine", (0, 118, -1)),
    ("chest", "spine1", (0, 132, 0)), ("neck", "chest", (0, 150, -2)), ("head", "neck", (0, 160, 1)),
    ("l_clavicle", "chest", (4, 145, -2)), ("l_arm", "l_clavicle", (17, 145, -3)),
    ("l_forearm", "l_arm", (44, 145, -3)), ("l_hand", "l_forearm", (70, 145, -3)),
    ("r_clavicle", "chest", (-4, 145, -2)), ("r_arm", "r_clavicle", (-17, 145, -3)),
    ("r_forearm", "r_arm", (-44, 145, -3)), ("r_hand", "r_forearm", (-70, 145, -3)),
    ("l_upleg", "hips", (9, 90, 0)), ("l_leg", "l_upleg", (9, 49, 1)), ("l_foot", "l_leg", (9, 8, -3)),
    ("l_toe", "l_foot", (9, 1, 10)),
    ("r_upleg", "hips", (-9, 90, 0)), ("r_leg", "r_upleg", (-9, 49, 1)), ("r_foot", "r_leg", (-9, 8, -3)),
    ("r_toe", "r_foot", (-9, 1, 10)),
]

MIXAMO = {
    "hips": "Hips", "spine": "Spine", "spine1": "Spine1", "chest": "Spine2", "neck": "Neck",
    "head": "Head", "clavicle": "Shoulder", "arm": "Arm", "forearm": "ForeArm", "hand": "Hand",
    "upleg": "UpLeg", "leg": "Leg", "foot": "Foot", "toe": "ToeBase",
}
CMU = dict(MIXAMO, spine="LowerBack", spine1="Spine", chest="Spine1")


def name(key, family):
    side, base = (key[:2], key[2:]) if key[:2] in ("l_", "r_") else ("", key)
    if family == "cmu" and base == "upleg":
        # CMU's hip joint sits between the hips and the thigh; here it is the thigh itself.
        return {"l_": "LeftUpLeg", "r_": "RightUpLeg"}[side]
    text = (MIXAMO if family == "mixamo" else CMU)[base]
    text = {"l_": "Left", "r_": "Right", "": ""}[side] + text
    return "mixamorig:" + text if family == "mixamo" else text


def ease(t, duration=0.8):
    """0 → 1 over `duration` seconds (smoothstep), then 1."""
    u = min(max(t / duration, 0.0), 1.0)
    return u * u * (3 - 2 * u)


def arms_down():
    return {"l_arm": quat_axis(Z, -1.25), "r_arm": quat_axis(Z, 1.25)}


def kneel(t):
    """A lunge down onto the right knee: left thigh forward and shin upright, right thigh
    down and shin back along the floor; the pelvis drops about 0.48 m."""
    e = ease(t)
    rots = arms_down()
    rots.update({
        "l_upleg": quat_axis(X, -1.5 * e), "l_leg": quat_axis(X, 1.5 * e),
        "r_upleg": quat_axis(X, 0.1 * e), "r_leg": quat_axis(X, 1.6 * e),
        "chest": quat_axis(X, 0.15 * e),
    })
    return rots, np.array([0.0, -0.48 * e, 0.05 * e])


def arms_overhead(t):
    """Both arms raised from the sides to overhead, elbows slightly bent."""
    e = ease(t)
    return {
        "l_arm": quat_axis(Z, -1.25 + 2.6 * e), "r_arm": quat_axis(Z, 1.25 - 2.6 * e),
        "l_forearm": quat_axis(Z, 0.3 * e), "r_forearm": quat_axis(Z, -0.3 * e),
    }, np.zeros(3)


def head_turn(t):
    """The head turned 70° to the left, then to the right, tilted."""
    turn = 1.2 * np.sin(np.pi * min(t / 1.0, 1.0) * 1.5)
    rots = arms_down()
    rots.update({
        "neck": quat_axis(Y, 0.4 * turn),
        "head": quat_mul(quat_axis(Y, 0.6 * turn), quat_axis(Z, 0.25 * turn)),
    })
    return rots, np.zeros(3)


def walk(t):
    return walk_rotations(t), walk_root(t)


def write_bvh(path, family, frames, fps, order, motion=walk):
    pos = {k: np.array(p, float) for k, _, p in LAYOUT}
    children = {k: [c for c, p, _ in LAYOUT if p == k] for k, _, _ in LAYOUT}
    lines = ["HIERARCHY"]
    sequence = []

    def joint(key, depth):
        pad = "  " * depth
        parent = dict((k, p) for k, p, _ in LAYOUT)[key]
        offset = pos[key] - (pos[parent] if parent else 0)
        lines.append(f"{pad}{'ROOT' if parent is None else 'JOINT'} {name(key, family)}")
        lines.append(pad + "{")
        lines.append(f"{pad}  OFFSET {offset[0]:.4f} {offset[1]:.4f} {offset[2]:.4f}")
        rot = " ".join(f"{a}rotation" for a in order)
        if parent is None:
            lines.append(f"{pad}  CHANNELS 6 Xposition Yposition Zposition {rot}")
        else:
            lines.append(f"{pad}  CHANNELS 3 {rot}")
        sequence.append(key)
        for c in children[key]:
            joint(c, depth + 1)
        if not children[key]:
            lines.extend([pad + "  End Site", pad + "  {", pad + "    OFFSET 0 5 0", pad + "  }"])
        lines.append(pad + "}")

    joint("hips", 0)
    lines.extend(["MOTION", f"Frames: {frames}", f"Frame Time: {1 / fps:.7f}"])
    for f in range(frames):
        t = f / fps
        rots, offset = motion(t)
        root = pos["hips"] + 100 * offset
        values = [f"{v:.4f}" for v in root]
        for key in sequence:
            q = rots.get(key, np.array([1.0, 0, 0, 0]))
            values += [f"{v:.5f}" for v in euler_degrees(q, order)]
        lines.append(" ".join(values))
    Path(path).write_text("\n".join(lines) + "\n")


def euler_degrees(q, order):
    """Angles for channels in `order` (e.g. "ZXY": R = Rz·Rx·Ry), degrees."""
    m = rotation_matrix(q)
    if order == "ZYX":
        return euler_zyx_degrees(q)
    if order == "ZXY":
        # R = Rz(a)·Rx(b)·Ry(c): m[2][1] = sin b.
        b = np.arcsin(np.clip(m[2][1], -1, 1))
        a = np.arctan2(-m[0][1], m[1][1])
        c = np.arctan2(-m[2][0], m[2][2])
        return np.degrees([a, b, c])
    raise ValueError(order)


def rotation_matrix(q):
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


KTIME = 46186158000  # FBX ticks per second


def write_fbx(path, frames, fps):
    """The Mixamo walk as ASCII FBX: Y up, centimetres, Euler XYZ (R = Rz·Ry·Rx) in degrees."""
    pos = {k: np.array(p, float) for k, _, p in LAYOUT}
    parents = {k: p for k, p, _ in LAYOUT}
    objects, links = [], []
    ids = iter(range(100001, 10**7))
    stack, layer = next(ids), next(ids)
    stop = round((frames - 1) / fps * KTIME)
    objects.append(f'\tAnimationStack: {stack}, "AnimStack::Take 001", "" {{\n\t\tProperties70:  {{\n'
                   f'\t\t\tP: "LocalStart", "KTime", "Time", "",0\n\t\t\tP: "LocalStop", "KTime", "Time", "",{stop}\n'
                   f'\t\t}}\n\t}}\n\tAnimationLayer: {layer}, "AnimLayer::BaseLayer", "" {{\n\t}}')
    links.append(f'\tC: "OO",{layer},{stack}')
    times = ",".join(str(round(f / fps * KTIME)) for f in range(frames))
    model_of = {}
    for key, parent, _ in LAYOUT:
        model, attr = next(ids), next(ids)
        model_of[key] = model
        o = pos[key] - (pos[parent] if parent else 0)
        objects.append(f'\tNodeAttribute: {attr}, "NodeAttribute::", "LimbNode" {{\n\t\tTypeFlags: "Skeleton"\n\t}}\n'
                       f'\tModel: {model}, "Model::{name(key, "mixamo")}", "LimbNode" {{\n\t\tVersion: 232\n'
                       f'\t\tProperties70:  {{\n\t\t\tP: "Lcl Translation", "Lcl Translation", "", "A",{o[0]},{o[1]},{o[2]}\n\t\t}}\n\t}}')
        links.append(f'\tC: "OO",{attr},{model}')
        links.append(f'\tC: "OO",{model},{model_of[parent] if parent else 0}')
        rot = np.array([euler_zyx_degrees(walk_rotations(f / fps).get(key, np.array([1.0, 0, 0, 0])))[::-1]
                        for f in range(frames)])
        channels = [("R", "Lcl Rotation", rot)]
        if parent is None:
            channels.append(("T", "Lcl Translation",
                             np.array([pos[key] + 100 * walk_root(f / fps) for f in range(frames)])))
        for kind, prop, values in channels:
            node = next(ids)
            objects.append(f'\tAnimationCurveNode: {node}, "AnimCurveNode::{kind}", "" {{\n\t}}')
            links.append(f'\tC: "OO",{node},{layer}')
            links.append(f'\tC: "OP",{node},{model}, "{prop}"')
            for k, axis in enumerate(["d|X", "d|Y", "d|Z"]):
                curve = next(ids)
                keys = ",".join(f"{v:.6f}" for v in values[:, k])
                objects.append(f'\tAnimationCurve: {curve}, "AnimCurve::", "" {{\n\t\tDefault: 0\n\t\tKeyVer: 4009\n'
                               f'\t\tKeyTime: *{frames} {{\n\t\t\ta: {times}\n\t\t}}\n'
                               f'\t\tKeyValueFloat: *{frames} {{\n\t\t\ta: {keys}\n\t\t}}\n'
                               f'\t\tKeyAttrFlags: *1 {{\n\t\t\ta: 24836\n\t\t}}\n'
                               f'\t\tKeyAttrDataFloat: *4 {{\n\t\t\ta: 0,0,0,0\n\t\t}}\n'
                               f'\t\tKeyAttrRefCount: *1 {{\n\t\t\ta: {frames}\n\t\t}}\n\t}}')
                links.append(f'\tC: "OP",{curve},{node}, "{axis}"')
    header = ('; FBX 7.4.0 project file\nFBXHeaderExtension:  {\n\tFBXHeaderVersion: 1003\n\tFBXVersion: 7400\n}\n'
              'GlobalSettings:  {\n\tVersion: 1000\n\tProperties70:  {\n'
              '\t\tP: "UpAxis", "int", "Integer", "",1\n\t\tP: "UpAxisSign", "int", "Integer", "",1\n'
              '\t\tP: "FrontAxis", "int", "Integer", "",2\n\t\tP: "FrontAxisSign", "int", "Integer", "",1\n'
              '\t\tP: "CoordAxis", "int", "Integer", "",0\n\t\tP: "CoordAxisSign", "int", "Integer", "",1\n'
              '\t\tP: "UnitScaleFactor", "double", "Number", "",1\n'
              f'\t\tP: "TimeMode", "enum", "", "",14\n\t\tP: "CustomFrameRate", "double", "Number", "",{fps}\n\t}}\n}}\n')
    Path(path).write_text(header + "Objects:  {\n" + "\n".join(objects) + "\n}\nConnections:  {\n"
                          + "\n".join(links) + "\n}\n")


# SMPL joint indices of the generic keys (body_pose rows are joints 1..21).
SMPL = {"hips": 0, "l_upleg": 1, "r_upleg": 2, "spine1": 3, "l_leg": 4, "r_leg": 5, "spine2": 6,
        "chest": 9, "neck": 12, "l_clavicle": 13, "r_clavicle": 14, "head": 15, "l_arm": 16,
        "r_arm": 17, "l_forearm": 18, "r_forearm": 19}


def smpl_poses(frames, fps, z_up):
    poses = np.zeros((frames, 52, 3), np.float32)
    trans = np.zeros((frames, 3), np.float32)
    up = quat_axis(X, np.pi / 2) if z_up else np.array([1.0, 0, 0, 0])
    for f in range(frames):
        t = f / fps
        rots = walk_rotations(t)
        for key, q in rots.items():
            j = SMPL[key]
            if j == 0:
                q = quat_mul(up, q)
            poses[f, j] = axis_angle(q)
        if "hips" not in rots:
            poses[f, 0] = axis_angle(up)
        r = walk_root(t) + np.array([0, 0.9, 0])
        trans[f] = rotation_matrix(up) @ r
    return poses, trans


def write_amass(path, frames):
    fps = 120.0
    poses, trans = smpl_poses(frames, fps, z_up=True)
    np.savez(path, poses=poses.reshape(frames, 156), trans=trans, betas=np.zeros(16, np.float32),
             mocap_framerate=np.array(fps), gender=np.array("neutral"))


def write_smpl(path, frames):
    fps = 30.0
    poses, trans = smpl_poses(frames, fps, z_up=False)
    np.savez(path, codecVersion=np.int32(1), smplVersion=np.int32(2), gender=np.int32(0),
             shapeParameters=np.zeros(10, np.float32), frameCount=np.int32(frames),
             frameRate=np.float32(fps), bodyTranslation=trans, bodyPose=poses[:, :22],
             headPose=np.zeros((frames, 3, 3), np.float32), leftHandPose=poses[:, 22:37],
             rightHandPose=poses[:, 37:52])
    Path(str(path) + ".npz").rename(path)


def main():
    if len(sys.argv) < 2 or sys.argv[1].startswith("-"):
        print(__doc__)
        sys.exit(0 if sys.argv[1:2] in (["-h"], ["--help"]) else 2)
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    write_bvh(out / "walk_mixamo.bvh", "mixamo", 60, 30.0, "ZYX")
    write_bvh(out / "walk_cmu.bvh", "cmu", 60, 30.0, "ZXY")
    write_fbx(out / "walk_mixamo.fbx", 60, 30.0)
    write_amass(out / "walk_amass.npz", 240)
    write_smpl(out / "walk.smpl", 60)
    if "--long" in sys.argv:
        write_amass(out / "amass_10k.npz", 10_000)
        write_bvh(out / "walk_mixamo_7k.bvh", "mixamo", 7_000, 30.0, "ZYX")
    if "--unseen" in sys.argv:
        for motion in (kneel, arms_overhead, head_turn):
            write_bvh(out / f"{motion.__name__}.bvh", "mixamo", 31, 30.0, "ZYX", motion)


if __name__ == "__main__":
    main()
