//! MATLAB files of either container, read the same way: MAT v5 (`save`, scipy's
//! `savemat`; parsed by matfile after [`crate::io::lct::inflate_elements`]) and MAT v7.3
//! (`save -v7.3`, hdf5storage: HDF5 after a 512-byte userblock, read through the
//! capture [`Reader`]'s size checks). A variable comes back in MATLAB's terms
//! whichever container held it: its MATLAB dims and its values in column-major order
//! (HDF5 stores a MATLAB array with its dims reversed, so its C-order values are the
//! same sequence). Structs (a v7.3 group) are read field by field, as `struct/field`.
use std::path::Path;

use crate::io::ytal::{Reader, YtalError};

/// A MATLAB array: its dims (MATLAB's order) and values, column-major.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Var<T> {
    /// Dims as MATLAB reports them (`size(x)`), at least two.
    pub(crate) dims: Vec<usize>,
    /// Values, first dim fastest.
    pub(crate) values: Vec<T>,
}

/// An open MATLAB file.
pub(crate) enum Mat<'a> {
    /// MAT v5, parsed whole.
    V5 {
        /// The parsed file (its numeric arrays: matfile drops the rest).
        mat: matfile::MatFile,
        /// Every top-level array as its header says, structs, cells, text and sparse
        /// arrays included, so messages name what the file holds.
        arrays: Vec<crate::io::lct::V5Array>,
        /// What messages name.
        path: &'a Path,
    },
    /// MAT v7.3: HDF5.
    V73(Reader<'a>),
}

impl Mat<'_> {
    /// The file messages name.
    pub(crate) fn path(&self) -> &Path {
        match self {
            Mat::V5 { path, .. } => path,
            Mat::V73(r) => r.path,
        }
    }

    /// An error naming the file.
    pub(crate) fn error(&self, message: impl Into<String>) -> YtalError {
        YtalError::Format {
            path: self.path().to_owned(),
            message: message.into(),
        }
    }

    /// The file's top-level variables (v7.3: datasets and groups, MATLAB's own
    /// `#refs#`/`#subsystem#` left out).
    pub(crate) fn names(&self) -> Vec<String> {
        let mut names: Vec<String> = match self {
            Mat::V5 { arrays, .. } => arrays
                .iter()
                .map(|a| {
                    if a.numeric() && !a.complex {
                        a.name.clone()
                    } else {
                        format!(
                            "{} ({}{})",
                            a.name,
                            if a.complex { "complex " } else { "" },
                            a.class_name()
                        )
                    }
                })
                .collect(),
            Mat::V73(r) => {
                let root = r.file.root();
                let mut n = root.datasets().unwrap_or_default();
                n.extend(root.groups().unwrap_or_default());
                n
            }
        };
        names.retain(|n| !n.starts_with('#'));
        names.sort();
        names
    }

    /// Whether the file has variable (or struct field) `name`.
    pub(crate) fn has(&self, name: &str) -> bool {
        match self {
            Mat::V5 { arrays, .. } => arrays.iter().any(|a| a.name == name),
            Mat::V73(r) => r.file.dataset(name).is_ok() || r.file.group(name).is_ok(),
        }
    }

    /// Variable `name` as f64; `None` when absent or empty.
    pub(crate) fn var(&self, name: &str) -> Result<Option<Var<f64>>, YtalError> {
        match self {
            Mat::V5 { mat, arrays, .. } => self.v5_var(mat, arrays, name, |v| v),
            Mat::V73(r) => {
                if !v73_numeric(r, name).map_err(|m| self.error(m))? {
                    return Ok(None);
                }
                Ok(r.floats(name)?.map(|(values, shape)| Var {
                    dims: matlab_dims(&shape),
                    values,
                }))
            }
        }
    }

    /// Variable `name` as f32 (the transients: half the memory of f64); `None` when
    /// absent or empty.
    pub(crate) fn var_f32(&self, name: &str) -> Result<Option<Var<f32>>, YtalError> {
        match self {
            Mat::V5 { mat, arrays, .. } => self.v5_var(mat, arrays, name, |v| v as f32),
            Mat::V73(r) => {
                if !v73_numeric(r, name).map_err(|m| self.error(m))? {
                    return Ok(None);
                }
                let Ok(ds) = r.file.dataset(name) else {
                    return Ok(None);
                };
                let shape = r.checked_shape(&ds, name, 4)?;
                super::super::ytal::memory_check(&shape, name).map_err(|m| self.error(m))?;
                let values = ds
                    .read_f32()
                    .map_err(|e| self.error(format!("`{name}` is not numeric: {e}")))?;
                if values.is_empty() {
                    return Ok(None);
                }
                Ok(Some(Var {
                    dims: matlab_dims(&shape),
                    values,
                }))
            }
        }
    }

    /// A MAT v5 variable: a full, real, numeric array whose values are as many as its
    /// dims say (matfile checks that with a product that wraps), converted by `f`, and
    /// within the memory this process can use; `None` when absent or empty.
    fn v5_var<T>(
        &self,
        mat: &matfile::MatFile,
        arrays: &[crate::io::lct::V5Array],
        name: &str,
        f: impl Fn(f64) -> T,
    ) -> Result<Option<Var<T>>, YtalError> {
        let Some(header) = arrays.iter().find(|a| a.name == name) else {
            return Ok(None);
        };
        if !header.numeric() {
            return Err(self.error(format!(
                "`{name}` is a {} array; it must be a full numeric array (save it with `full(...)` and \
                 `double(...)`)",
                header.class_name()
            )));
        }
        if header.complex {
            return Err(self.error(format!(
                "`{name}` is complex; a capture's values are real (save `real(...)`, or the magnitudes, \
                 if that is what was meant)"
            )));
        }
        let Some(a) = mat.find_by_name(name) else {
            return Err(self.error(format!("`{name}` cannot be read as a numeric array")));
        };
        let dims = a.size().clone();
        let count = dims.iter().try_fold(1usize, |n, &d| n.checked_mul(d));
        let held = v5_len(a.data());
        if count != Some(held) {
            return Err(self.error(format!(
                "`{name}` has dims {dims:?} but holds {held} values: the file is damaged"
            )));
        }
        super::super::ytal::memory_check(&dims, name).map_err(|m| self.error(m))?;
        let values = v5_values(a.data(), f);
        Ok((!values.is_empty()).then_some(Var { dims, values }))
    }

    /// Variable `name`, required.
    pub(crate) fn required(&self, name: &str, what: &str) -> Result<Var<f64>, YtalError> {
        self.var(name)?
            .ok_or_else(|| self.error(format!("no `{name}` ({what})")))
    }

    /// A finite scalar variable; `None` when absent.
    pub(crate) fn scalar(&self, name: &str) -> Result<Option<f64>, YtalError> {
        match self.var(name)? {
            None => Ok(None),
            Some(v) if v.values.len() == 1 && v.values[0].is_finite() => Ok(Some(v.values[0])),
            Some(v) => Err(self.error(format!(
                "`{name}` should be one finite number; it has dims {:?}",
                v.dims
            ))),
        }
    }

    /// A finite scalar, required.
    pub(crate) fn required_scalar(&self, name: &str, what: &str) -> Result<f64, YtalError> {
        self.scalar(name)?
            .ok_or_else(|| self.error(format!("no `{name}` ({what})")))
    }
}

/// Whether a MAT v7.3 variable `name` is there as a numeric array (`false`: absent);
/// an error names what it is instead. MATLAB marks each array with its class
/// (`MATLAB_class`): text is stored as uint16 character codes, a sparse array as a
/// group, and read as numbers they would pass for a capture's values.
fn v73_numeric(r: &Reader<'_>, name: &str) -> Result<bool, String> {
    const NUMERIC: [&str; 11] = [
        "double", "single", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64",
        "logical",
    ];
    let class = |attrs: std::collections::HashMap<String, hdf5_pure::AttrValue>| {
        attrs.get("MATLAB_class").and_then(super::text_attr)
    };
    if let Ok(ds) = r.file.dataset(name) {
        let attrs = ds.attrs().unwrap_or_default();
        // An empty array is stored as its dims (uint64) marked `MATLAB_empty`: read as
        // values, `t0 = []` was two numbers where v5's empty array reads as absent.
        if attrs.get("MATLAB_empty").is_some_and(truthy) {
            return Ok(false);
        }
        return match class(attrs) {
            Some(c) if !NUMERIC.contains(&c.as_str()) => Err(format!(
                "`{name}` is a MATLAB {c} array; it must be a full numeric array"
            )),
            _ => Ok(true),
        };
    }
    if let Ok(g) = r.file.group(name) {
        let attrs = g.attrs().unwrap_or_default();
        let what = if attrs.contains_key("MATLAB_sparse") {
            "sparse".to_owned()
        } else {
            class(attrs).unwrap_or_else(|| "struct".into())
        };
        return Err(format!(
            "`{name}` is a MATLAB {what} array; it must be a full numeric array (save it with `full(...)`)"
        ));
    }
    Ok(false)
}

/// Whether an attribute holds a true flag (MATLAB writes `MATLAB_empty` as a uint8
/// or uint32 1, hdf5storage as whatever integer its options say).
fn truthy(v: &hdf5_pure::AttrValue) -> bool {
    use hdf5_pure::AttrValue as A;
    match v {
        A::U8(x) => *x != 0,
        A::U16(x) => *x != 0,
        A::U32(x) => *x != 0,
        A::U64(x) => *x != 0,
        A::I8(x) => *x != 0,
        A::I16(x) => *x != 0,
        A::I32(x) => *x != 0,
        A::I64(x) => *x != 0,
        A::U8Array(x) => x.iter().any(|&x| x != 0),
        A::U16Array(x) => x.iter().any(|&x| x != 0),
        A::U32Array(x) => x.iter().any(|&x| x != 0),
        A::U64Array(x) => x.iter().any(|&x| x != 0),
        A::I8Array(x) => x.iter().any(|&x| x != 0),
        A::I16Array(x) => x.iter().any(|&x| x != 0),
        A::I32Array(x) => x.iter().any(|&x| x != 0),
        A::I64Array(x) => x.iter().any(|&x| x != 0),
        _ => false,
    }
}

/// MATLAB's dims of an array HDF5 stores with `shape`: reversed, at least two.
fn matlab_dims(shape: &[usize]) -> Vec<usize> {
    let mut dims: Vec<usize> = shape.iter().rev().copied().collect();
    while dims.len() < 2 {
        dims.push(1);
    }
    dims
}

/// How many values a v5 numeric array holds.
fn v5_len(d: &matfile::NumericData) -> usize {
    use matfile::NumericData as N;
    match d {
        N::Int8 { real, .. } => real.len(),
        N::UInt8 { real, .. } => real.len(),
        N::Int16 { real, .. } => real.len(),
        N::UInt16 { real, .. } => real.len(),
        N::Int32 { real, .. } => real.len(),
        N::UInt32 { real, .. } => real.len(),
        N::Int64 { real, .. } => real.len(),
        N::UInt64 { real, .. } => real.len(),
        N::Single { real, .. } => real.len(),
        N::Double { real, .. } => real.len(),
    }
}

/// A v5 numeric array's real part, converted by `f` (a complex one is refused before).
fn v5_values<T>(d: &matfile::NumericData, f: impl Fn(f64) -> T) -> Vec<T> {
    use matfile::NumericData as N;
    match d {
        N::Int8 { real, .. } => real.iter().map(|&v| f(f64::from(v))).collect(),
        N::UInt8 { real, .. } => real.iter().map(|&v| f(f64::from(v))).collect(),
        N::Int16 { real, .. } => real.iter().map(|&v| f(f64::from(v))).collect(),
        N::UInt16 { real, .. } => real.iter().map(|&v| f(f64::from(v))).collect(),
        N::Int32 { real, .. } => real.iter().map(|&v| f(f64::from(v))).collect(),
        N::UInt32 { real, .. } => real.iter().map(|&v| f(f64::from(v))).collect(),
        N::Int64 { real, .. } => real.iter().map(|&v| f(v as f64)).collect(),
        N::UInt64 { real, .. } => real.iter().map(|&v| f(v as f64)).collect(),
        N::Single { real, .. } => real.iter().map(|&v| f(f64::from(v))).collect(),
        N::Double { real, .. } => real.iter().map(|&v| f(v)).collect(),
    }
}

/// The points of a list stored as MATLAB `n × 3` (or a single point as `1 × 3` or
/// `3 × 1`), checked finite.
pub(crate) fn points(mat: &Mat<'_>, var: &Var<f64>, name: &str) -> Result<Vec<glam::DVec3>, YtalError> {
    let v = &var.values;
    let n = v.len() / 3;
    let pts: Vec<glam::DVec3> = match var.dims.as_slice() {
        [1, 3] | [3, 1] | [3] => vec![glam::DVec3::new(v[0], v[1], v[2])],
        [rows, 3] => (0..*rows)
            .map(|i| glam::DVec3::new(v[i], v[i + n], v[i + 2 * n]))
            .collect(),
        dims => {
            return Err(mat.error(format!(
                "`{name}` has dims {dims:?}; expected an n × 3 list of points"
            )));
        }
    };
    if let Some(i) = pts.iter().position(|p| !p.is_finite()) {
        return Err(mat.error(format!("`{name}` point {i} is not finite")));
    }
    Ok(pts)
}
