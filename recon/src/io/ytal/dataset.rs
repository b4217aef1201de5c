//! One dataset of a capture, read safely. A capture comes from anywhere (a paper's
//! download, a colleague's disk, the fuzzer), and the HDF5 layer trusts the shapes,
//! chunk sizes and offsets a file declares when it allocates and reads, so every
//! dataset's declared size is checked here against the limits below and against what
//! the file can hold before a value is read.
use std::path::Path;

use glam::DVec3;
use hdf5_pure::File;

use super::{Grid, GridFormat, MAX_DATASET_BYTES, YtalError};

/// A dataset's values (as f64) and shape.
type Values = (Vec<f64>, Vec<usize>);

/// An open capture file and what its messages name.
pub(crate) struct Reader<'a> {
    pub(crate) file: File,
    pub(crate) path: &'a Path,
    /// Length of the file, bytes.
    pub(crate) file_len: u64,
}

/// Best compression ratio deflate can reach: a chunked dataset cannot hold more than
/// this times the file's length.
const MAX_GZIP_RATIO: u64 = 1032;

/// Most chunks a dataset may be split into.
const MAX_CHUNKS: u64 = 1 << 22;

/// Largest chunk, bytes (h5py aims at 1 MiB at most): the HDF5 layer sizes its
/// decompression buffers by the declared chunk, whatever the data.
const MAX_CHUNK_BYTES: u64 = 64 << 20;

impl Reader<'_> {
    /// A dataset's shape, after checking that reading it is safe: the declared size
    /// (as `out_width`-byte values in memory) fits [`MAX_DATASET_BYTES`] and what the
    /// file can hold (its length, times the best gzip ratio for chunked data), and a
    /// chunked layout has a sane chunk count. A small file that declares a huge shape
    /// (an "HDF5 bomb") is refused here, before the HDF5 layer allocates for it.
    pub(crate) fn checked_shape(
        &self,
        ds: &hdf5_pure::Dataset,
        name: &str,
        out_width: u64,
    ) -> Result<Vec<usize>, YtalError> {
        let err = |m: String| self.format(format!("dataset `{name}`: {m}"));
        let shape = ds.shape().map_err(|e| err(e.to_string()))?;
        let elements = shape
            .iter()
            .try_fold(1u64, |a, &d| a.checked_mul(d))
            .ok_or_else(|| err(format!("its shape {shape:?} overflows")))?;
        let stored = ds
            .element_size()
            .ok()
            .and_then(|w| elements.checked_mul(w))
            .ok_or_else(|| err(format!("its shape {shape:?} overflows")))?;
        let declared = stored.max(elements.saturating_mul(out_width));
        if declared > MAX_DATASET_BYTES {
            return Err(err(format!(
                "its shape {shape:?} declares {declared} bytes, more than the {MAX_DATASET_BYTES} a capture dataset may have"
            )));
        }
        let chunked = matches!(ds.layout(), Ok(hdf5_pure::Layout::Chunked { .. }));
        let holds = if chunked {
            self.file_len.saturating_mul(MAX_GZIP_RATIO)
        } else {
            self.file_len
        };
        if stored > holds {
            return Err(err(format!(
                "its shape {shape:?} declares {stored} bytes but the file has {} bytes: it is truncated or forged",
                self.file_len
            )));
        }
        if let Ok(Some(chunk)) = ds.chunk_shape() {
            let count = shape
                .iter()
                .zip(&chunk)
                .try_fold(1u64, |a, (&d, &c)| a.checked_mul(d.div_ceil(c.max(1))));
            let chunk_bytes = chunk
                .iter()
                .try_fold(ds.element_size().unwrap_or(8).max(1), |a, &c| a.checked_mul(c));
            if chunk.len() != shape.len()
                || chunk.contains(&0)
                || count.is_none_or(|n| n > MAX_CHUNKS)
                || chunk_bytes.is_none_or(|b| b > MAX_CHUNK_BYTES)
            {
                return Err(err(format!(
                    "its chunk shape {chunk:?} does not fit its shape {shape:?}, makes too many chunks, \
                     or makes chunks over {MAX_CHUNK_BYTES} bytes"
                )));
            }
        }
        // Every stored chunk must lie inside the file and inside the dataset: the HDF5
        // layer trusts a chunk's recorded size and offset when it reads (the fuzzer
        // found a 160 KB file whose chunk record made it allocate 3.4 GB).
        // A chunk index the HDF5 layer cannot list (an address past the end of the
        // address space, as in a 14 KB file the fuzzer found that made it reserve 4 GiB
        // to read) is refused too: what is not checked is not read.
        if chunked {
            let chunks = ds.chunks().map_err(|e| {
                err(format!(
                    "its chunk index cannot be read ({e}): the file is damaged or forged"
                ))
            })?;
            for c in &chunks {
                let inside_file = c
                    .address
                    .checked_add(c.storage_size)
                    .is_some_and(|end| end <= self.file_len);
                let inside_data =
                    c.offset.len() == shape.len() && c.offset.iter().zip(&shape).all(|(o, d)| o < d);
                if !inside_file || !inside_data {
                    return Err(err(format!(
                        "a chunk (at {:?}, {} bytes at byte {}) lies outside the dataset or beyond the end of the file",
                        c.offset, c.storage_size, c.address
                    )));
                }
            }
        }
        // A contiguous layout records its own address and byte count, which the HDF5
        // layer reads whatever the shape says: they must lie inside the file as well.
        if let Ok(hdf5_pure::Layout::Contiguous {
            address: Some(address),
            size,
        }) = ds.layout()
            && address.checked_add(size).is_none_or(|end| end > self.file_len)
        {
            return Err(err(format!(
                "its data ({size} bytes) lies beyond the end of the file ({} bytes): it is truncated or forged",
                self.file_len
            )));
        }
        shape
            .into_iter()
            .map(|d| usize::try_from(d).map_err(|_| err("a dimension does not fit this machine".into())))
            .collect()
    }

    pub(crate) fn format(&self, message: String) -> YtalError {
        YtalError::Format {
            path: self.path.to_path_buf(),
            message,
        }
    }

    /// A dataset's checked shape ([`Reader::checked_shape`]), without reading it;
    /// `None` when it is missing.
    pub(crate) fn shape_of(&self, name: &str) -> Result<Option<Vec<usize>>, YtalError> {
        match self.file.dataset(name) {
            Ok(ds) => self.checked_shape(&ds, name, 8).map(Some),
            Err(_) => Ok(None),
        }
    }

    pub(crate) fn has(&self, name: &str) -> bool {
        self.file.dataset(name).is_ok()
    }

    /// Values and shape; `None` for a missing or empty (null) dataset. Its values (as
    /// f64) must fit the memory this process can still take: a chunked dataset of
    /// zeros compresses a thousandfold, so a file of a few MB can declare GiBs that
    /// pass every check on the file and would be allocated whole.
    pub(crate) fn floats(&self, name: &str) -> Result<Option<Values>, YtalError> {
        self.floats_within(name, None)
    }

    /// [`Reader::floats`] of a dataset expected to hold at most `most` values (a
    /// scalar, a point): a larger one is refused from its shape, before it is read.
    fn floats_within(&self, name: &str, most: Option<(u64, &str)>) -> Result<Option<Values>, YtalError> {
        let Ok(ds) = self.file.dataset(name) else {
            return Ok(None);
        };
        let shape = self.checked_shape(&ds, name, 8)?;
        let elements = shape.iter().map(|&d| d as u64).product::<u64>();
        if let Some((most, what)) = most
            && elements > most
        {
            return Err(self.format(format!(
                "dataset `{name}` should hold {what}, its shape {shape:?} holds {elements} values"
            )));
        }
        let need = elements.saturating_mul(8);
        if let Some(available) = crate::io::memory_available()
            && need > available
        {
            return Err(self.format(format!(
                "dataset `{name}` (shape {shape:?}) takes {need} bytes to read, more than the {available} this process can still use: read it on a machine with more memory"
            )));
        }
        let values = ds
            .read_f64()
            .map_err(|e| self.format(format!("dataset `{name}` is not numeric: {e}")))?;
        if values.is_empty() {
            return Ok(None);
        }
        Ok(Some((values, shape)))
    }

    pub(crate) fn scalar(&self, name: &str) -> Result<Option<f64>, YtalError> {
        match self.floats_within(name, Some((1, "one value")))? {
            None => Ok(None),
            Some((v, _)) if v.len() == 1 => Ok(Some(v[0])),
            Some((v, _)) => Err(self.format(format!(
                "dataset `{name}` should hold one value, it holds {}",
                v.len()
            ))),
        }
    }

    pub(crate) fn required_scalar(&self, name: &str) -> Result<f64, YtalError> {
        self.scalar(name)?
            .ok_or_else(|| self.format(format!("dataset `{name}` is missing or empty")))
    }

    pub(crate) fn point(&self, name: &str) -> Result<Option<DVec3>, YtalError> {
        match self.floats_within(name, Some((3, "a point (3 finite values)")))? {
            None => Ok(None),
            Some((v, _)) if v.len() == 3 && v.iter().all(|x| x.is_finite()) => {
                Ok(Some(DVec3::new(v[0], v[1], v[2])))
            }
            Some((v, _)) => Err(self.format(format!(
                "dataset `{name}` should hold a point (3 finite values), it holds {v:?}"
            ))),
        }
    }

    pub(crate) fn grid(&self, side: &str) -> Result<Grid, YtalError> {
        let xyz_name = format!("{side}_grid_xyz");
        let (xyz, shape) = self
            .floats(&xyz_name)?
            .ok_or_else(|| self.format(format!("dataset `{xyz_name}` is missing or empty")))?;
        if shape.last() != Some(&3) || !(shape.len() == 2 || shape.len() == 3) {
            return Err(self.format(format!(
                "dataset `{xyz_name}` has shape {shape:?}; expected (N, 3) or (X, Y, 3)"
            )));
        }
        let format = if shape.len() == 2 {
            GridFormat::N3
        } else {
            GridFormat::XY3
        };
        let points = to_points(&xyz);
        let normals_name = format!("{side}_grid_normals");
        let normals = match self.floats(&normals_name)? {
            Some((n, nshape)) => {
                if nshape.iter().product::<usize>() == 3 {
                    // One normal for the whole grid.
                    vec![unit(to_points(&n)[0]); points.len()]
                } else if squeezed(&nshape) == squeezed(&shape) {
                    // One a point, the same shape but for axes of length 1: y-tal's
                    // converter of phasor-field files writes (N, 1, 3) beside (N, 3).
                    to_points(&n).into_iter().map(unit).collect()
                } else {
                    return Err(self.format(format!(
                        "dataset `{normals_name}` has shape {nshape:?} but `{xyz_name}` has {shape:?}: one normal a \
                         point (or one for all) is needed"
                    )));
                }
            }
            None => {
                tracing::warn!(
                    "{}: no `{normals_name}`; assuming the y-tal convention, a relay facing +z",
                    self.path.display()
                );
                vec![DVec3::Z; points.len()]
            }
        };
        if let Some(i) = normals.iter().position(|n| *n == DVec3::ZERO || !n.is_finite()) {
            return Err(self.format(format!(
                "dataset `{normals_name}`: normal {i} is zero or not finite"
            )));
        }
        if let Some(i) = points.iter().position(|p| !p.is_finite()) {
            return Err(self.format(format!("dataset `{xyz_name}`: point {i} is not finite")));
        }
        Ok(Grid {
            points,
            normals,
            format,
            shape: shape[..shape.len() - 1].to_vec(),
        })
    }
}

fn to_points(v: &[f64]) -> Vec<DVec3> {
    v.chunks_exact(3).map(|c| DVec3::new(c[0], c[1], c[2])).collect()
}

/// `n` scaled to unit length, or zero where it has no direction (zero, or not finite).
/// Where the plain normalisation gives zero for a finite, non-zero `n` (squaring a
/// component of 10³⁰⁰ overflows, one of 10⁻²⁰⁰ underflows), `n` is first divided by
/// its largest component.
pub(crate) fn unit(n: DVec3) -> DVec3 {
    // The plain division where it works, so ordinary normals keep their last bits.
    let u = n.normalize_or_zero();
    let m = n.abs().max_element();
    if u != DVec3::ZERO || !(m > 0.0 && m.is_finite()) {
        return u;
    }
    (n / m).normalize_or_zero()
}

/// A shape without its axes of length 1.
fn squeezed(shape: &[usize]) -> Vec<usize> {
    shape.iter().copied().filter(|&d| d != 1).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Normals stored in double precision at any scale are directions (h5py writes
    /// float64 when asked): until 2026-12-06 one of 10³⁰⁰ or 10⁻²⁰⁰ read as zero (its
    /// square overflowed or underflowed) and the capture was refused.
    #[test]
    fn a_normal_at_any_finite_scale_is_its_direction() {
        let d = DVec3::new(0.6, 0.0, 0.8);
        for scale in [1.0, 1e300, 1e-200, 1e-310] {
            let n = unit(d * scale);
            assert!((n - d).length() < 1e-12, "{scale:e}: {n}");
        }
        assert_eq!(unit(DVec3::ZERO), DVec3::ZERO);
        assert_eq!(unit(DVec3::new(f64::INFINITY, 0.0, 1.0)), DVec3::ZERO);
        assert_eq!(unit(DVec3::new(f64::NAN, 0.0, 1.0)), DVec3::ZERO);
    }
}
