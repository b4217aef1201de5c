//! Fixed-length arrays read exactly: serde reads `[T; N]` by taking the first N items
//! and ignores any more, so `pairs.grid = [24, 24, 24]` would be taken as `[24, 24]`.
//! Fields read through these (`#[serde(deserialize_with = "crate::config::exact::array")]`)
//! refuse any other length, and the error names the key and line like every other.
use serde::de::{Deserialize, Deserializer, Error};

/// `[T; N]`, refusing arrays of any other length.
pub(crate) fn array<'de, D, T, const N: usize>(d: D) -> Result<[T; N], D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    exactly(Vec::<T>::deserialize(d)?)
}

/// `Option<[T; N]>`, refusing arrays of any other length (absent: `None`).
pub(crate) fn option<'de, D, T, const N: usize>(d: D) -> Result<Option<[T; N]>, D::Error>
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

#[cfg(test)]
mod tests {
    #[derive(serde::Deserialize, Debug)]
    struct Raw {
        #[serde(deserialize_with = "super::array")]
        grid: [usize; 2],
        #[serde(default, deserialize_with = "super::option")]
        size: Option<[f64; 2]>,
    }

    #[test]
    fn arrays_of_another_length_are_refused() {
        let ok: Raw = toml::from_str("grid = [24, 24]\nsize = [0.5, 0.5]").unwrap();
        assert_eq!(ok.grid, [24, 24]);
        assert_eq!(ok.size, Some([0.5, 0.5]));
        let none: Raw = toml::from_str("grid = [1, 2]").unwrap();
        assert_eq!(none.size, None);
        for bad in [
            "grid = [24, 24, 24]",
            "grid = [24]",
            "grid = [1, 2]\nsize = [1.0, 2.0, 3.0]",
        ] {
            let e = toml::from_str::<Raw>(bad).unwrap_err().to_string();
            assert!(e.contains("exactly 2"), "{bad}: {e}");
        }
    }
}
