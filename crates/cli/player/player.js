// The f3g player: loads a baked avatar (`f3g export-avatar`'s .glb), skins its Gaussians on
// the GPU with Spark's SplatSkinning and applies its pose correctives and expressions each
// frame of a motion.
//
// Served files: `avatar.glb`, `motions.json` ([{name, frames, fps, url}]) and per motion a
// little-endian float32 array of `frames × (16·J + E)`: each joint's world matrix (column
// major) in the frame's pose, then the E expression weights in the file's order.
//
// Skinning: Spark's SplatSkinning in its linear-blend mode (four bones per splat, on the GPU),
// as f3g skins, is given each joint's skinning matrix S_j = W_j · rest_j⁻¹; its own rest pose
// stays the identity (Spark would compose rest⁻¹ · S, not S · rest⁻¹). Linear blending
// transforms each splat's covariance, so the splats are Spark's extended splats with
// covariances (`extSplats`, `covSplats`). The correctives and expressions change the canonical
// splats before skinning, on the CPU.
//
// Light fixed in the world (`F3G_world_shading`, avatars trained with `world_shading`): each
// frame, every splat's canonical normal is turned by its blended skinning matrix (normalised),
// and its degree-0 colour multiplied by the degree ≤ 2 SH of that normal times the file's
// coefficients, as f3g's baked avatar does (crates/avatar/src/model/shading.rs).
//
// The page sets `window.f3g = {ready, error, frame, setFrame(i), setView(...), fps}` so that
// tests and scripts can wait for it and drive it; errors are shown on the page, not only
// logged.

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import {
  SparkRenderer,
  SplatMesh,
  SplatSkinning,
  SplatSkinningMode,
} from "@sparkjsdev/spark";

const C0 = 0.28209479177387814;
// The floor grid's cell (metres).
const FLOOR_CELL = 0.5;
const state = { ready: false, error: null, frame: 0, fps: 0 };
window.f3g = state;

function fail(message) {
  state.error = String(message);
  const box = document.getElementById("error");
  box.textContent = "f3g player: " + state.error;
  box.style.display = "block";
  document.getElementById("status").textContent = "error";
  console.error(state.error);
}

window.addEventListener("error", (e) => fail(e.message));
window.addEventListener("unhandledrejection", (e) => fail(e.reason?.message ?? e.reason));

async function fetchBytes(url) {
  const response = await fetch(url);
  if (!response.ok) throw new Error(`${url}: HTTP ${response.status}`);
  return response.arrayBuffer();
}

// A binary glTF: its JSON and a typed view of every accessor, checked against the buffer.
function parseGlb(buffer, name) {
  const view = new DataView(buffer);
  if (buffer.byteLength < 20 || view.getUint32(0, true) !== 0x46546c67) {
    throw new Error(`${name} is not a binary glTF file`);
  }
  const total = view.getUint32(8, true);
  if (total > buffer.byteLength) throw new Error(`${name} is truncated`);
  let at = 12, json = null, bin = null;
  while (at + 8 <= total) {
    const length = view.getUint32(at, true), kind = view.getUint32(at + 4, true);
    if (at + 8 + length > total) throw new Error(`${name} is truncated`);
    const bytes = new Uint8Array(buffer, at + 8, length);
    if (kind === 0x4e4f534a) json = JSON.parse(new TextDecoder().decode(bytes));
    if (kind === 0x004e4942) bin = bytes;
    at += 8 + length;
  }
  if (!json || !bin) throw new Error(`${name} has no JSON or no binary chunk`);
  const width = { SCALAR: 1, VEC2: 2, VEC3: 3, VEC4: 4, MAT4: 16 };
  const types = { 5126: Float32Array, 5125: Uint32Array, 5123: Uint16Array, 5121: Uint8Array };
  // An accessor's values; `normalized` unsigned bytes (quantised skin weights) as floats.
  function accessor(index) {
    const a = json.accessors?.[index];
    if (!a) throw new Error(`${name}: accessor ${index} is missing`);
    const Type = types[a.componentType];
    if (!Type) throw new Error(`${name}: accessor ${index} has component type ${a.componentType}`);
    const count = a.count * width[a.type];
    const start = (a.byteOffset ?? 0);
    const values = new Type(bufferView(a.bufferView, start, count * Type.BYTES_PER_ELEMENT));
    if (!a.normalized) return values;
    if (a.componentType !== 5121) throw new Error(`${name}: accessor ${index} is normalized but not bytes`);
    return Float32Array.from(values, (x) => x / 255);
  }
  // `length` bytes (all when undefined) of buffer view `index` from `offset`, copied.
  function bufferView(index, offset = 0, length) {
    const v = json.bufferViews?.[index];
    if (!v) throw new Error(`${name}: buffer view ${index} is missing`);
    const start = (v.byteOffset ?? 0) + offset;
    const size = length ?? v.byteLength;
    if (start + size > bin.byteLength) throw new Error(`${name}: buffer view ${index} does not fit the buffer`);
    return bin.buffer.slice(bin.byteOffset + start, bin.byteOffset + start + size);
  }
  return { json, accessor, view: bufferView };
}

// The browser's own inflater: `format` "gzip" (SPZ) or "deflate" (zlib, the packed arrays).
async function inflate(bytes, format) {
  const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream(format));
  return new Uint8Array(await new Response(stream).arrayBuffer());
}

// SPZ version 2 or 3 (crates/splat/src/spz.rs has the layout) in glTF's frame: SPZ stores
// right-up-back, so x and z change sign, with the quaternion's x, z and the odd SH functions.
const SPZ_FLIP_SH = [1, -1, -1, -1, -1, 1, 1, 1, 1, 1, 1, -1, -1, -1, -1];
async function decodeSpz(compressed, count) {
  const raw = await inflate(compressed, "gzip");
  const header = new DataView(raw.buffer, raw.byteOffset, 16);
  const version = header.getUint32(4, true), n = header.getUint32(8, true);
  const degree = raw[12], fractional = raw[13];
  if (header.getUint32(0, true) !== 0x5053474e || version < 2 || version > 3 || degree > 3 || raw[14] & 2) {
    throw new Error("avatar.glb: the SPZ payload is not SPZ version 2 or 3 without extensions");
  }
  if (n !== count) throw new Error(`avatar.glb: the SPZ payload holds ${n} Gaussians, POSITION ${count}`);
  const k = (degree + 1) * (degree + 1), rb = version >= 3 ? 4 : 3;
  if (raw.length !== 16 + n * (19 + rb - 3 + 3 * (k - 1))) throw new Error("avatar.glb: the SPZ payload is truncated");
  let at = 16;
  const means = new Float32Array(3 * n), unit = 1 / (1 << fractional);
  for (let i = 0; i < 3 * n; i++, at += 3) {
    const fixed = (raw[at] | (raw[at + 1] << 8) | (raw[at + 2] << 16)) << 8 >> 8;
    means[i] = (i % 3 === 1 ? 1 : -1) * fixed * unit;
  }
  const opacities = new Float32Array(n);
  for (let g = 0; g < n; g++) opacities[g] = raw[at++] / 255;
  const sh = Array.from({ length: k }, () => new Float32Array(3 * n));
  for (let i = 0; i < 3 * n; i++) sh[0][i] = (raw[at++] / 255 - 0.5) / 0.15;
  const scales = new Float32Array(3 * n);
  for (let i = 0; i < 3 * n; i++) scales[i] = Math.exp(raw[at++] / 16 - 10);
  const rotations = new Float32Array(4 * n);
  for (let g = 0; g < n; g++, at += rb) {
    const q = [0, 0, 0, 0];
    if (rb === 3) {
      for (let a = 0; a < 3; a++) q[a] = raw[at + a] / 127.5 - 1;
      q[3] = Math.sqrt(Math.max(0, 1 - q[0] * q[0] - q[1] * q[1] - q[2] * q[2]));
    } else {
      let word = (raw[at] | (raw[at + 1] << 8) | (raw[at + 2] << 16) | (raw[at + 3] << 24)) >>> 0;
      const largest = word >>> 30;
      let squares = 0;
      for (let i = 3; i >= 0; i--) {
        if (i === largest) continue;
        const m = ((word & 511) / 511) * Math.SQRT1_2;
        q[i] = (word >>> 9) & 1 ? -m : m;
        squares += q[i] * q[i];
        word >>>= 10;
      }
      q[largest] = Math.sqrt(Math.max(0, 1 - squares));
    }
    rotations.set([-q[0], q[1], -q[2], q[3]], 4 * g);
  }
  for (let g = 0; g < n; g++) {
    for (let j = 1; j < k; j++) {
      for (let c = 0; c < 3; c++) sh[j][3 * g + c] = SPZ_FLIP_SH[j - 1] * (raw[at++] - 128) / 128;
    }
  }
  return { means, opacities, sh, scales, rotations };
}

// `F3G_packed_arrays` (crates/avatar/src/infer/avatar_file.rs): zlib-deflated integers, each
// array stored component by component, times its scale; returned row-major by name.
async function unpackArrays(glb, ext, n) {
  const raw = await inflate(glb.view(ext.bufferView), "deflate");
  const data = new DataView(raw.buffer, raw.byteOffset, raw.byteLength);
  const arrays = new Map();
  let at = 0;
  for (const { name, width, bits, scale } of ext.arrays) {
    const size = bits / 8;
    if (at + n * width * size > raw.length) throw new Error("avatar.glb: F3G_packed_arrays is truncated");
    const values = new Float32Array(n * width);
    for (let c = 0; c < width; c++) {
      for (let g = 0; g < n; g++, at += size) {
        values[g * width + c] = (size === 1 ? data.getInt8(at) : data.getInt16(at, true)) * scale;
      }
    }
    arrays.set(name, values);
  }
  const take = (name) => {
    if (!arrays.has(name)) throw new Error(`avatar.glb: F3G_packed_arrays has no array ${name}`);
    return arrays.get(name);
  };
  return { names: ext.arrays.map((a) => a.name), take };
}

// Vectors `[n, 3]` scaled to unit length (quantised normals).
function unit(v) {
  for (let i = 0; i < v.length; i += 3) {
    const l = Math.hypot(v[i], v[i + 1], v[i + 2]) || 1;
    v[i] /= l; v[i + 1] /= l; v[i + 2] /= l;
  }
  return v;
}

// The avatar's arrays (see crates/avatar/src/infer/avatar_file.rs for the layout), from a
// float file or a compressed one (SPZ Gaussians, packed correctives and expressions).
async function readAvatar(glb) {
  const { json, accessor } = glb;
  if (!json.extensions?.F3G_avatar) {
    throw new Error("avatar.glb is not an f3g avatar (no F3G_avatar extension)");
  }
  const primitive = json.meshes[0].primitives[0];
  const at = primitive.attributes;
  const n = json.accessors[at.POSITION].count;
  const get = (name, w) => {
    const values = accessor(at[name]);
    if (values.length !== w * n) {
      throw new Error(`avatar.glb: ${name} holds ${values.length} values for ${n} Gaussians`);
    }
    return values;
  };
  const spz = primitive.extensions.KHR_gaussian_splatting?.extensions?.KHR_gaussian_splatting_compression_spz_2;
  let gaussians;
  if (spz) {
    gaussians = await decodeSpz(glb.view(spz.bufferView), n);
  } else {
    const sh = [];
    for (let l = 0; l <= 3; l++) {
      if (at[`KHR_gaussian_splatting:SH_DEGREE_${l}_COEF_0`] === undefined) break;
      for (let m = 0; m < 2 * l + 1; m++) {
        sh.push(get(`KHR_gaussian_splatting:SH_DEGREE_${l}_COEF_${m}`, 3));
      }
    }
    gaussians = {
      means: get("POSITION", 3), sh,
      rotations: get("KHR_gaussian_splatting:ROTATION", 4),
      scales: get("KHR_gaussian_splatting:SCALE", 3),
      opacities: get("KHR_gaussian_splatting:OPACITY", 1),
    };
  }
  const ext = primitive.extensions.F3G_pose_correctives;
  const k = ext.count, e = ext.expressions;
  const packed = primitive.extensions.F3G_packed_arrays
    ? await unpackArrays(glb, primitive.extensions.F3G_packed_arrays, n) : null;
  const correctives = [];
  const expressions = [];
  if (packed) {
    for (let c = 0; c < k; c++) {
      const part = (name) => packed.take(`corrective_${c}:${name}`);
      correctives.push({
        position: part("position"), colour: part("colour"),
        logScale: part("logScale"), opacityLogit: part("opacityLogit"),
      });
    }
    for (const name of packed.names) {
      if (name.startsWith("expression:")) expressions.push(packed.take(name));
    }
    if (expressions.length !== e) {
      throw new Error(`avatar.glb: ${expressions.length} packed expressions, ${e} expected`);
    }
  } else {
    const targets = primitive.targets ?? [];
    if (targets.length !== k + e) {
      throw new Error(`avatar.glb: ${targets.length} morph targets for ${k} correctives and ${e} expressions`);
    }
    for (let c = 0; c < k; c++) {
      correctives.push({
        position: accessor(targets[c].POSITION),
        colour: accessor(ext.colour[c]),
        logScale: accessor(ext.logScale[c]),
        opacityLogit: accessor(ext.opacityLogit[c]),
      });
    }
    for (let i = 0; i < e; i++) expressions.push(accessor(targets[k + i].POSITION));
  }
  const light = primitive.extensions.F3G_world_shading;
  let shading = null;
  if (light) {
    if (!Array.isArray(light.coefficients) || light.coefficients.length !== 27) {
      throw new Error("avatar.glb: F3G_world_shading.coefficients is not 27 numbers");
    }
    const normals = packed ? unit(packed.take("shading:normal")) : accessor(light.normal);
    if (normals.length !== 3 * n) {
      throw new Error(`avatar.glb: F3G_world_shading.normal holds ${normals.length} values for ${n} Gaussians`);
    }
    shading = { coefficients: Float32Array.from(light.coefficients), normals };
  }
  const skin = json.skins[0];
  const joints = skin.joints.length;
  // The canonical pose's world matrices, from the nodes' hierarchy.
  const parents = new Array(json.nodes.length).fill(-1);
  json.nodes.forEach((node, i) => (node.children ?? []).forEach((c) => (parents[c] = i)));
  const world = [];
  const local = (node) => new THREE.Matrix4().compose(
    new THREE.Vector3(...(node.translation ?? [0, 0, 0])),
    new THREE.Quaternion(...(node.rotation ?? [0, 0, 0, 1])),
    new THREE.Vector3(...(node.scale ?? [1, 1, 1])));
  const worldOf = (i) => {
    if (world[i]) return world[i];
    const m = local(json.nodes[i]);
    world[i] = parents[i] >= 0 ? worldOf(parents[i]).clone().multiply(m) : m;
    return world[i];
  };
  const rest = skin.joints.map((i) => worldOf(i));
  return {
    n, joints, rest, ...gaussians,
    skinJoints: get("JOINTS_0", 4),
    skinWeights: get("WEIGHTS_0", 4),
    correctives,
    expressions,
    shading,
    featureJoints: ext.featureJoints,
    featureUsed: ext.featureUsed === undefined ? new Uint32Array(0) : accessor(ext.featureUsed),
    featureMean: ext.featureMean === undefined ? new Float32Array(0) : accessor(ext.featureMean),
    featureMap: ext.featureMap === undefined ? new Float32Array(0) : accessor(ext.featureMap),
    root: skin.joints.findIndex((i) => parents[i] < 0 || !skin.joints.includes(parents[i])),
  };
}

// The avatar's canonical Gaussians as a binary 3DGS .ply, which Spark reads with its SH.
function canonicalPly(a) {
  const coeffs = a.sh.length;
  const names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"];
  for (let i = 0; i < 3 * (coeffs - 1); i++) names.push(`f_rest_${i}`);
  names.push("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3");
  const header = `ply\nformat binary_little_endian 1.0\nelement vertex ${a.n}\n` +
    names.map((p) => `property float ${p}\n`).join("") + "end_header\n";
  const head = new TextEncoder().encode(header);
  const body = new Float32Array(a.n * names.length);
  for (let g = 0; g < a.n; g++) {
    const row = body.subarray(g * names.length, (g + 1) * names.length);
    row.set(a.means.subarray(3 * g, 3 * g + 3), 0);
    for (let ch = 0; ch < 3; ch++) {
      row[6 + ch] = a.sh[0][3 * g + ch];
      for (let c = 1; c < coeffs; c++) row[9 + ch * (coeffs - 1) + c - 1] = a.sh[c][3 * g + ch];
    }
    const o = 9 + 3 * (coeffs - 1);
    const p = Math.min(Math.max(a.opacities[g], 1e-6), 1 - 1e-6);
    row[o] = Math.log(p / (1 - p));
    for (let i = 0; i < 3; i++) row[o + 1 + i] = Math.log(Math.max(a.scales[3 * g + i], 1e-12));
    const q = a.rotations.subarray(4 * g, 4 * g + 4);
    row.set([q[3], q[0], q[1], q[2]], o + 4);
  }
  const out = new Uint8Array(head.length + body.byteLength);
  out.set(head, 0);
  out.set(new Uint8Array(body.buffer), head.length);
  return out;
}

// 3DGS's real SH of degree ≤ 2 at unit vector (x, y, z), in crates/splat/src/sh.rs's order.
function shBasis2(x, y, z, out) {
  const c1 = 0.4886025119029199;
  out[0] = 0.28209479177387814;
  out[1] = -c1 * y; out[2] = c1 * z; out[3] = -c1 * x;
  out[4] = 1.0925484305920792 * x * y;
  out[5] = -1.0925484305920792 * y * z;
  out[6] = 0.31539156525252005 * (2 * z * z - x * x - y * y);
  out[7] = -1.0925484305920792 * x * z;
  out[8] = 0.5462742152960396 * (x * x - y * y);
}

// The light on every splat in a pose (`[n, 3]`), or null for an avatar without one: the
// canonical normal turned by the blend of its bones' skinning matrices, normalised.
function worldShading(a, bones) {
  if (!a.shading) return null;
  const { coefficients, normals } = a.shading;
  const out = new Float32Array(3 * a.n), y = new Float32Array(9);
  const linear = bones.map((m) => m.elements); // column major
  for (let g = 0; g < a.n; g++) {
    const nx = normals[3 * g], ny = normals[3 * g + 1], nz = normals[3 * g + 2];
    let x = 0, yy = 0, z = 0;
    for (let i = 0; i < 4; i++) {
      const w = a.skinWeights[4 * g + i];
      if (w === 0) continue;
      const m = linear[a.skinJoints[4 * g + i]];
      x += w * (m[0] * nx + m[4] * ny + m[8] * nz);
      yy += w * (m[1] * nx + m[5] * ny + m[9] * nz);
      z += w * (m[2] * nx + m[6] * ny + m[10] * nz);
    }
    const length = Math.hypot(x, yy, z) || 1;
    shBasis2(x / length, yy / length, z / length, y);
    for (let c = 0; c < 3; c++) {
      let s = 0;
      for (let k = 0; k < 9; k++) s += y[k] * coefficients[3 * k + c];
      out[3 * g + c] = s;
    }
  }
  return out;
}

// The corrective weights of a pose, from its skinning matrices S_j = W_j · rest_j⁻¹: the
// features R_root⁻¹ R_j − I (row major) of the feature joints, centred, times the map.
function correctiveWeights(a, skinning) {
  const k = a.correctives.length, f = a.featureUsed.length;
  if (k === 0 || f === 0) return new Float32Array(k);
  const rotation = (m) => {
    const r = new THREE.Matrix3().setFromMatrix4(m);
    const e = r.elements; // column major
    for (let c = 0; c < 3; c++) {
      const len = Math.hypot(e[3 * c], e[3 * c + 1], e[3 * c + 2]) || 1;
      for (let i = 0; i < 3; i++) e[3 * c + i] /= len;
    }
    return r;
  };
  const rootInverse = rotation(skinning[a.root]).transpose();
  const all = new Float32Array(9 * a.featureJoints.length);
  a.featureJoints.forEach((j, i) => {
    const r = rootInverse.clone().multiply(rotation(skinning[j])).elements;
    for (let row = 0; row < 3; row++) {
      for (let col = 0; col < 3; col++) {
        all[9 * i + 3 * row + col] = r[3 * col + row] - (row === col ? 1 : 0);
      }
    }
  });
  const weights = new Float32Array(k);
  for (let c = 0; c < k; c++) {
    let w = 0;
    for (let i = 0; i < f; i++) w += a.featureMap[c * f + i] * (all[a.featureUsed[i]] - a.featureMean[i]);
    weights[c] = w;
  }
  return weights;
}

async function main() {
  const params = new URLSearchParams(location.search);
  // `?bare` hides the controls (pictures for comparison), `?paused` starts still.
  if (params.get("bare") !== null) document.body.classList.add("bare");
  const status = document.getElementById("status");
  const avatar = await readAvatar(parseGlb(await fetchBytes("avatar.glb"), "avatar.glb"));
  if (avatar.joints > 256) {
    throw new Error(`the avatar has ${avatar.joints} joints; Spark's skinning takes at most 256`);
  }
  const motions = await (await fetch("motions.json")).json();
  status.textContent = `${avatar.n} Gaussians, ${avatar.joints} joints, ${avatar.correctives.length} correctives`;

  const canvas = document.getElementById("view");
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: false, preserveDrawingBuffer: true });
  renderer.setPixelRatio(1);
  renderer.setClearColor(0xffffff, 1);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0xffffff);
  const spark = new SparkRenderer({ renderer, covSplats: true, accumExtSplats: true });
  scene.add(spark);
  const camera = new THREE.PerspectiveCamera(30, 1, 0.05, 100);
  const floor = new THREE.GridHelper(FLOOR_CELL * 60, 60, 0x8a8a8a, 0xd0d0d0);
  const controls = new OrbitControls(camera, canvas);

  const mesh = new SplatMesh({
    fileBytes: canonicalPly(avatar), fileType: "ply", extSplats: true, covSplats: true,
  });
  await mesh.initialized;
  scene.add(mesh);
  const packed = mesh.extSplats;
  const skinning = new SplatSkinning({
    mesh, numSplats: avatar.n, numBones: avatar.joints, mode: SplatSkinningMode.LINEAR_BLEND,
  });
  const restInverse = avatar.rest.map((m) => m.clone().invert());
  const jv = new THREE.Vector4(), wv = new THREE.Vector4();
  for (let i = 0; i < avatar.n; i++) {
    jv.fromArray(avatar.skinJoints, 4 * i);
    wv.fromArray(avatar.skinWeights, 4 * i);
    skinning.setSplatBones(i, jv, wv);
  }
  mesh.skinning = skinning;
  mesh.updateGenerator();

  // The canonical attributes the correctives and expressions are added to.
  const dc = avatar.sh[0];
  const logScale = Float32Array.from(avatar.scales, (s) => Math.log(Math.max(s, 1e-12)));
  const logit = Float32Array.from(avatar.opacities, (p) => {
    const q = Math.min(Math.max(p, 1e-6), 1 - 1e-6);
    return Math.log(q / (1 - q));
  });
  const center = new THREE.Vector3(), scales = new THREE.Vector3();
  const quaternion = new THREE.Quaternion(), color = new THREE.Color();

  // The camera follows the root across the floor (a walk leaves the view otherwise): moved by
  // the root's horizontal displacement each frame, centred on it when a motion starts. Not
  // while a script holds an exact view (`setView`).
  let followed = null;
  function follow(row) {
    const root = new THREE.Vector3(row[12], row[13], row[14]);
    if (controls.enabled) {
      const d = root.clone().sub(followed ?? controls.target);
      d.y = 0;
      camera.position.add(d);
      controls.target.add(d);
    }
    followed = root;
    // The floor's lines stay put under a walk: moved by whole cells only.
    floor.position.x = Math.round(root.x / FLOOR_CELL) * FLOOR_CELL;
    floor.position.z = Math.round(root.z / FLOOR_CELL) * FLOOR_CELL;
  }

  // A motion is framed as a whole when it starts: the heights its joints reach over all its
  // frames (a kneel, a jump, arms overhead), with room for the soles below the ankles and the
  // skull above the head joint, fill the view's height from the current direction. Not while
  // a script holds an exact view (`setView`).
  function frameMotion(data, count) {
    if (!controls.enabled || count === 0) return;
    let low = Infinity, high = -Infinity;
    for (let f = 0; f < count; f++) {
      for (let j = 0; j < avatar.joints; j++) {
        const y = data[f * stride + 16 * j + 13];
        low = Math.min(low, y);
        high = Math.max(high, y);
      }
    }
    // Room below for the soles, a foot nearer the camera and the control bar; above for the
    // skull over the head joint.
    low = Math.min(low, floor.position.y) - 0.3;
    high += 0.3;
    const root = new THREE.Vector3(data[12], data[13], data[14]);
    const target = new THREE.Vector3(root.x, (low + high) / 2, root.z);
    // From at least 8° above, so that the floor shows as a floor.
    const along = camera.position.clone().sub(controls.target).normalize();
    if (along.y < 0.14) along.setY(0.14).normalize();
    const fit = (1.15 * (high - low)) / 2 / Math.tan(THREE.MathUtils.degToRad(camera.fov / 2));
    controls.target.copy(target);
    camera.position.copy(target).addScaledVector(along, Math.max(fit, 1.0));
    followed = root;
  }

  let motion = null, frames = 0, stride = 0;
  async function loadMotion(index) {
    const m = motions[index];
    const data = new Float32Array(await fetchBytes(m.url));
    stride = 16 * avatar.joints + avatar.expressions.length;
    if (data.length !== m.frames * stride) {
      throw new Error(`${m.url}: ${data.length} values for ${m.frames} frames of ${stride}`);
    }
    motion = { ...m, data };
    frames = m.frames;
    followed = null;
    frameMotion(data, frames);
    const slider = document.getElementById("frame");
    slider.max = String(Math.max(frames - 1, 0));
    showFrame(0);
  }

  function showFrame(f) {
    f = Math.min(Math.max(Math.round(f), 0), Math.max(frames - 1, 0));
    state.frame = f;
    const row = motion.data.subarray(f * stride, (f + 1) * stride);
    follow(row);
    const bones = [];
    for (let j = 0; j < avatar.joints; j++) {
      const m = new THREE.Matrix4().fromArray(row, 16 * j).multiply(restInverse[j]);
      skinning.setBoneMatrix(j, m);
      bones.push(m);
    }
    skinning.updateBones();
    const w = correctiveWeights(avatar, bones);
    const light = worldShading(avatar, bones);
    const e = row.subarray(16 * avatar.joints);
    for (let g = 0; g < avatar.n; g++) {
      let x = avatar.means[3 * g], y = avatar.means[3 * g + 1], z = avatar.means[3 * g + 2];
      let r = dc[3 * g], gr = dc[3 * g + 1], b = dc[3 * g + 2];
      let s0 = logScale[3 * g], s1 = logScale[3 * g + 1], s2 = logScale[3 * g + 2];
      let o = logit[g];
      for (let c = 0; c < w.length; c++) {
        const k = avatar.correctives[c], wc = w[c];
        if (wc === 0) continue;
        x += wc * k.position[3 * g]; y += wc * k.position[3 * g + 1]; z += wc * k.position[3 * g + 2];
        r += wc * k.colour[3 * g] / C0; gr += wc * k.colour[3 * g + 1] / C0; b += wc * k.colour[3 * g + 2] / C0;
        s0 += wc * k.logScale[3 * g]; s1 += wc * k.logScale[3 * g + 1]; s2 += wc * k.logScale[3 * g + 2];
        o += wc * k.opacityLogit[g];
      }
      for (let i = 0; i < e.length; i++) {
        if (e[i] === 0) continue;
        const d = avatar.expressions[i];
        x += e[i] * d[3 * g]; y += e[i] * d[3 * g + 1]; z += e[i] * d[3 * g + 2];
      }
      center.set(x, y, z);
      scales.set(Math.exp(s0), Math.exp(s1), Math.exp(s2));
      const q = avatar.rotations;
      quaternion.set(q[4 * g], q[4 * g + 1], q[4 * g + 2], q[4 * g + 3]);
      if (light) {
        color.setRGB((0.5 + C0 * r) * light[3 * g], (0.5 + C0 * gr) * light[3 * g + 1],
          (0.5 + C0 * b) * light[3 * g + 2], THREE.LinearSRGBColorSpace);
      } else {
        color.setRGB(0.5 + C0 * r, 0.5 + C0 * gr, 0.5 + C0 * b, THREE.LinearSRGBColorSpace);
      }
      packed.setSplat(g, center, scales, quaternion, 1 / (1 + Math.exp(-o)), color);
    }
    packed.needsUpdate = true;
    mesh.updateVersion();
    document.getElementById("frame").value = String(f);
    document.getElementById("frameText").textContent = `${f} / ${frames}`;
  }

  function fitView(width, height) {
    renderer.setSize(width, height, false);
    camera.aspect = width / height;
    camera.updateProjectionMatrix();
  }
  // Frame the avatar: the box of its canonical means.
  const box = new THREE.Box3().setFromArray(avatar.means);
  const middle = box.getCenter(new THREE.Vector3());
  // The floor: a grid at the canonical avatar's lowest point, where retargeting puts the feet
  // (docs/motions.md, rule 6), so that floating and sinking show. Left out of `?bare`
  // pictures, which are compared with f3g's renders.
  floor.position.set(middle.x, box.min.y, middle.z);
  floor.visible = !document.body.classList.contains("bare");
  scene.add(floor);
  camera.position.set(middle.x, middle.y, middle.z + 4.0);
  controls.target.copy(middle);
  controls.update();
  fitView(canvas.clientWidth || 640, canvas.clientHeight || 480);
  window.addEventListener("resize", () => fitView(canvas.clientWidth, canvas.clientHeight));

  // Exact views for scripts and tests: eye, target (world), vertical field of view (deg).
  state.setView = (eye, target, fovDeg, width, height) => {
    controls.enabled = false;
    camera.fov = fovDeg;
    camera.up.set(0, 1, 0);
    camera.position.set(...eye);
    camera.lookAt(new THREE.Vector3(...target));
    fitView(width, height);
  };
  state.setFrame = (f) => { playing = false; showFrame(f); };
  state.rendered = 0;

  let playing = params.get("paused") === null;
  document.getElementById("play").textContent = playing ? "pause" : "play";
  let speed = 1, clock = 0, last = performance.now(), counted = 0, since = last;
  document.getElementById("play").onclick = () => {
    playing = !playing;
    document.getElementById("play").textContent = playing ? "pause" : "play";
  };
  document.getElementById("frame").oninput = (ev) => { playing = false; showFrame(Number(ev.target.value)); };
  document.getElementById("speed").onchange = (ev) => { speed = Number(ev.target.value); };
  const picker = document.getElementById("motion");
  motions.forEach((m, i) => picker.add(new Option(`${m.name} (${m.frames})`, String(i))));
  picker.onchange = (ev) => loadMotion(Number(ev.target.value)).catch((e) => fail(e.message));
  if (motions.length === 0) throw new Error("the server lists no motion");
  await loadMotion(0);
  if (params.get("frame") !== null) showFrame(Number(params.get("frame")));

  renderer.setAnimationLoop((now) => {
    const dt = (now - last) / 1000;
    last = now;
    if (playing && frames > 1) {
      clock += dt * speed * (motion.fps || 15);
      const f = Math.floor(clock) % frames;
      if (f !== state.frame) showFrame(f);
    }
    if (controls.enabled) controls.update();
    renderer.render(scene, camera);
    state.rendered += 1;
    counted += 1;
    if (now - since > 1000) {
      state.fps = (counted * 1000) / (now - since);
      document.getElementById("fps").textContent = `${state.fps.toFixed(1)} fps`;
      counted = 0;
      since = now;
    }
    if (!state.ready && state.rendered > 2) {
      state.ready = true;
      document.getElementById("status").textContent += " — ready";
    }
  });
}

main().catch((e) => fail(e.message ?? e));
