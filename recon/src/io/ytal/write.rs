//! Encoding a capture in y-tal's own layout (what `tal.io.write_capture` writes): the
//! enum types h5py gives `H_format`, the grid formats and numpy booleans, `H` chunked
//! and deflated, and the histogram flags folded into `scene_info`.
use std::path::Path;

use glam::DVec3;
use hdf5_pure::{Datatype, EnumTypeBuilder, FileBuilder, make_i8_type, make_i32_type};

use super::{FLAG_KEYS, YtalCapture, YtalError};

impl YtalCapture {
    /// Writes the capture in y-tal's own layout (what `tal.io.write_capture` writes), so
    /// y-tal and h5py read it. The file is replaced atomically and durably
    /// ([`crate::io::write_bytes_atomically`]).
    ///
    /// The capture is checked as the reader checks it first (`H` against its shape, the
    /// grids, the flags and the origins), and the target before the encoding (minutes
    /// for a large `H`): what the reader would refuse is not written.
    pub fn write(&self, path: &Path) -> Result<(), YtalError> {
        self.check().map_err(|message| YtalError::Format {
            path: path.to_path_buf(),
            message: format!("not written: {message}"),
        })?;
        if let Some(why) = crate::io::non_regular_target(path) {
            return Err(YtalError::Hdf5 {
                path: path.to_path_buf(),
                message: why.into(),
            });
        }
        let bytes = self.to_bytes().map_err(|e| YtalError::Hdf5 {
            path: path.to_path_buf(),
            message: format!("cannot be encoded: {e}"),
        })?;
        crate::io::write_bytes_atomically(path, &bytes).map_err(|e| YtalError::Hdf5 {
            path: path.to_path_buf(),
            message: match crate::io::FolderNotSynced::of(&e) {
                Some(done) => done.to_string(),
                None => format!("cannot be written: {e}"),
            },
        })
    }

    /// The capture as the bytes of a y-tal HDF5 file (what [`YtalCapture::write`] stores).
    pub fn to_bytes(&self) -> Result<Vec<u8>, hdf5_pure::Error> {
        let h_type = enum_type(
            make_i32_type(),
            &[
                ("UNKNOWN", 0),
                ("T_Sx_Sy", 1),
                ("T_Lx_Ly_Sx_Sy", 2),
                ("T_Si", 3),
                ("T_Li_Si", 4),
            ],
        )?;
        let grid_type = enum_type(make_i32_type(), &[("UNKNOWN", 0), ("N_3", 1), ("X_Y_3", 2)])?;
        // numpy booleans, as h5py stores them.
        let bool_type = enum_type(make_i8_type(), &[("FALSE", 0), ("TRUE", 1)])?;
        let shape = |s: &[usize]| s.iter().map(|&d| d as u64).collect::<Vec<u64>>();
        let mut b = FileBuilder::new();
        b.create_dataset("H")
            .with_f32_data(&self.h)
            .with_shape(&shape(&self.h_shape))
            .with_chunks(&chunks(&self.h_shape))
            .with_deflate(4);
        b.create_dataset("H_format")
            .with_enum_i32_data(h_type, &[self.h_format as i32]);
        for (side, grid) in [("sensor", &self.sensor_grid), ("laser", &self.laser_grid)] {
            let mut gshape = shape(&grid.shape);
            gshape.push(3);
            let flat = |v: &[DVec3]| {
                v.iter()
                    .flat_map(|p| [p.x as f32, p.y as f32, p.z as f32])
                    .collect::<Vec<f32>>()
            };
            b.create_dataset(&format!("{side}_grid_xyz"))
                .with_f32_data(&flat(&grid.points))
                .with_shape(&gshape);
            b.create_dataset(&format!("{side}_grid_normals"))
                .with_f32_data(&flat(&grid.normals))
                .with_shape(&gshape);
            b.create_dataset(&format!("{side}_grid_format"))
                .with_enum_i32_data(grid_type.clone(), &[grid.format as i32]);
        }
        // An unknown origin is left out, which y-tal reads as `None`.
        for (name, origin) in [("sensor_xyz", self.sensor_xyz), ("laser_xyz", self.laser_xyz)] {
            if let Some(p) = origin {
                b.create_dataset(name)
                    .with_f32_data(&[p.x as f32, p.y as f32, p.z as f32]);
            }
        }
        b.create_dataset("delta_t")
            .with_f64_data(&[self.delta_t])
            .with_shape(&[]);
        b.create_dataset("t_start")
            .with_f64_data(&[self.t_start])
            .with_shape(&[]);
        b.create_dataset("t_accounts_first_and_last_bounces")
            .with_enum_u8_data(bool_type, &[u8::from(self.t_accounts_first_and_last_bounces)])
            .with_shape(&[]);
        let mut info = self.scene_info.clone();
        if let Some(flags) = &self.flags {
            let text = info.get_or_insert_with(String::new);
            if !(text.is_empty() || text.ends_with('\n')) {
                text.push('\n');
            }
            for (key, bit) in FLAG_KEYS {
                let list: Vec<String> = (0..flags.len())
                    .filter(|&i| flags[i] & bit != 0)
                    .map(|i| i.to_string())
                    .collect();
                text.push_str(&format!("{key}: [{}]\n", list.join(", ")));
            }
        }
        // Always written, `{}` where there is nothing to say: y-tal's reader (since
        // 0.21, `is_polarized`) looks into `scene_info` and fails on a file without one.
        let info = info.unwrap_or_else(|| "{}\n".to_owned());
        b.create_dataset("scene_info")
            .with_vlen_strings(&[&info])
            .with_shape(&[]);
        b.finish()
    }
}

fn enum_type(base: Datatype, members: &[(&str, i32)]) -> Result<Datatype, hdf5_pure::FormatError> {
    members
        .iter()
        .fold(EnumTypeBuilder::with_base(base), |b, &(name, v)| b.value(name, v))
        .build()
}

/// Chunks of about 256 KiB for `H`: whole time axis, as many transients as fit.
fn chunks(shape: &[usize]) -> Vec<u64> {
    let t = shape[0].max(1);
    let mut left = (65_536 / t).max(1);
    let mut out = vec![t as u64];
    for &d in shape[1..].iter().rev() {
        let take = d.min(left).max(1);
        out.push(take as u64);
        left = (left / take).max(1);
    }
    out[1..].reverse();
    out
}
