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
        if bounds && !values.is_empty() {
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
        self.accessors.push(accessor);
        self.accessors.len() - 1
    }

    /// The `.glb` bytes of `document` (its `buffers`, `bufferViews` and `accessors` are set
    /// from this buffer).
    pub fn finish(mut self, mut document: Value) -> Vec<u8> {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        document["buffers"] = json!([{ "byteLength": self.bin.len() }]);
        document["bufferViews"] = Value::Array(self.views);
        document["accessors"] = Value::Array(self.accessors);
        let mut text = serde_json::to_vec(&document).expect("serialisable");
        while !text.len().is_multiple_of(4) {
            text.push(b' ');
        }
        let total = 12 + 8 + text.len() + 8 + self.bin.len();
        let mut out = Vec::with_capacity(total);
        out.extend(b"glTF");
        out.extend(2u32.to_le_bytes());
        out.extend((total as u32).to_le_bytes());
        out.extend((text.len() as u32).to_le_bytes());
        out.extend(b"JSON");
        out.extend(text);
        out.extend((self.bin.len() as u32).to_le_bytes());
        out.extend(b"BIN\0");
        out.extend(self.bin);
        out
    }
}
