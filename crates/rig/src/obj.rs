//! Wavefront OBJ meshes: positions and faces only (texture and normal indices are ignored,
//! polygons are fanned into triangles).

use std::fmt::Write;
use std::path::Path;

use glam::Vec3;

use crate::RigError;
use crate::rig::Mesh;

/// Writes a triangle mesh, atomically.
pub fn write_obj(path: &Path, vertices: &[Vec3], triangles: &[[u32; 3]]) -> Result<(), RigError> {
    let mut s = String::with_capacity(40 * (vertices.len() + triangles.len()));
    s.push_str("# written by f3g\n");
    for v in vertices {
        let _ = writeln!(s, "v {} {} {}", v.x, v.y, v.z);
    }
    for t in triangles {
        let _ = writeln!(s, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    f3g_io::write_atomic(path, s.as_bytes()).map_err(|e| RigError::File {
        file: e.path,
        reason: e.reason,
    })
}

/// Reads an OBJ file.
pub fn read_obj(path: &Path) -> Result<Mesh, RigError> {
    let text = std::fs::read_to_string(path).map_err(|e| RigError::file(path, e))?;
    parse_obj(&text, path)
}

/// Parses OBJ text; `path` labels errors.
pub fn parse_obj(text: &str, path: &Path) -> Result<Mesh, RigError> {
    let err = |line: usize, reason: String| RigError::Line {
        file: path.to_path_buf(),
        line,
        reason,
    };
    let mut mesh = Mesh::default();
    let mut faces: Vec<(usize, Vec<i64>)> = Vec::new();
    for (n, line) in text.lines().enumerate().map(|(i, l)| (i + 1, l.trim())) {
        let mut words = line.split_whitespace();
        match words.next() {
            Some("v") => {
                let xyz: Vec<f32> = words
                    .take(3)
                    .map(|w| {
                        w.parse::<f32>()
                            .map_err(|_| err(n, format!("{} is not a number", f3g_io::quoted(w))))
                    })
                    .collect::<Result<_, _>>()?;
                if xyz.len() != 3 || xyz.iter().any(|v| !v.is_finite()) {
                    return Err(err(n, "a vertex needs three finite coordinates".into()));
                }
                mesh.vertices.push(Vec3::new(xyz[0], xyz[1], xyz[2]));
            }
            Some("f") => {
                let idx: Vec<i64> = words
                    .map(|w| {
                        w.split('/')
                            .next()
                            .unwrap_or("")
                            .parse::<i64>()
                            .map_err(|_| err(n, format!("bad face index {}", f3g_io::quoted(w))))
                    })
                    .collect::<Result<_, _>>()?;
                if idx.len() < 3 {
                    return Err(err(n, "a face needs at least three vertices".into()));
                }
                faces.push((n, idx));
            }
            _ => {}
        }
    }
    let count = mesh.vertices.len() as i64;
    for (n, idx) in faces {
        // 1-based, or negative = relative to the end.
        let resolved: Vec<u32> = idx
            .iter()
            .map(|&i| {
                let r = if i < 0 { count + i } else { i - 1 };
                if r < 0 || r >= count {
                    Err(err(n, format!("face index {i} is outside 1..={count}")))
                } else {
                    Ok(r as u32)
                }
            })
            .collect::<Result<_, _>>()?;
        for k in 1..resolved.len() - 1 {
            mesh.triangles
                .push([resolved[0], resolved[k], resolved[k + 1]]);
        }
    }
    if mesh.vertices.is_empty() || mesh.triangles.is_empty() {
        return Err(RigError::file(path, "the mesh has no vertices or no faces"));
    }
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_quads() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.obj");
        let v = vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::Z];
        write_obj(&p, &v, &[[0, 1, 2], [0, 2, 3]]).unwrap();
        let m = read_obj(&p).unwrap();
        assert_eq!(m.vertices, v);
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);
        let quad = parse_obj(
            "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1 -1/1\n",
            Path::new("q.obj"),
        )
        .unwrap();
        assert_eq!(quad.triangles, vec![[0, 1, 2], [0, 2, 3]]);
    }

    #[test]
    fn errors_name_the_line() {
        let e = parse_obj("v 0 0 0\nv 1 0\n", Path::new("b.obj"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("b.obj:2:"), "{e}");
        let e = parse_obj("v 0 0 0\nf 1 2 3\n", Path::new("b.obj"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("b.obj:2: face index 2 is outside"), "{e}");
        assert!(
            parse_obj("# nothing\n", Path::new("e.obj"))
                .unwrap_err()
                .to_string()
                .contains("no vertices")
        );
    }
}
