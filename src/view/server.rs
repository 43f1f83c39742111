//! The viewer's local web server: GET and HEAD of a fixed set of paths,
//! nothing else, written on `std::net` (one thread per connection, at most
//! `MAX_CONNECTIONS`, one request each).
//!
//! Why not a crate: the light synchronous candidate, tiny_http 0.12, reads
//! a request line of any length into memory, and an async framework (axum,
//! actix) brings a runtime for what is six read-only paths for one person;
//! a request head capped at `MAX_HEAD` bytes and an exact path table are
//! fewer lines than adapting either. Safe by construction: only the page,
//! `runs.json` and the named runs' `field.bin`, `cameras.json` and
//! `version` exist as paths; a path with `..`, `%`, a backslash, `//` or a
//! character outside `[A-Za-z0-9/._-]` is refused before lookup; requests
//! with a body are refused; nothing is ever written.

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::Result;
use burn::tensor::Device;

use crate::field::checkpoint;
use crate::view::{INDEX_HTML, VIEWER_JS, ViewRun, cameras_file, field_file, runs_json};

/// The longest request head (request line and headers) read.
pub const MAX_HEAD: usize = 8192;
/// The longest path served (the real ones are under 30 bytes).
pub const MAX_PATH: usize = 256;
/// Connections handled at once; more are answered 503.
const MAX_CONNECTIONS: usize = 32;

/// A file's bytes, shared by the requests that send it.
type Body = Arc<Vec<u8>>;

/// A served run's packed files, kept until its checkpoint changes.
struct Cached {
    version: String,
    field: Body,
    cameras: Body,
}

struct Served {
    run: ViewRun,
    cache: Mutex<Option<Cached>>,
}

/// What the server answers from.
pub struct Site {
    runs: Vec<Served>,
    device: Device,
    live: bool,
    open: AtomicUsize,
}

impl Site {
    /// The page and `runs`; `live`: the page polls each run's version.
    pub fn new(runs: Vec<ViewRun>, device: Device, live: bool) -> Arc<Self> {
        let runs = runs.into_iter().map(|run| Served { run, cache: Mutex::new(None) }).collect();
        Arc::new(Self { runs, device, live, open: AtomicUsize::new(0) })
    }

    /// The answer to `GET path`: status, content type, body.
    pub fn get(&self, path: &str) -> (u16, &'static str, Body) {
        let text = |s: &str| Arc::new(s.as_bytes().to_vec());
        match path {
            "/" | "/index.html" => return (200, "text/html; charset=utf-8", text(INDEX_HTML)),
            "/viewer.js" => return (200, "text/javascript; charset=utf-8", text(VIEWER_JS)),
            "/runs.json" => {
                return (
                    200,
                    "application/json",
                    text(&runs_json(self.runs.iter().map(|s| s.run.name.as_str()), self.live)),
                );
            }
            _ => {}
        }
        let parts: Vec<&str> = path.trim_start_matches('/').split('/').collect();
        let (Some(served), Some(file)) = (self.run_of(&parts), parts.get(2)) else {
            return (404, "text/plain", text("not found\n"));
        };
        let answer = match *file {
            "version" => Ok(("text/plain", text(&checkpoint_version(&served.run)))),
            "field.bin" => self.cached(served).map(|c| ("application/octet-stream", c.0)),
            "cameras.json" => self.cached(served).map(|c| ("application/json", c.1)),
            _ => return (404, "text/plain", text("not found\n")),
        };
        match answer {
            Ok((kind, body)) => (200, kind, body),
            Err(e) => (500, "text/plain", text(&format!("{}: {e:#}\n", served.run.name))),
        }
    }

    /// The run of `runs/N/...` (three parts exactly).
    fn run_of(&self, parts: &[&str]) -> Option<&Served> {
        if parts.len() != 3 || parts[0] != "runs" || parts[1].len() > 4 {
            return None;
        }
        self.runs.get(parts[1].parse::<usize>().ok()?)
    }

    /// The run's field and cameras, packed again when its checkpoint changed.
    fn cached(&self, served: &Served) -> Result<(Body, Body)> {
        let mut cache = served.cache.lock().unwrap_or_else(|p| p.into_inner());
        let version = checkpoint_version(&served.run);
        if let Some(c) = cache.as_ref().filter(|c| c.version == version) {
            return Ok((c.field.clone(), c.cameras.clone()));
        }
        let ck = checkpoint::load_with(&served.run.checkpoint, &self.device, false)?;
        let field = Arc::new(field_file(&ck)?);
        let cameras = Arc::new(cameras_file(&ck, served.run.data.as_deref()).into_bytes());
        *cache = Some(Cached { version, field: field.clone(), cameras: cameras.clone() });
        Ok((field, cameras))
    }
}

/// A checkpoint's identity without reading it: its size and modification
/// time (checkpoints are replaced by rename, so a new one changes both or
/// at least the time).
fn checkpoint_version(run: &ViewRun) -> String {
    match std::fs::metadata(&run.checkpoint) {
        Ok(m) => {
            let modified = m.modified().ok().and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok());
            format!("{}-{}", m.len(), modified.map_or(0, |d| d.as_nanos()))
        }
        Err(_) => "missing".into(),
    }
}

/// Serves `site` on `listener` until the process ends.
pub fn serve(listener: TcpListener, site: Arc<Site>) {
    for stream in listener.incoming() {
        let Ok(mut stream) = stream else { continue };
        if site.open.fetch_add(1, Ordering::SeqCst) >= MAX_CONNECTIONS {
            site.open.fetch_sub(1, Ordering::SeqCst);
            let _ = respond(&mut stream, 503, "text/plain", b"busy\n", false);
            continue;
        }
        let site = site.clone();
        std::thread::spawn(move || {
            let _ = handle(&mut stream, &site);
            site.open.fetch_sub(1, Ordering::SeqCst);
        });
    }
}

/// Reads one request and answers it.
fn handle(stream: &mut TcpStream, site: &Site) -> std::io::Result<()> {
    stream.set_read_timeout(Some(Duration::from_secs(10)))?;
    let head = match read_head(stream)? {
        Ok(head) => head,
        Err(status) => return respond(stream, status, "text/plain", b"bad request\n", false),
    };
    match parse(&head) {
        Ok((method, path)) => {
            let (status, kind, body) = site.get(path);
            respond(stream, status, kind, &body, method == "HEAD")
        }
        Err(status) => {
            let body = format!("{}\n", reason(status));
            respond(stream, status, "text/plain", body.as_bytes(), false)
        }
    }
}

/// The request head up to its blank line: Err(431) past `MAX_HEAD` bytes,
/// Err(400) when the connection ends first.
fn read_head(stream: &mut TcpStream) -> std::io::Result<Result<String, u16>> {
    let mut head = Vec::with_capacity(1024);
    let mut buf = [0u8; 1024];
    while !head.windows(4).any(|w| w == b"\r\n\r\n") {
        if head.len() > MAX_HEAD {
            return Ok(Err(431));
        }
        let n = stream.read(&mut buf)?;
        if n == 0 {
            return Ok(Err(400));
        }
        head.extend_from_slice(&buf[..n]);
    }
    Ok(String::from_utf8(head).map_err(|_| 400))
}

/// The method and path of a request head, or the status refusing it.
pub fn parse(head: &str) -> Result<(&str, &str), u16> {
    let mut lines = head.split("\r\n");
    let request = lines.next().unwrap_or_default();
    let mut words = request.split(' ');
    let (Some(method), Some(target), Some(version), None) = (words.next(), words.next(), words.next(), words.next())
    else {
        return Err(400);
    };
    if !version.starts_with("HTTP/1.") {
        return Err(400);
    }
    if method != "GET" && method != "HEAD" {
        return Err(405);
    }
    for header in lines.take_while(|l| !l.is_empty()) {
        let Some((name, value)) = header.split_once(':') else { return Err(400) };
        let name = name.trim().to_ascii_lowercase();
        let value = value.trim();
        if (name == "content-length" && value != "0") || name == "transfer-encoding" {
            return Err(413); // no request here has a body
        }
    }
    let path = target.split_once('?').map_or(target, |(p, _)| p);
    if path.len() > MAX_PATH {
        return Err(414);
    }
    let allowed = |c: char| c.is_ascii_alphanumeric() || "/._-".contains(c);
    if !path.starts_with('/') || path.contains("..") || path.contains("//") || !path.chars().all(allowed) {
        return Err(400);
    }
    Ok((method, path))
}

fn reason(status: u16) -> &'static str {
    match status {
        200 => "OK",
        400 => "Bad Request",
        404 => "Not Found",
        405 => "Method Not Allowed",
        413 => "Payload Too Large",
        414 => "URI Too Long",
        431 => "Request Header Fields Too Large",
        500 => "Internal Server Error",
        _ => "Service Unavailable",
    }
}

fn respond(stream: &mut TcpStream, status: u16, kind: &str, body: &[u8], head_only: bool) -> std::io::Result<()> {
    let allow = if status == 405 { "Allow: GET, HEAD\r\n" } else { "" };
    let head = format!(
        "HTTP/1.1 {status} {}\r\nContent-Type: {kind}\r\nContent-Length: {}\r\n{allow}Cache-Control: no-store\r\n\
         X-Content-Type-Options: nosniff\r\nConnection: close\r\n\r\n",
        reason(status),
        body.len()
    );
    stream.write_all(head.as_bytes())?;
    if !head_only {
        stream.write_all(body)?;
    }
    stream.flush()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn requests_other_than_a_plain_get_of_a_clean_path_are_refused() {
        let get =
            |target: &str| parse(&format!("GET {target} HTTP/1.1\r\nHost: x\r\n\r\n")).map(|(_, p)| p.to_string());
        assert_eq!(get("/runs/0/field.bin"), Ok("/runs/0/field.bin".into()));
        assert_eq!(get("/runs.json?t=5"), Ok("/runs.json".into()));
        for bad in ["/../Cargo.toml", "/runs/0/../../x", "/%2e%2e/x", "//etc/passwd", "/a\\b", "runs.json", "/ü"] {
            assert_eq!(get(bad), Err(400), "{bad}");
        }
        assert_eq!(get(&format!("/{}", "a".repeat(MAX_PATH))), Err(414));
        assert_eq!(parse("POST / HTTP/1.1\r\n\r\n"), Err(405));
        assert_eq!(parse("DELETE /runs.json HTTP/1.1\r\n\r\n"), Err(405));
        assert_eq!(parse("GET / HTTP/1.1\r\nContent-Length: 5\r\n\r\n"), Err(413));
        assert_eq!(parse("GET / HTTP/1.1\r\nTransfer-Encoding: chunked\r\n\r\n"), Err(413));
        assert_eq!(parse("GET / HTTP/1.1\r\nno colon\r\n\r\n"), Err(400));
        assert_eq!(parse("GET /\r\n\r\n"), Err(400));
        assert_eq!(parse("garbage\r\n\r\n"), Err(400));
        assert_eq!(parse("GET / SPDY/3\r\n\r\n"), Err(400));
    }
}
