//! Fixed-length arrays read exactly: [`periscope_drivers::exact`], which the scene
//! files' reader shares; re-exported here for the daemon's configs and plans.
pub(crate) use periscope_drivers::exact::{array, option};

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
