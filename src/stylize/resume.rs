//! Resuming a stylization: `OUT/resume.bin` holds what a killed run cannot
//! recompute exactly. Everything else (the registration, the style side,
//! the frozen sample lists, the per-step random draws) is deterministic
//! and rebuilt; the guides are rebuilt from the fields they were built from
//! (the refit's, and the smooth update's first), so a resumed run ends with
//! the same field, bit for bit on the CPU backends, as an uninterrupted one.
//! Written atomically after the refit and every `schedule.checkpoint_every`
//! image steps; removed when the run finishes.

use std::path::{Path, PathBuf};

use anyhow::{Result, bail};
use serde::{Deserialize, Serialize};

use crate::stylize::config::StylizeConfig;
use crate::stylize::{CurvePoint, Method, StylizeJob};
use crate::util::tensor_file::{self, ArrayRef};

pub const RESUME_FILE: &str = "resume.bin";
/// The file's `format` (a safetensors file: `util::tensor_file`).
const FORMAT: &str = "refnpr-stylize-resume";
/// The tag of the files older versions wrote (bincode), refused with advice.
const OLD_MAGIC: &[u8; 8] = b"REFNPRS1";

/// A stylization's state between two steps.
#[derive(Debug, Clone)]
pub struct ResumeState {
    /// What the run was: a resumed run must be the same job.
    pub job: JobKey,
    /// The field after the refit (the first guides are built from it).
    pub refit_sh: Vec<f32>,
    /// The field when the smooth update began (its guides are built from it).
    pub smooth_sh: Option<Vec<f32>>,
    /// The field now, and its RMSprop state.
    pub sh: Vec<f32>,
    pub rms: Vec<f32>,
    /// Image steps done (0: the refit just ended).
    pub image_steps: usize,
    /// Optimiser steps over all phases (the shared learning-rate schedule).
    pub optimiser_steps: usize,
    pub curve: Vec<CurvePoint>,
}

/// What the file holds besides the four fields' arrays (`refit_sh`,
/// `smooth_sh` when there is one, `sh`, `rms`).
#[derive(Serialize, Deserialize)]
struct Meta {
    job: JobKey,
    image_steps: usize,
    optimiser_steps: usize,
    curve: Vec<CurvePoint>,
}

/// The parts of a job that decide its result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobKey {
    pub method: Method,
    pub photo: PathBuf,
    pub case: PathBuf,
    pub style: Option<PathBuf>,
    /// The config as TOML (floats compare exactly in text).
    pub config: String,
}

impl JobKey {
    pub fn of(job: &StylizeJob) -> Self {
        Self {
            method: job.method,
            photo: job.photo.clone(),
            case: job.case.clone(),
            style: job.style.clone(),
            config: toml::to_string(&job.config).unwrap_or_default(),
        }
    }

    /// Whether `self` and `other` are the same job: the same method and
    /// inputs, and configs that read as the same `StylizeConfig` (a key
    /// added since the file was written reads as its default, so an older
    /// resume file still resumes where its run's settings are unchanged);
    /// configs that do not parse compare as text. A key whose default is
    /// not what runs did before it existed (`schedule.coarse_matches`:
    /// true, where older coarse runs matched at full size) changes what the
    /// rest of such a resumed run does: resumed before its smooth update,
    /// the run is the one a fresh run makes today.
    pub fn same_job(&self, other: &JobKey) -> bool {
        let parse = |c: &str| toml::from_str::<StylizeConfig>(c).ok();
        let configs = match (parse(&self.config), parse(&other.config)) {
            (Some(a), Some(b)) => a == b,
            _ => self.config == other.config,
        };
        (&self.method, &self.photo, &self.case, &self.style) == (&other.method, &other.photo, &other.case, &other.style)
            && configs
    }
}

pub fn path(out: &Path) -> PathBuf {
    out.join(RESUME_FILE)
}

/// A field-sized array as a one-dimensional tensor.
fn flat<'a>(name: &'a str, values: &'a [f32]) -> ArrayRef<'a> {
    ArrayRef::F32(name, vec![values.len()], values)
}

impl ResumeState {
    pub fn save(&self, out: &Path) -> Result<()> {
        let meta = Meta {
            job: self.job.clone(),
            image_steps: self.image_steps,
            optimiser_steps: self.optimiser_steps,
            curve: self.curve.clone(),
        };
        let mut arrays = vec![flat("refit_sh", &self.refit_sh), flat("sh", &self.sh), flat("rms", &self.rms)];
        if let Some(smooth) = &self.smooth_sh {
            arrays.push(flat("smooth_sh", smooth));
        }
        tensor_file::save(&path(out), FORMAT, &meta, &arrays)
    }

    /// The state a killed run of `job` left in its output folder, if any;
    /// an error when the folder holds another job's state.
    pub fn load(job: &StylizeJob) -> Result<Option<Self>> {
        let file = path(&job.out);
        if !file.exists() {
            return Ok(None);
        }
        let state = Self::read(&file)?;
        let key = JobKey::of(job);
        if !state.job.same_job(&key) {
            bail!(
                "{} belongs to another stylization (method, inputs or config differ: it was {:?} of {} after {}); \
                 run without --resume to start again, or choose another output folder",
                file.display(),
                state.job.method,
                state.job.photo.display(),
                state.job.case.display()
            );
        }
        Ok(Some(state))
    }

    /// Reads a resume file, whatever job it belongs to.
    pub fn read(file: &Path) -> Result<Self> {
        let older = "run without --resume to start the stylization again";
        let (meta, mut arrays): (Meta, _) =
            tensor_file::load(file, FORMAT, "a refnpr stylization resume file", (OLD_MAGIC, older))?;
        let smooth_sh = if arrays.has("smooth_sh") { Some(arrays.f32("smooth_sh")?) } else { None };
        Ok(Self {
            job: meta.job,
            refit_sh: arrays.f32("refit_sh")?,
            smooth_sh,
            sh: arrays.f32("sh")?,
            rms: arrays.f32("rms")?,
            image_steps: meta.image_steps,
            optimiser_steps: meta.optimiser_steps,
            curve: meta.curve,
        })
    }

    /// Removes the state of a finished run.
    pub fn remove(out: &Path) {
        std::fs::remove_file(path(out)).ok();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(config: String) -> JobKey {
        JobKey { method: Method::RefNpr, photo: "run".into(), case: "case".into(), style: None, config }
    }

    /// A resume file written before a config key existed (its TOML without
    /// the key) is the same job while the key is at its default, another
    /// job when the key is set; another input is another job.
    #[test]
    fn a_key_added_since_the_file_reads_as_its_default() {
        let config = StylizeConfig::default();
        let now = key(toml::to_string(&config).unwrap());
        let line = format!("coarse_matches = {}\n", config.schedule.coarse_matches);
        assert!(now.config.contains(&line), "the test's key is not in the TOML");
        let older = key(now.config.replacen(&line, "", 1));
        assert_ne!(older.config, now.config);
        assert!(older.same_job(&now), "a file without the new key was refused");
        let mut set = config.clone();
        set.schedule.coarse_matches = !config.schedule.coarse_matches;
        assert!(!older.same_job(&key(toml::to_string(&set).unwrap())), "a changed setting was accepted");
        assert!(!now.same_job(&JobKey { case: "other".into(), ..now.clone() }), "another case was accepted");
    }
}
