//! Fixed-length arrays read exactly from config files: serde reads `[T; N]` by taking
//! the first N items and ignores any more, so `pairs.grid = [24, 24, 24]` would be
//! taken as `[24, 24]`. Fields read through these
//! (`#[serde(deserialize_with = "periscope_drivers::exact::array")]`) refuse any other
//! length, and the error names the key and line like every other. Here, in the crate
//! every config reader depends on: instrument configs and plans (the daemon) and scene
//! files (the simulator) read arrays alike.
use serde::de::{Deserialize, Deserializer, Error};

/// `[T; N]`, refusing arrays of any other length.
pub fn array<'de, D, T, const N: usize>(d: D) -> Result<[T; N], D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    exactly(Vec::<T>::deserialize(d)?)
}

/// `Option<[T; N]>`, refusing arrays of any other length (absent: `None`).
pub fn option<'de, D, T, const N: usize>(d: D) -> Result<Option<[T; N]>, D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    Option::<Vec<T>>::deserialize(d)?.map(exactly).transpose()
}

fn exactly<E: Error, T, const N: usize>(v: Vec<T>) -> Result<[T; N], E> {
    let len = v.len();
    v.try_into()
        .map_err(|_| E::invalid_length(len, &format!("an array of exactly {N} numbers").as_str()))
}
