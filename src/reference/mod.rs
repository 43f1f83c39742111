//! Stage 2, the reference: cases (`case`: `reference.toml` or the authors'
//! `data_config.json`, style images), R³ itself in plain Rust (`r3`), and
//! running it on a photoreal field (`registration`: the `reference` and
//! `register` commands, `registration.bin`).

pub mod case;
pub mod r3;
pub mod registration;
