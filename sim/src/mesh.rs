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
        let u = axis.any_orthonormal_vector();
        let v = axis.normalize().cross(u);
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
        let (models, _) = tobj::load_obj_buf(&mut std::io::Cursor::new(bytes), &options, |_| {
            Err(tobj::LoadError::OpenFileFailed)
        })
        .map_err(|e| e.to_string())?;
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
    let mut reader = std::io::Cursor::new(bytes);
    let ply = Parser::<DefaultElement>::new()
        .read_ply(&mut reader)
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
