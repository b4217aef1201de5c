//! Triangle meshes: the one geometric representation the simulator's light transport
//! works on, with builders for the primitive shapes scenes are made of and loaders for
//! OBJ (tobj) and PLY (ply-rs-bw) files.
use std::path::Path;

use glam::{DMat3, DVec3};

/// An indexed triangle mesh.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions, metres.
    pub vertices: Vec<DVec3>,
    /// Triangles as vertex indices, counter-clockwise seen from the front.
    pub triangles: Vec<[u32; 3]>,
}

/// Why a mesh file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    /// The file could not be read or parsed.
    #[error("mesh file {path}: {message}")]
    File {
        /// The file.
        path: String,
        /// What went wrong.
        message: String,
    },
}

impl Mesh {
    /// Appends `other`.
    pub fn append(&mut self, other: &Mesh) {
        let base = self.vertices.len() as u32;
        self.vertices.extend(&other.vertices);
        self.triangles
            .extend(other.triangles.iter().map(|t| t.map(|i| i + base)));
    }

    /// The mesh rotated by `r` then moved by `t`.
    pub fn transformed(&self, r: DMat3, t: DVec3) -> Mesh {
        Mesh {
            vertices: self.vertices.iter().map(|v| r * *v + t).collect(),
            triangles: self.triangles.clone(),
        }
    }

    /// Corners of triangle `i`.
    pub fn corners(&self, i: usize) -> [DVec3; 3] {
        self.triangles[i].map(|k| self.vertices[k as usize])
    }

    /// Unit normal of triangle `i` (zero for a degenerate one).
    pub fn normal(&self, i: usize) -> DVec3 {
        let [a, b, c] = self.corners(i);
        (b - a).cross(c - a).normalize_or_zero()
    }

    /// Area of triangle `i`.
    pub fn area(&self, i: usize) -> f64 {
        let [a, b, c] = self.corners(i);
        0.5 * (b - a).cross(c - a).length()
    }

    /// Total area.
    pub fn total_area(&self) -> f64 {
        (0..self.triangles.len()).map(|i| self.area(i)).sum()
    }

    /// A rectangle in the xy plane, `[x0, x1] × [y0, y1]` at z = 0, facing +z.
    pub fn rectangle(x: [f64; 2], y: [f64; 2]) -> Mesh {
        Mesh {
            vertices: vec![
                DVec3::new(x[0], y[0], 0.0),
                DVec3::new(x[1], y[0], 0.0),
                DVec3::new(x[1], y[1], 0.0),
                DVec3::new(x[0], y[1], 0.0),
            ],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
        }
    }

    /// A parametric surface `f(u, v)`, u and v in [0, 1], on an `nu × nv` grid of quads.
    pub fn parametric(nu: usize, nv: usize, f: impl Fn(f64, f64) -> DVec3) -> Mesh {
        let (nu, nv) = (nu.max(1), nv.max(1));
        let mut m = Mesh::default();
        for j in 0..=nv {
            for i in 0..=nu {
                m.vertices.push(f(i as f64 / nu as f64, j as f64 / nv as f64));
            }
        }
        let at = |i: usize, j: usize| (j * (nu + 1) + i) as u32;
        for j in 0..nv {
            for i in 0..nu {
                m.triangles.push([at(i, j), at(i + 1, j), at(i + 1, j + 1)]);
                m.triangles.push([at(i, j), at(i + 1, j + 1), at(i, j + 1)]);
            }
        }
        m
    }

    /// An axis-aligned box centred at the origin with half extents `h`.
    pub fn cuboid(h: DVec3) -> Mesh {
        let mut m = Mesh::default();
        for axis in 0..3 {
            for sign in [-1.0, 1.0] {
                let n = DVec3::from_array(std::array::from_fn(|k| if k == axis { sign } else { 0.0 }));
                let u = DVec3::from_array(std::array::from_fn(
                    |k| if k == (axis + 1) % 3 { 1.0 } else { 0.0 },
                ));
                let v = n.cross(u);
                let face = Mesh::parametric(1, 1, |a, b| (n + u * (2.0 * a - 1.0) + v * (2.0 * b - 1.0)) * h);
                m.append(&face);
            }
        }
        m
    }

    /// An ellipsoid with semi-axes `h`, `n` segments around.
    pub fn ellipsoid(h: DVec3, n: usize) -> Mesh {
        Mesh::parametric(n, n / 2, |u, v| {
            let (phi, theta) = (u * std::f64::consts::TAU, v * std::f64::consts::PI);
            DVec3::new(theta.sin() * phi.cos(), theta.sin() * phi.sin(), -theta.cos()) * h
        })
    }

    /// A closed capsule-free cylinder of `radius` from `a` to `b` (side only; its ends
    /// are hidden inside the figures that use it or too small to matter).
    pub fn cylinder(a: DVec3, b: DVec3, radius: f64, n: usize) -> Mesh {
        let axis = b - a;
        // glam's `any_orthonormal_vector` wants a unit vector: given the axis itself,
        // it tilted each ring and shrank the radius (a mannequin's arm 15 mm across
        // instead of 35 until 2026-12-07).
        let dir = axis.normalize();
        let u = dir.any_orthonormal_vector();
        let v = dir.cross(u);
        Mesh::parametric(n, 1, |s, t| {
            let phi = s * std::f64::consts::TAU;
            a + axis * t + (u * phi.cos() + v * phi.sin()) * radius
        })
    }

    /// Loads an OBJ or PLY file (by extension); all objects/faces are merged, polygons
    /// triangulated. Files over [`MAX_MESH_FILE_BYTES`] are refused unread; an OBJ's
    /// `mtllib` is never followed (materials are not used, and a scene file must not
    /// make the daemon open other paths).
    pub fn load(path: &Path) -> Result<Mesh, MeshError> {
        let err = |message: String| MeshError::File {
            path: path.display().to_string(),
            message,
        };
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .unwrap_or("")
            .to_ascii_lowercase();
        if ext != "obj" && ext != "ply" {
            return Err(err(format!("unknown mesh format `.{ext}`: use .obj or .ply")));
        }
        let bytes = read_mesh_file(path).map_err(err)?;
        if ext == "obj" {
            Mesh::from_obj_bytes(&bytes)
        } else {
            Mesh::from_ply_bytes(&bytes)
        }
        .map_err(err)
    }

    /// Decodes an OBJ file held in memory (no materials; `mtllib` is ignored).
    pub fn from_obj_bytes(bytes: &[u8]) -> Result<Mesh, String> {
        let options = tobj::LoadOptions {
            triangulate: true,
            single_index: true,
            ..Default::default()
        };
        // A scene uses positions and faces only. tobj trusts a face's texture and
        // normal indices in its arithmetic (the `mesh` fuzz target found a relative
        // texture index before the first coordinate that overflows it, a panic where
        // overflow is checked), so it is given no texture coordinates or normals to
        // look up; and any other panic in it is this file's error, never a crash of the
        // daemon that loads the scene.
        let bytes = positions_only(bytes);
        let decoded = std::panic::catch_unwind(|| {
            tobj::load_obj_buf(&mut std::io::Cursor::new(&bytes), &options, |_| {
                Err(tobj::LoadError::OpenFileFailed)
            })
        })
        .map_err(|payload| {
            let why = payload
                .downcast_ref::<&str>()
                .map(|s| (*s).to_owned())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "a panic without a message".into());
            format!("is malformed: the OBJ decoder failed on it ({why})")
        })?;
        let (models, _) = decoded.map_err(|e| e.to_string())?;
        let mut mesh = Mesh::default();
        for model in models {
            let m = &model.mesh;
            let part = Mesh {
                vertices: m
                    .positions
                    .chunks_exact(3)
                    .map(|p| DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64))
                    .collect(),
                triangles: m.indices.chunks_exact(3).map(|t| [t[0], t[1], t[2]]).collect(),
            };
            mesh.append(&part);
        }
        mesh.validated()
    }

    /// Decodes a PLY file (ASCII or binary) held in memory.
    pub fn from_ply_bytes(bytes: &[u8]) -> Result<Mesh, String> {
        load_ply(bytes)?.validated()
    }

    /// Checks what every loaded mesh must satisfy: faces, indices in range, finite
    /// vertices, and sizes that fit.
    fn validated(self) -> Result<Mesh, String> {
        if self.triangles.is_empty() {
            return Err("contains no faces".into());
        }
        let n = u32::try_from(self.vertices.len()).map_err(|_| "has more than 2^32 vertices".to_string())?;
        if let Some(bad) = self.triangles.iter().flatten().find(|&&i| i >= n) {
            return Err(format!("face refers to vertex {bad}, but there are only {n}"));
        }
        if self.vertices.iter().any(|v| !v.is_finite()) {
            return Err("a vertex is not finite".into());
        }
        Ok(self)
    }
}

/// An OBJ file's bytes without its texture coordinate (`vt`) and normal (`vn`) lines,
/// which a scene does not use; faces that still name them then look nothing up. A line
/// is told as tobj tells it: its first word, split on Unicode whitespace (the fuzzer
/// put a vertical tab before a `vt`). A line that is not UTF-8 is kept, and tobj
/// refuses the file for it.
fn positions_only(bytes: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(bytes.len());
    for line in bytes.split_inclusive(|&b| b == b'\n') {
        let first = std::str::from_utf8(line)
            .ok()
            .and_then(|text| text.split_whitespace().next());
        if !matches!(first, Some("vt" | "vn")) {
            out.extend_from_slice(line);
        }
    }
    out
}

/// Largest mesh file a scene may name, bytes.
pub const MAX_MESH_FILE_BYTES: u64 = 1 << 30;

/// A mesh file's bytes: a regular file of at most [`MAX_MESH_FILE_BYTES`]. A FIFO
/// (whose open would block), a device (`/dev/zero` never ends) or a directory is refused
/// before it is opened, and the cap applies to what is read, not only to the size the
/// file claims.
fn read_mesh_file(path: &Path) -> Result<Vec<u8>, String> {
    use std::io::Read;
    let meta = std::fs::metadata(path).map_err(|e| e.to_string())?;
    if !meta.is_file() {
        return Err("is not a regular file (a FIFO, device or directory): give an .obj or .ply file".into());
    }
    let too_large = |len: u64| {
        format!("is {len} bytes or more, more than the {MAX_MESH_FILE_BYTES} a scene mesh may have")
    };
    if meta.len() > MAX_MESH_FILE_BYTES {
        return Err(too_large(meta.len()));
    }
    let mut bytes = Vec::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(MAX_MESH_FILE_BYTES + 1).read_to_end(&mut bytes))
        .map_err(|e| e.to_string())?;
    if bytes.len() as u64 > MAX_MESH_FILE_BYTES {
        return Err(too_large(bytes.len() as u64));
    }
    Ok(bytes)
}

fn load_ply(bytes: &[u8]) -> Result<Mesh, String> {
    use ply_rs_bw::parser::Parser;
    use ply_rs_bw::ply::{DefaultElement, Property};
    let parser = Parser::<DefaultElement>::new();
    let header = parser
        .read_ply_header(&mut std::io::Cursor::new(bytes))
        .map_err(|e| e.to_string())?;
    ply_elements_fit(bytes, &header)?;
    let ply = parser
        .read_ply(&mut std::io::Cursor::new(bytes))
        .map_err(|e| e.to_string())?;
    let scalar = |p: &Property| -> Option<f64> {
        Some(match p {
            Property::Float(v) => *v as f64,
            Property::Double(v) => *v,
            Property::Int(v) => *v as f64,
            Property::UInt(v) => *v as f64,
            Property::Short(v) => *v as f64,
            Property::UShort(v) => *v as f64,
            Property::Char(v) => *v as f64,
            Property::UChar(v) => *v as f64,
            _ => return None,
        })
    };
    let mut mesh = Mesh::default();
    for v in ply.payload.get("vertex").ok_or("no `vertex` element")? {
        let get = |k: &str| {
            v.get(k)
                .and_then(scalar)
                .ok_or(format!("vertex without numeric `{k}`"))
        };
        mesh.vertices.push(DVec3::new(get("x")?, get("y")?, get("z")?));
    }
    for f in ply.payload.get("face").ok_or("no `face` element")? {
        let list = f
            .get("vertex_indices")
            .or_else(|| f.get("vertex_index"))
            .ok_or("face without `vertex_indices`")?;
        let idx: Vec<u32> = match list {
            Property::ListInt(v) => v.iter().map(|&i| i as u32).collect(),
            Property::ListUInt(v) => v.clone(),
            Property::ListUChar(v) => v.iter().map(|&i| i as u32).collect(),
            Property::ListUShort(v) => v.iter().map(|&i| i as u32).collect(),
            Property::ListShort(v) => v.iter().map(|&i| i as u32).collect(),
            _ => return Err("face indices are not an integer list".into()),
        };
        for k in 1..idx.len().saturating_sub(1) {
            mesh.triangles.push([idx[0], idx[k], idx[k + 1]]);
        }
    }
    Ok(mesh)
}

/// Refuses a PLY header whose elements cannot fit in the bytes after it, before the
/// parser reads them: an instance of a binary element takes at least its scalars' bytes
/// and its lists' counts, an ASCII one at least a character and a separator a property.
/// A binary element without properties takes no bytes at all, so the parser would read
/// as many of them as the header claims out of nothing (the `mesh` fuzz target found
/// one claiming 10^11 faces, which held gigabytes and tens of seconds).
fn ply_elements_fit(bytes: &[u8], header: &ply_rs_bw::ply::Header) -> Result<(), String> {
    use ply_rs_bw::ply::{Encoding, PropertyType, ScalarType};
    let size = |t: &ScalarType| match t {
        ScalarType::Char | ScalarType::UChar => 1u64,
        ScalarType::Short | ScalarType::UShort => 2,
        ScalarType::Int | ScalarType::UInt | ScalarType::Float => 4,
        ScalarType::Double => 8,
    };
    let end = b"end_header";
    let payload = bytes
        .windows(end.len())
        .position(|w| w == end)
        .and_then(|at| {
            let rest = &bytes[at..];
            rest.iter()
                .position(|&b| b == b'\n')
                .map(|nl| (rest.len() - nl - 1) as u64)
        })
        .ok_or("no `end_header` line")?;
    let mut need = 0u64;
    for (name, e) in header.elements.iter() {
        let each: u64 = e
            .properties
            .values()
            .map(|p| match (&header.encoding, &p.data_type) {
                (Encoding::Ascii, _) => 2,
                (_, PropertyType::Scalar(t)) => size(t),
                (_, PropertyType::List(count, _)) => size(count),
            })
            .sum();
        if each == 0 && e.count > 0 {
            return Err(format!(
                "element `{name}` has no properties but claims {} instances",
                e.count
            ));
        }
        need = need.saturating_add((e.count as u64).saturating_mul(each));
    }
    if need > payload {
        return Err(format!(
            "its header declares elements of at least {need} bytes, but {payload} follow it: \
             the file is truncated or forged"
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every vertex of a cylinder lies at its radius from the axis, each ring across
    /// the axis, whatever the axis's length and direction (a limb of the mannequin:
    /// until 2026-12-07 a non-unit axis gave a 15 mm radius for 35 and tilted rings).
    #[test]
    fn a_cylinder_is_round_and_square_to_its_axis() {
        for (a, b, r) in [
            (DVec3::ZERO, DVec3::new(0.0, 0.0, 0.45), 0.035),
            (DVec3::new(0.1, 0.3, -0.2), DVec3::new(-0.3, 0.8, 0.25), 0.048),
        ] {
            let m = Mesh::cylinder(a, b, r, 16);
            let dir = (b - a).normalize();
            for v in &m.vertices {
                let along = (*v - a).dot(dir);
                let across = (*v - a - dir * along).length();
                assert!((across - r).abs() < 1e-12, "radius {across} for {r}");
                let end = if along < 0.5 * (b - a).length() {
                    0.0
                } else {
                    (b - a).length()
                };
                assert!(
                    (along - end).abs() < 1e-12,
                    "a ring {along} along the axis, not at {end}"
                );
            }
        }
    }

    #[test]
    fn an_obj_keeps_its_positions_and_faces_without_its_texture_coordinates_and_normals() {
        let quad = b"# a unit quad\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n\
                     vn 0 0 1\nf 1/1/1 2/2/1 3/3/1 4/4/1\n";
        let m = Mesh::from_obj_bytes(quad).unwrap();
        assert_eq!(m.triangles.len(), 2);
        assert_eq!(m.vertices.len(), 4);
        let area: f64 = m
            .triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| m.vertices[i as usize]);
                (b - a).cross(c - a).length() / 2.0
            })
            .sum();
        assert!((area - 1.0).abs() < 1e-12, "{area}");
        // A relative texture index before the first coordinate (found by the `mesh`
        // fuzz target: it overflowed tobj's arithmetic) or past the last: looked up
        // nowhere, the triangle kept.
        for face in [
            "f 1/-2 2 3\n",
            "f 1/-9223372036854775807/-3 2 3\n",
            "f 1/99/99 2/1 3\n",
        ] {
            // The coordinate's line starts with a vertical tab, whitespace to tobj.
            let text = format!("v 0 0 0\nv 1 0 0\nv 0 1 0\n\u{b}vt 0 0\n{face}");
            let m = Mesh::from_obj_bytes(text.as_bytes()).unwrap_or_else(|e| panic!("{face}: {e}"));
            assert_eq!((m.vertices.len(), m.triangles.len()), (3, 1), "{face}");
        }
    }

    /// A binary little-endian PLY of three vertices and `faces` declared triangles,
    /// `body` after its header.
    fn binary_ply(face_element: &str, body: &[u8]) -> Vec<u8> {
        let mut out = format!(
            "ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n\
             property float y\nproperty float z\n{face_element}end_header\n"
        )
        .into_bytes();
        out.extend_from_slice(body);
        out
    }

    #[test]
    fn a_ply_whose_header_claims_more_than_its_bytes_is_refused_before_it_is_read() {
        let mut body = Vec::new();
        for v in [[0f32, 0., 0.], [1., 0., 0.], [0., 1., 0.]] {
            v.iter().for_each(|c| body.extend_from_slice(&c.to_le_bytes()));
        }
        let triangle = {
            let mut t = body.clone();
            t.push(3);
            [0i32, 1, 2]
                .iter()
                .for_each(|i| t.extend_from_slice(&i.to_le_bytes()));
            t
        };
        let list = "element face 1\nproperty list uchar int vertex_indices\n";
        let m = Mesh::from_ply_bytes(&binary_ply(list, &triangle)).unwrap();
        assert_eq!((m.vertices.len(), m.triangles.len()), (3, 1));
        // Faces without properties take no bytes: 10^11 of them (found by the `mesh`
        // fuzz target) would be read out of nothing.
        let empty = "element face 99999999999\n";
        let e = Mesh::from_ply_bytes(&binary_ply(empty, &body)).unwrap_err();
        assert!(e.contains("`face` has no properties"), "{e}");
        // More faces than the bytes after the header can hold.
        let many = list.replace("face 1", "face 1000000");
        let e = Mesh::from_ply_bytes(&binary_ply(&many, &triangle)).unwrap_err();
        assert!(e.contains("truncated or forged"), "{e}");
        // ASCII: a character and a separator a property at least.
        let ascii = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
                     property float z\nelement face 1\nproperty list uchar int vertex_indices\n\
                     end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n";
        let m = Mesh::from_ply_bytes(ascii.as_bytes()).unwrap();
        assert_eq!((m.vertices.len(), m.triangles.len()), (3, 1));
        let e = Mesh::from_ply_bytes(ascii.replace("face 1", "face 100").as_bytes()).unwrap_err();
        assert!(e.contains("truncated or forged"), "{e}");
    }
}
