//! One run per output folder: a lock file (`refnpr.lock`) naming the process
//! that holds it. A second run pointed at the same folder refuses, naming the
//! first; a lock left by a process that no longer exists (a killed run) is
//! taken over. The lock goes when its holder is dropped.

use anyhow::{Context, Result, bail};
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::util::files;

pub const LOCK_FILE: &str = "refnpr.lock";

/// Holds `DIR/refnpr.lock` until dropped.
#[derive(Debug)]
pub struct OutputLock {
    path: PathBuf,
}

/// Who holds a lock: the process id, when it started (so a recycled id is
/// not mistaken for the holder), and what it runs.
#[derive(Debug, PartialEq)]
struct Holder {
    pid: u32,
    start: Option<u64>,
    command: String,
}

impl Holder {
    fn this_process() -> Self {
        let pid = std::process::id();
        let command = std::env::args().collect::<Vec<_>>().join(" ");
        Self { pid, start: process_start(pid), command }
    }

    fn text(&self) -> String {
        let start = self.start.map(|s| s.to_string()).unwrap_or_default();
        format!("pid {}\nstart {}\ncommand {}\n", self.pid, start, self.command)
    }

    fn parse(text: &str) -> Option<Self> {
        let field = |key: &str| text.lines().find_map(|l| l.strip_prefix(key)).map(str::trim);
        Some(Self {
            pid: field("pid ")?.parse().ok()?,
            start: field("start").and_then(|s| s.parse().ok()),
            command: field("command").unwrap_or("").to_string(),
        })
    }

    /// Whether the process still runs. Where we cannot tell (no `/proc`),
    /// assume it does: refusing is safe, the message says how to override.
    fn alive(&self) -> bool {
        if !Path::new("/proc/self").exists() {
            return true;
        }
        match process_start(self.pid) {
            None => false,
            Some(now) => self.start.is_none_or(|s| s == now),
        }
    }
}

/// A process's start time in clock ticks since boot (`/proc/PID/stat`, field
/// 22), or `None` when no such process exists.
fn process_start(pid: u32) -> Option<u64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // The command name (field 2) is in parentheses and may hold spaces.
    let after = &stat[stat.rfind(')')? + 1..];
    after.split_whitespace().nth(19)?.parse().ok()
}

impl OutputLock {
    /// Takes `dir`'s lock (creating `dir`), or says which run holds it.
    pub fn acquire(dir: &Path) -> Result<Self> {
        files::create_dir(dir)?;
        let path = dir.join(LOCK_FILE);
        let me = Holder::this_process();
        // Two tries: the second after removing a dead holder's lock.
        for _ in 0..2 {
            match std::fs::OpenOptions::new().write(true).create_new(true).open(&path) {
                Ok(mut f) => {
                    f.write_all(me.text().as_bytes()).map_err(|e| files::io_error(e, &path))?;
                    return Ok(Self { path });
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    let text = std::fs::read_to_string(&path).unwrap_or_default();
                    match Holder::parse(&text) {
                        Some(h) if h.alive() => bail!(
                            "{} is in use by another refnpr run (process {}: {}); wait for it to finish or stop it, \
                             or choose another output folder (if that process is not a refnpr run, delete {})",
                            dir.display(),
                            h.pid,
                            h.command,
                            path.display()
                        ),
                        // A dead holder's lock, or one cut short before its text was written.
                        _ => std::fs::remove_file(&path)
                            .with_context(|| format!("cannot remove the stale lock {}", path.display()))?,
                    }
                }
                Err(e) => return Err(files::io_error(e, &path)),
            }
        }
        bail!("{}: another process keeps taking the lock", path.display())
    }
}

impl Drop for OutputLock {
    fn drop(&mut self) {
        std::fs::remove_file(&self.path).ok();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("refnpr-lock-{name}-{}", std::process::id()));
        std::fs::remove_dir_all(&d).ok();
        d
    }

    #[test]
    fn a_second_run_is_refused_until_the_first_lets_go() {
        let dir = scratch("second");
        let first = OutputLock::acquire(&dir).unwrap();
        let err = format!("{:#}", OutputLock::acquire(&dir).unwrap_err());
        assert!(err.contains("in use by another refnpr run") && err.contains(&std::process::id().to_string()), "{err}");
        drop(first);
        assert!(!dir.join(LOCK_FILE).exists());
        let again = OutputLock::acquire(&dir).unwrap();
        drop(again);
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn a_dead_holders_lock_is_taken_over() {
        let dir = scratch("dead");
        std::fs::create_dir_all(&dir).unwrap();
        // A process that has exited: its id names nothing now (or a
        // different process, with another start time).
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let pid = child.id();
        child.wait().unwrap();
        let stale = Holder { pid, start: Some(1), command: "refnpr stylize (killed)".into() };
        std::fs::write(dir.join(LOCK_FILE), stale.text()).unwrap();
        let lock = OutputLock::acquire(&dir).unwrap();
        let text = std::fs::read_to_string(dir.join(LOCK_FILE)).unwrap();
        assert_eq!(Holder::parse(&text).unwrap().pid, std::process::id());
        drop(lock);
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn a_holder_round_trips_through_its_text() {
        let me = Holder::this_process();
        assert_eq!(Holder::parse(&me.text()), Some(me));
        assert_eq!(Holder::parse("garbage"), None);
    }
}
