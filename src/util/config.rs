//! TOML settings over defaults: a file gives only the fields it changes;
//! unknown keys and wrong types are errors that name the file.

use anyhow::{Context, Result};
use serde::Serialize;
use serde::de::DeserializeOwned;
use std::path::Path;

/// Overlays `user` onto `base` table by table.
pub fn merge(base: &mut toml::Value, user: toml::Value) {
    match (base, user) {
        (toml::Value::Table(b), toml::Value::Table(u)) => {
            for (k, v) in u {
                match b.get_mut(&k) {
                    Some(slot) => merge(slot, v),
                    None => {
                        b.insert(k, v);
                    }
                }
            }
        }
        (slot, v) => *slot = v,
    }
}

/// `user` over `base`: fields `user` leaves out keep `base`'s values.
/// `source` and `what` name the input in errors ("configs/x.toml", "config").
pub fn overlay<T: Serialize + DeserializeOwned>(base: &T, user: toml::Value, source: &str, what: &str) -> Result<T> {
    let mut merged = toml::Value::try_from(base).context("serialising the default config")?;
    merge(&mut merged, user);
    merged.try_into().with_context(|| format!("{source}: invalid {what}"))
}

/// TOML text over `base` (see `overlay`).
pub fn parse_over<T: Serialize + DeserializeOwned>(base: &T, text: &str, source: &str, what: &str) -> Result<T> {
    let user: toml::Value = toml::from_str(text).with_context(|| format!("{source} is not valid TOML"))?;
    overlay(base, user, source, what)
}

/// The text of a config file, naming it on failure.
pub fn read(path: &Path) -> Result<String> {
    std::fs::read_to_string(path).with_context(|| format!("cannot read config {}", path.display()))
}
