//! Writing binary glTF (`.glb`): one binary buffer that accessors are appended to, and the
//! JSON document around it. Used to export rigs ([`crate::gltf::write`]) and anything else f3g
//! writes as glTF.
//!
//! Layout: a 12-byte header (`glTF`, version 2, total length), a JSON chunk padded with spaces
//! and a BIN chunk padded with zeros to 4 bytes; every buffer view starts on a 4-byte
//! boundary, so every accessor is aligned for its component type.

use serde_json::{Value, json};

/// glTF component types.
pub const FLOAT: u32 = 5126;
pub const UNSIGNED_INT: u32 = 5125;
pub const UNSIGNED_SHORT: u32 = 5123;
pub const UNSIGNED_BYTE: u32 = 5121;

/// A value type one accessor element can hold, with its glTF component type.
pub trait Component: Copy {
    const TYPE: u32;
    fn bytes(self) -> Vec<u8>;
}

impl Component for f32 {
    const TYPE: u32 = FLOAT;
    fn bytes(self) -> Vec<u8> {
        self.to_le_bytes().to_vec()
    }
}

impl Component for u32 {
    const TYPE: u32 = UNSIGNED_INT;
    fn bytes(self) -> Vec<u8> {
        self.to_le_bytes().to_vec()
    }
}

impl Component for u16 {
    const TYPE: u32 = UNSIGNED_SHORT;
    fn bytes(self) -> Vec<u8> {
        self.to_le_bytes().to_vec()
    }
}

impl Component for u8 {
    const TYPE: u32 = UNSIGNED_BYTE;
    fn bytes(self) -> Vec<u8> {
        vec![self]
    }
}

/// Accessors and buffer views over one binary buffer.
#[derive(Default)]
pub struct GlbBuffer {
    bin: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

impl GlbBuffer {
    /// Appends `values` as an accessor of `kind` (`SCALAR`, `VEC3`, `MAT4`, …, whose width
    /// `values.len()` must be a multiple of) and returns its index. `bounds` adds the per-component
    /// `min`/`max` that glTF requires of POSITION accessors. `target` is the buffer view's
    /// target (34962 vertex attributes, 34963 indices), if any.
    pub fn accessor<T: Component>(
        &mut self,
        values: &[T],
        kind: &str,
        bounds: bool,
        target: Option<u32>,
    ) -> usize
    where
        f64: From<T>,
    {
        let width = match kind {
            "SCALAR" => 1,
            "VEC2" => 2,
            "VEC3" => 3,
            "VEC4" => 4,
            "MAT4" => 16,
            other => panic!("unknown accessor type {other}"),
        };
        assert!(values.len().is_multiple_of(width), "{kind} accessor");
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        for v in values {
            self.bin.extend(v.bytes());
        }
        let mut view = json!({
            "buffer": 0,
            "byteOffset": offset,
            "byteLength": self.bin.len() - offset,
        });
        if let Some(t) = target {
            view["target"] = json!(t);
        }
        self.views.push(view);
        let mut accessor = json!({
            "bufferView": self.views.len() - 1,
            "componentType": T::TYPE,
            "count": values.len() / width,
            "type": kind,
        });
        if bounds {
            set_bounds(&mut accessor, values, width);
        }
        self.accessors.push(accessor);
        self.accessors.len() - 1
    }

    /// Like [`Self::accessor`] for unsigned bytes read as `value / 255` (glTF's `normalized`,
    /// as quantised `WEIGHTS_0` are).
    pub fn normalized_bytes(&mut self, values: &[u8], kind: &str, target: Option<u32>) -> usize {
        let index = self.accessor(values, kind, false, target);
        self.accessors[index]["normalized"] = json!(true);
        index
    }

    /// An accessor of `count` float elements of `kind` without a buffer view: its values come
    /// from an extension (a compressed payload), and a reader that knows none sees zeros.
    /// `bounds_of` are the values it stands for (`count` elements), whose per-component `min`
    /// and `max` glTF requires of POSITION.
    pub fn placeholder(&mut self, count: usize, kind: &str, bounds_of: Option<&[f32]>) -> usize {
        let mut accessor = json!({ "componentType": FLOAT, "count": count, "type": kind });
        if let Some(values) = bounds_of {
            set_bounds(&mut accessor, values, values.len() / count.max(1));
        }
        self.accessors.push(accessor);
        self.accessors.len() - 1
    }

    /// The `.glb` bytes of `document` (its `buffers`, `bufferViews` and `accessors` are set
    /// from this buffer).
    pub fn finish(self, mut document: Value) -> Vec<u8> {
        document["buffers"] = json!([{ "byteLength": self.bin.len().next_multiple_of(4) }]);
        document["bufferViews"] = Value::Array(self.views);
        document["accessors"] = Value::Array(self.accessors);
        glb_bytes(&document, self.bin)
    }
}

/// Sets an accessor's per-component `min` and `max` over `values` (`width` per element);
/// nothing for no values.
fn set_bounds<T: Copy>(accessor: &mut Value, values: &[T], width: usize)
where
    f64: From<T>,
{
    if values.is_empty() || width == 0 {
        return;
    }
    let mut min = vec![f64::INFINITY; width];
    let mut max = vec![f64::NEG_INFINITY; width];
    for row in values.chunks_exact(width) {
        for (k, &v) in row.iter().enumerate() {
            min[k] = min[k].min(f64::from(v));
            max[k] = max[k].max(f64::from(v));
        }
    }
    accessor["min"] = json!(min);
    accessor["max"] = json!(max);
}

/// The `.glb` container of a document and its binary chunk (padded to 4 bytes).
fn glb_bytes(document: &Value, mut bin: Vec<u8>) -> Vec<u8> {
    bin.resize(bin.len().next_multiple_of(4), 0);
    let mut text = serde_json::to_vec(document).expect("serialisable");
    while !text.len().is_multiple_of(4) {
        text.push(b' ');
    }
    let total = 12 + 8 + text.len() + 8 + bin.len();
    let mut out = Vec::with_capacity(total);
    out.extend(b"glTF");
    out.extend(2u32.to_le_bytes());
    out.extend((total as u32).to_le_bytes());
    out.extend((text.len() as u32).to_le_bytes());
    out.extend(b"JSON");
    out.extend(text);
    out.extend((bin.len() as u32).to_le_bytes());
    out.extend(b"BIN\0");
    out.extend(bin);
    out
}

/// The nodes of a skinned character: one per joint of `skeleton` (its local transform from
/// `transform`: `translation`, `rotation`, optionally `scale`), children listed, then a node
/// holding mesh 0 with skin 0; and the scene's root nodes.
pub fn skinned_nodes(
    skeleton: &crate::Skeleton,
    transform: impl Fn(usize) -> Value,
    mesh_name: &str,
) -> (Vec<Value>, Vec<usize>) {
    let joints = skeleton.joints();
    let mut nodes: Vec<Value> = joints
        .iter()
        .enumerate()
        .map(|(i, joint)| {
            let mut node = transform(i);
            node["name"] = json!(joint.name);
            node
        })
        .collect();
    for (i, joint) in joints.iter().enumerate() {
        if let Some(p) = joint.parent {
            nodes[p]
                .as_object_mut()
                .expect("a node is an object")
                .entry("children")
                .or_insert_with(|| json!([]))
                .as_array_mut()
                .expect("children are an array")
                .push(json!(i));
        }
    }
    let mesh_node = nodes.len();
    nodes.push(json!({ "name": mesh_name, "mesh": 0, "skin": 0 }));
    let roots = joints
        .iter()
        .enumerate()
        .filter(|(_, j)| j.parent.is_none())
        .map(|(i, _)| i)
        .chain([mesh_node])
        .collect();
    (nodes, roots)
}

/// A binary glTF read back: its JSON document and binary chunk, with typed accessors that
/// check every offset and count against the buffer (a damaged file is an error, never a
/// panic or a huge allocation).
pub struct GlbFile {
    pub document: Value,
    bin: Vec<u8>,
}

impl GlbFile {
    /// Parses `.glb` bytes (header, JSON chunk, optional BIN chunk).
    pub fn parse(bytes: &[u8]) -> Result<Self, String> {
        let word = |at: usize| -> Result<u32, String> {
            bytes
                .get(at..at + 4)
                .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .ok_or_else(|| "truncated: the file ends inside its header".to_string())
        };
        if bytes.get(..4) != Some(b"glTF") {
            return Err("not a binary glTF file (no `glTF` magic)".into());
        }
        if word(4)? != 2 {
            return Err(format!("glTF version {}, expected 2", word(4)?));
        }
        let total = word(8)? as usize;
        if total > bytes.len() {
            return Err(format!(
                "truncated: the header says {total} bytes, the file has {}",
                bytes.len()
            ));
        }
        let (mut at, mut json, mut bin) = (12usize, None, Vec::new());
        while at + 8 <= total {
            let (length, kind) = (word(at)? as usize, word(at + 4)?);
            let chunk = bytes
                .get(at + 8..at + 8 + length)
                .filter(|_| at + 8 + length <= total)
                .ok_or_else(|| format!("truncated: a chunk of {length} bytes runs past the end"))?;
            match kind {
                0x4E4F534A => {
                    json = Some(
                        serde_json::from_slice::<Value>(chunk)
                            .map_err(|e| format!("the JSON chunk is not valid JSON: {e}"))?,
                    );
                }
                0x004E4942 => bin = chunk.to_vec(),
                _ => {}
            }
            at += 8 + length;
        }
        let document = json.ok_or("no JSON chunk")?;
        Ok(Self { document, bin })
    }

    /// The bytes of accessor `index` (tightly packed, as this module writes them) and its
    /// element count, for components of `size` bytes, `width` per element.
    fn accessor_bytes(
        &self,
        index: usize,
        component: u32,
        size: usize,
        width: usize,
    ) -> Result<(&[u8], usize), String> {
        let a = self
            .document
            .pointer(&format!("/accessors/{index}"))
            .ok_or_else(|| format!("accessor {index} does not exist"))?;
        if a["componentType"].as_u64() != Some(u64::from(component)) {
            return Err(format!(
                "accessor {index} has component type {}, expected {component}",
                a["componentType"]
            ));
        }
        let count = a["count"]
            .as_u64()
            .ok_or_else(|| format!("accessor {index} has no count"))? as usize;
        let view_index = a["bufferView"]
            .as_u64()
            .ok_or_else(|| format!("accessor {index} has no buffer view"))?;
        let view = self
            .document
            .pointer(&format!("/bufferViews/{view_index}"))
            .ok_or_else(|| format!("buffer view {view_index} does not exist"))?;
        if view.get("byteStride").is_some_and(|s| !s.is_null()) {
            return Err(format!("buffer view {view_index} is interleaved"));
        }
        let start = view["byteOffset"].as_u64().unwrap_or(0) as usize
            + a["byteOffset"].as_u64().unwrap_or(0) as usize;
        let length = count
            .checked_mul(size * width)
            .filter(|&l| l <= self.bin.len())
            .ok_or_else(|| {
                format!("accessor {index} has count {count}, more than the buffer holds")
            })?;
        let bytes = start
            .checked_add(length)
            .and_then(|end| self.bin.get(start..end))
            .ok_or_else(|| format!("accessor {index} runs past the end of the buffer"))?;
        Ok((bytes, count))
    }

    /// The file's bytes again (after editing its document).
    pub fn to_bytes(&self) -> Vec<u8> {
        glb_bytes(&self.document, self.bin.clone())
    }

    /// Float accessor `index` with `width` components per element, flattened.
    pub fn floats(&self, index: usize, width: usize) -> Result<Vec<f32>, String> {
        let (bytes, _) = self.accessor_bytes(index, FLOAT, 4, width)?;
        Ok(bytes
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect())
    }

    /// Unsigned short accessor `index`, flattened.
    pub fn shorts(&self, index: usize, width: usize) -> Result<Vec<u16>, String> {
        let (bytes, _) = self.accessor_bytes(index, UNSIGNED_SHORT, 2, width)?;
        Ok(bytes
            .chunks_exact(2)
            .map(|b| u16::from_le_bytes([b[0], b[1]]))
            .collect())
    }

    /// Unsigned int accessor `index`, flattened.
    pub fn ints(&self, index: usize, width: usize) -> Result<Vec<u32>, String> {
        let (bytes, _) = self.accessor_bytes(index, UNSIGNED_INT, 4, width)?;
        Ok(bytes
            .chunks_exact(4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect())
    }

    /// Unsigned byte accessor `index`, flattened, and whether it is `normalized`.
    pub fn bytes(&self, index: usize, width: usize) -> Result<(Vec<u8>, bool), String> {
        let (bytes, _) = self.accessor_bytes(index, UNSIGNED_BYTE, 1, width)?;
        let normalized = self.document["accessors"][index]["normalized"] == json!(true);
        Ok((bytes.to_vec(), normalized))
    }

    /// The component type of accessor `index`, if it has one.
    pub fn component_type(&self, index: usize) -> Option<u32> {
        self.document["accessors"][index]["componentType"]
            .as_u64()
            .map(|t| t as u32)
    }

    /// Bytes in the binary chunk.
    pub fn bin_len(&self) -> usize {
        self.bin.len()
    }

    /// The bytes of buffer view `index` (e.g. an embedded file).
    pub fn view(&self, index: usize) -> Result<&[u8], String> {
        let view = self
            .document
            .pointer(&format!("/bufferViews/{index}"))
            .ok_or_else(|| format!("buffer view {index} does not exist"))?;
        let start = view["byteOffset"].as_u64().unwrap_or(0) as usize;
        let length = view["byteLength"].as_u64().unwrap_or(0) as usize;
        start
            .checked_add(length)
            .and_then(|end| self.bin.get(start..end))
            .ok_or_else(|| format!("buffer view {index} runs past the end of the buffer"))
    }
}

impl GlbBuffer {
    /// Appends raw bytes as a buffer view (e.g. an embedded file) and returns its index.
    pub fn view(&mut self, bytes: &[u8]) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        self.views.push(json!({
            "buffer": 0,
            "byteOffset": self.bin.len(),
            "byteLength": bytes.len(),
        }));
        self.bin.extend_from_slice(bytes);
        self.views.len() - 1
    }
}
