//! What the glTF tests share: a builder of small glTF files (buffer, views and
//! accessors written by hand) and a one-triangle mesh.
#![allow(dead_code)] // each test binary uses its own part

use std::path::{Path, PathBuf};

use glam::Vec3;

/// A fresh folder for one test (tests run in parallel, so each gets its own).
pub fn test_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("dray-gltf-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Builds the binary buffer, buffer views and accessors of a test file.
#[derive(Default)]
pub struct Builder {
    pub bin: Vec<u8>,
    pub views: Vec<String>,
    pub accessors: Vec<String>,
}

impl Builder {
    pub fn view(&mut self, bytes: &[u8]) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.views.push(format!(
            r#"{{"buffer":0,"byteOffset":{offset},"byteLength":{}}}"#,
            bytes.len()
        ));
        self.views.len() - 1
    }

    /// A float accessor of `ty` ("VEC3", ...); VEC3 ones get min/max (POSITION needs them).
    pub fn floats(&mut self, data: &[f32], ty: &str) -> usize {
        let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&bytes);
        let dims = match ty {
            "SCALAR" => 1,
            "VEC2" => 2,
            "VEC3" => 3,
            _ => 4,
        };
        let minmax = if dims == 3 {
            let mut lo = [f32::INFINITY; 3];
            let mut hi = [f32::NEG_INFINITY; 3];
            for v in data.chunks(3) {
                for c in 0..3 {
                    if v[c].is_finite() {
                        lo[c] = lo[c].min(v[c]);
                        hi[c] = hi[c].max(v[c]);
                    }
                }
            }
            format!(r#","min":{lo:?},"max":{hi:?}"#)
        } else {
            String::new()
        };
        self.accessors.push(format!(
            r#"{{"bufferView":{view},"componentType":5126,"count":{},"type":"{ty}"{minmax}}}"#,
            data.len() / dims
        ));
        self.accessors.len() - 1
    }

    pub fn indices(&mut self, data: &[u16]) -> usize {
        let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&bytes);
        self.accessors.push(format!(
            r#"{{"bufferView":{view},"componentType":5123,"count":{},"type":"SCALAR"}}"#,
            data.len()
        ));
        self.accessors.len() - 1
    }

    /// The complete JSON with one buffer at `uri` and the given extra top-level members.
    pub fn json(&self, uri: Option<&str>, rest: &str) -> String {
        let uri = uri.map(|u| format!(r#""uri":"{u}","#)).unwrap_or_default();
        format!(
            r#"{{"asset":{{"version":"2.0"}},"buffers":[{{{uri}"byteLength":{}}}],"bufferViews":[{}],"accessors":[{}],{rest}}}"#,
            self.bin.len(),
            self.views.join(","),
            self.accessors.join(",")
        )
    }

    /// Write `name.gltf` and `name.bin` into `dir` and return the .gltf path.
    pub fn write(&self, dir: &Path, name: &str, rest: &str) -> PathBuf {
        std::fs::write(dir.join(format!("{name}.bin")), &self.bin).unwrap();
        let path = dir.join(format!("{name}.gltf"));
        std::fs::write(&path, self.json(Some(&format!("{name}.bin")), rest)).unwrap();
        path
    }
}

pub const TRI_POS: [f32; 9] = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0];

pub fn approx(a: Vec3, b: Vec3) -> bool {
    (a - b).length() < 1e-5
}

/// One triangle mesh "Tri" with POSITION (0), NORMAL (1), TANGENT (2) and indices (3).
pub fn triangle_builder() -> Builder {
    let mut b = Builder::default();
    b.floats(&TRI_POS, "VEC3");
    b.floats(&[0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0], "VEC3");
    b.floats(&[1.0, 0.0, 0.0, 1.0].repeat(3), "VEC4");
    b.indices(&[0, 1, 2]);
    b
}

pub const TRI_MESH: &str = r#""meshes":[{"name":"Tri","primitives":[{"attributes":{"POSITION":0,"NORMAL":1,"TANGENT":2},"indices":3}]}]"#;
