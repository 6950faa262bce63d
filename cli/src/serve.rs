//! `silvr serve DIR`: the built studio (trunk's `dist/`) and a folder of reconstructions over HTTP, and the
//! link that opens the folder's point clouds in the studio.
//!
//! Hand-rolled on `std::net` with one thread per connection: a static file server with byte ranges and a
//! strict CORS rule is all this needs, and no crate in the tree is made for it (an HTTP framework would
//! bring an async runtime for a handful of local connections).
//!
//! URL layout: `/data/<path>` is a file under DIR, every other path a file of the studio (`/` its
//! `index.html`). Nothing outside the two roots is ever read: paths are decoded, checked segment by
//! segment, canonicalised and required to stay inside their root (so a symlink out of it is refused).

use std::fs::File;
use std::io::{self, Read, Seek, SeekFrom, Write};
use std::net::{IpAddr, Shutdown, TcpListener, TcpStream};
use std::path::{Component, Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
// The link's encoding is the studio's own (one codec for the links serve prints and the page reads).
use silvr_worker::view::{decode_bytes, encode};

/// Largest request head (request line + headers) accepted; larger ones get 431.
const MAX_HEAD_BYTES: usize = 16 * 1024;
/// Time a client has to send its whole request head (also bounds a slow-drip client).
const HEAD_TIMEOUT: Duration = Duration::from_secs(10);
/// A client that stops reading a download for this long loses the connection (and frees its thread).
const WRITE_TIMEOUT: Duration = Duration::from_secs(60);
/// Connections served at once (one thread each); more get 503.
const MAX_CONNECTIONS: usize = 64;
/// PLY files the printed link opens at once, and directory levels searched for them.
const MAX_LINKED_PLYS: usize = 16;
const PLY_SEARCH_DEPTH: usize = 4;
/// How to build the studio, printed when none is found.
const BUILD_STUDIO: &str =
    "scripts/setup.sh studio && PATH=\"$PWD/web/node_modules/.bin:$PATH\" trunk build --release";

#[derive(clap::Args)]
pub struct ServeCmd {
    /// Folder served under /data/ (e.g. a `silvr demo` or `silvr train` output).
    dir: PathBuf,
    /// TCP port; 0 picks a free one.
    #[arg(long, default_value_t = 8080)]
    port: u16,
    /// Address to listen on. Anything but loopback makes DIR readable from the network.
    #[arg(long, default_value = "127.0.0.1")]
    bind: IpAddr,
    /// The built studio (default: $SILVR_STUDIO_DIST, else ./dist, else the dist/ of the workspace this
    /// binary was built in).
    #[arg(long)]
    studio: Option<PathBuf>,
    /// Also let pages of this origin (e.g. https://studio.example) read the files; repeatable, `*` for
    /// any website.
    #[arg(long = "allow-origin", value_name = "ORIGIN")]
    allow_origin: Vec<String>,
    /// Log one line per request to stderr.
    #[arg(long)]
    verbose: bool,
}

pub fn run(cmd: ServeCmd) -> Result<()> {
    let data = cmd
        .dir
        .canonicalize()
        .with_context(|| format!("{}: no such folder", cmd.dir.display()))?;
    if !data.is_dir() {
        bail!("{} is not a folder", cmd.dir.display());
    }
    let studio = find_studio(cmd.studio.as_deref());
    let listener = TcpListener::bind((cmd.bind, cmd.port)).with_context(|| {
        format!(
            "listening on {}:{} (another server on that port? --port 0 picks a free one)",
            cmd.bind, cmd.port
        )
    })?;
    let port = listener.local_addr()?.port();
    let cors = Cors::new(cmd.bind, port, &cmd.allow_origin)?;

    let host = link_host(cmd.bind);
    let plys = find_plys(&data);
    let studio_label = match (&studio.root, studio.built) {
        (Some(root), true) => root.display().to_string(),
        _ => format!("{} (not built)", studio.shown.display()),
    };
    let mut out = io::stdout().lock();
    writeln!(
        out,
        "serving the studio from {studio_label} and {} at http://{}:{port}/",
        data.display(),
        url_host(cmd.bind)
    )?;
    writeln!(out, "open: {}", studio_link(&host, port, &plys))?;
    for rel in &plys {
        writeln!(
            out,
            "  {}: {}",
            rel.display(),
            studio_link(&host, port, std::slice::from_ref(rel))
        )?;
    }
    out.flush()?;
    drop(out);
    if plys.is_empty() {
        eprintln!(
            "note: no .ply file within {PLY_SEARCH_DEPTH} levels of {}",
            data.display()
        );
    }
    if !studio.built {
        eprintln!(
            "warning: the studio is not built (no index.html in {}); only /data/ is served. Build it in \
             {} with:\n  {BUILD_STUDIO}",
            studio.shown.display(),
            workspace_root().display()
        );
    }
    if !cmd.bind.is_loopback() {
        eprintln!(
            "warning: listening on {}: anyone on the network can read everything under {}",
            cmd.bind,
            data.display()
        );
    }

    let server = Arc::new(Server {
        studio: studio.root,
        data,
        cors,
        verbose: cmd.verbose,
    });
    let active = Arc::new(AtomicUsize::new(0));
    for conn in listener.incoming() {
        let conn = match conn {
            Ok(c) => c,
            Err(e) => {
                // Out of file descriptors and the like: back off instead of spinning on the error.
                eprintln!("warning: accepting a connection: {e}");
                std::thread::sleep(Duration::from_millis(50));
                continue;
            }
        };
        if active.fetch_add(1, Ordering::SeqCst) >= MAX_CONNECTIONS {
            active.fetch_sub(1, Ordering::SeqCst);
            busy(conn);
            continue;
        }
        let slot = Slot(active.clone());
        let server = server.clone();
        // On a failed spawn the closure, and with it the slot, is dropped: the count stays right.
        let spawned = std::thread::Builder::new()
            .name("silvr-serve".into())
            .spawn(move || {
                let _slot = slot;
                server.handle(conn);
            });
        if let Err(e) = spawned {
            eprintln!("warning: starting a connection thread: {e}");
        }
    }
    Ok(())
}

/// `silvr serve OUT` as a command the user can paste: this binary's absolute path, quoted for a shell.
pub fn open_command(out: &Path) -> String {
    let exe = std::env::current_exe().unwrap_or_else(|_| PathBuf::from("silvr"));
    // Linux names a binary rebuilt while it ran "<path> (deleted)"; the path itself holds the new build.
    let exe = exe
        .to_str()
        .and_then(|s| s.strip_suffix(" (deleted)"))
        .map(PathBuf::from)
        .filter(|p| p.is_file())
        .unwrap_or(exe);
    let out = out.canonicalize().unwrap_or_else(|_| out.to_path_buf());
    format!(
        "{} serve {}",
        shell_quote(&exe.to_string_lossy()),
        shell_quote(&out.to_string_lossy())
    )
}

fn shell_quote(s: &str) -> String {
    let plain = !s.is_empty()
        && s.bytes()
            .all(|b| b.is_ascii_alphanumeric() || b"_-./:@%+=,".contains(&b));
    if plain {
        s.to_string()
    } else {
        format!("'{}'", s.replace('\'', r"'\''"))
    }
}

/// Decrements the connection count when its thread ends, however it ends.
struct Slot(Arc<AtomicUsize>);

impl Drop for Slot {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::SeqCst);
    }
}

/// Answers a connection over the limit without reading it (written from the accept loop: keep it short).
fn busy(mut conn: TcpStream) {
    let _ = conn.set_write_timeout(Some(Duration::from_secs(1)));
    let body = "too many connections, retry\n";
    let _ = write!(
        conn,
        "HTTP/1.1 503 Service Unavailable\r\nRetry-After: 1\r\nContent-Type: text/plain; charset=utf-8\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    let _ = conn.shutdown(Shutdown::Write);
}

/// The studio folder chosen, and whether it holds a build.
struct Studio {
    /// Canonical root files are served from (None: nothing to serve).
    root: Option<PathBuf>,
    /// The path named in messages.
    shown: PathBuf,
    built: bool,
}

/// `--studio`, else `$SILVR_STUDIO_DIST`, else the first of `./dist` and the build workspace's `dist/`
/// that holds `index.html`. A folder named explicitly is served even without a build (with a warning).
fn find_studio(flag: Option<&Path>) -> Studio {
    let explicit = flag.map(Path::to_path_buf).or_else(|| {
        std::env::var_os("SILVR_STUDIO_DIST")
            .filter(|v| !v.is_empty())
            .map(PathBuf::from)
    });
    let workspace = workspace_root().join("dist");
    let candidates = match &explicit {
        Some(p) => vec![p.clone()],
        None => vec![PathBuf::from("dist"), workspace.clone()],
    };
    for dir in &candidates {
        if let Ok(root) = dir.canonicalize() {
            if root.join("index.html").is_file() {
                return Studio {
                    shown: root.clone(),
                    root: Some(root),
                    built: true,
                };
            }
        }
    }
    match explicit {
        Some(p) => Studio {
            root: p.canonicalize().ok().filter(|r| r.is_dir()),
            shown: p,
            built: false,
        },
        None => Studio {
            root: None,
            shown: workspace.canonicalize().unwrap_or(workspace),
            built: false,
        },
    }
}

/// The workspace this binary was built in (where the studio is built).
fn workspace_root() -> PathBuf {
    let cli = Path::new(env!("CARGO_MANIFEST_DIR"));
    cli.parent().unwrap_or(cli).to_path_buf()
}

/// Host of the printed links: loopback for a wildcard bind (the browser is most likely on this machine).
fn link_host(bind: IpAddr) -> String {
    match bind {
        IpAddr::V4(a) if a.is_unspecified() => "127.0.0.1".into(),
        IpAddr::V6(a) if a.is_unspecified() => "[::1]".into(),
        ip => url_host(ip),
    }
}

/// An address as a URL's host (IPv6 in brackets).
fn url_host(ip: IpAddr) -> String {
    match ip {
        IpAddr::V4(a) => a.to_string(),
        IpAddr::V6(a) => format!("[{a}]"),
    }
}

/// `http://HOST:PORT/#src=<data URL>&src=...`: the studio reads its inputs from the fragment, which the
/// browser never sends to a server.
fn studio_link(host: &str, port: u16, plys: &[PathBuf]) -> String {
    let srcs: Vec<String> = plys
        .iter()
        .map(|rel| format!("src={}", encode(&data_url(host, port, rel))))
        .collect();
    if srcs.is_empty() {
        format!("http://{host}:{port}/")
    } else {
        format!("http://{host}:{port}/#{}", srcs.join("&"))
    }
}

/// The URL of a file under DIR, each path segment percent-encoded.
fn data_url(host: &str, port: u16, rel: &Path) -> String {
    let segments: Vec<String> = rel
        .components()
        .map(|c| encode(&c.as_os_str().to_string_lossy()))
        .collect();
    format!("http://{host}:{port}/data/{}", segments.join("/"))
}

/// `.ply` files under `root` (at most [`PLY_SEARCH_DEPTH`] path components deep), relative to it, sorted
/// by path, the first [`MAX_LINKED_PLYS`]. Only files the server would serve: UTF-8 names, inside the root.
fn find_plys(root: &Path) -> Vec<PathBuf> {
    fn walk(root: &Path, rel: &Path, depth: usize, found: &mut Vec<PathBuf>) {
        let Ok(entries) = std::fs::read_dir(root.join(rel)) else {
            return;
        };
        for entry in entries.flatten() {
            let name = entry.file_name();
            let Some(name) = name.to_str() else { continue };
            let rel = rel.join(name);
            let Ok(kind) = entry.file_type() else {
                continue;
            };
            if kind.is_dir() {
                // Not through symlinks: no loops, and nothing outside the root. Not into datasets (a
                // demo's `dataset/` holds ground truth and hundreds of lidar sweeps): the link is for
                // reconstructions.
                let dataset = ["manifest.json", "transforms.json"]
                    .iter()
                    .any(|f| root.join(&rel).join(f).is_file());
                if depth < PLY_SEARCH_DEPTH && !dataset {
                    walk(root, &rel, depth + 1, found);
                }
            } else if name.to_ascii_lowercase().ends_with(".ply") {
                let inside = root
                    .join(&rel)
                    .canonicalize()
                    .is_ok_and(|p| p.starts_with(root) && p.is_file());
                if inside {
                    found.push(rel);
                }
            }
        }
    }
    let mut found = Vec::new();
    walk(root, Path::new(""), 1, &mut found);
    // Shallow files first (a folder's own reconstructions before its sub-folders'), then by path.
    found.sort_by(|a, b| (a.components().count(), a).cmp(&(b.components().count(), b)));
    found.truncate(MAX_LINKED_PLYS);
    found
}

/// Which cross-origin pages may read the responses.
struct Cors {
    /// Allowed origins, as browsers write them (`scheme://host[:port]`).
    origins: Vec<String>,
    /// `--allow-origin '*'`: any website.
    any: bool,
    /// `Host` values a loopback server answers (`None`: any).
    hosts: Option<Vec<String>>,
}

impl Cors {
    /// The server's own origins (its bind address, and the loopback names when it listens on loopback),
    /// plus the `--allow-origin` ones. Never any website by default: a page elsewhere must not be able to
    /// read a user's files off a loopback server.
    fn new(bind: IpAddr, port: u16, extra: &[String]) -> Result<Cors> {
        let origin = |host: &str| {
            if port == 80 {
                format!("http://{host}")
            } else {
                format!("http://{host}:{port}")
            }
        };
        let mut origins = vec![origin(&url_host(bind))];
        // A wildcard bind listens on loopback too: pages from these origins are this same server.
        if bind.is_loopback() || bind.is_unspecified() {
            for host in ["localhost", "127.0.0.1", "[::1]"] {
                origins.push(origin(host));
            }
        }
        let mut any = false;
        for o in extra {
            let o = o.trim().trim_end_matches('/');
            if o == "*" {
                any = true;
            } else if o == "null" || o.contains("://") {
                origins.push(o.to_string());
            } else {
                bail!("--allow-origin {o}: expected an origin like https://studio.example[:port] or *");
            }
        }
        // DNS rebinding: a website whose name is made to resolve to 127.0.0.1 would be same-origin with a
        // loopback server and read DIR without any CORS check. A loopback server answers only requests
        // addressed to its own names; one bound to a network address (the user was warned) answers all.
        let hosts = (bind.is_loopback() || bind.is_unspecified()).then(|| {
            let mut h: Vec<String> = ["localhost", "127.0.0.1", "[::1]"]
                .iter()
                .map(|n| n.to_string())
                .chain([url_host(bind)])
                .collect();
            // `--allow-origin` names a studio elsewhere, not a name for this server; it stays out.
            h.dedup();
            h.iter()
                .flat_map(|n| {
                    let with_port = format!("{n}:{port}");
                    if port == 80 {
                        vec![with_port, n.clone()]
                    } else {
                        vec![with_port]
                    }
                })
                .collect()
        });
        Ok(Cors {
            origins,
            any,
            hosts,
        })
    }

    /// Whether a request with this `Host` header is addressed to this server (see `hosts`). Requests
    /// without one (HTTP/1.0 tools) are; browsers always send it.
    fn host_ok(&self, host: Option<&str>) -> bool {
        match (&self.hosts, host) {
            (Some(names), Some(h)) => names.iter().any(|n| n.eq_ignore_ascii_case(h.trim())),
            _ => true,
        }
    }

    /// `Access-Control-Allow-Origin` for a request with this `Origin` header, if it may read the answer.
    fn allow(&self, origin: Option<&str>) -> Option<String> {
        if let Some(o) = origin {
            if self.origins.iter().any(|a| a.eq_ignore_ascii_case(o)) {
                return Some(o.to_string());
            }
        }
        self.any.then(|| "*".to_string())
    }
}

/// A parsed request head (header names lower-cased).
#[derive(Debug)]
struct Request {
    method: String,
    target: String,
    headers: Vec<(String, String)>,
}

impl Request {
    fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_str())
    }
}

enum Body {
    Empty,
    Text(String),
    /// `len` bytes of the file from `start`, streamed.
    File {
        file: File,
        start: u64,
        len: u64,
    },
}

struct Response {
    status: u16,
    headers: Vec<(&'static str, String)>,
    body: Body,
}

impl Response {
    fn text(status: u16, text: impl Into<String>) -> Response {
        Response {
            status,
            headers: vec![("Content-Type", "text/plain; charset=utf-8".into())],
            body: Body::Text(text.into()),
        }
    }

    fn error(status: u16) -> Response {
        Response::text(status, format!("{status} {}\n", reason(status)))
    }
}

struct Server {
    /// Canonical roots.
    studio: Option<PathBuf>,
    data: PathBuf,
    cors: Cors,
    verbose: bool,
}

impl Server {
    fn handle(&self, mut conn: TcpStream) {
        let _ = conn.set_write_timeout(Some(WRITE_TIMEOUT));
        let _ = conn.set_nodelay(true);
        let (response, head_only, line) = match read_head(&mut conn) {
            Ok(req) => (
                self.respond(&req),
                req.method == "HEAD",
                format!("{} {}", req.method, req.target),
            ),
            Err(None) => return,
            Err(Some(status)) => (Response::error(status), false, "(bad request)".into()),
        };
        let status = response.status;
        let sent = write_response(&mut conn, response, head_only);
        if self.verbose {
            let peer = conn
                .peer_addr()
                .map_or_else(|_| "?".into(), |a| a.to_string());
            match sent {
                Ok(n) => eprintln!("{peer} {line} {status} {n}"),
                Err(e) => eprintln!("{peer} {line} {status} ({e})"),
            }
        }
        finish(conn);
    }

    fn respond(&self, req: &Request) -> Response {
        if !self.cors.host_ok(req.header("host")) {
            return Response::text(
                421,
                "421 Misdirected Request: this loopback server answers only requests addressed to \
                 localhost, 127.0.0.1 or [::1] (DNS rebinding protection)\n"
                    .to_string(),
            );
        }
        let allow = self.cors.allow(req.header("origin"));
        let mut resp = match req.method.as_str() {
            "GET" | "HEAD" => self.get(req),
            "OPTIONS" => {
                let mut r = Response {
                    status: 204,
                    headers: vec![("Allow", "GET, HEAD, OPTIONS".into())],
                    body: Body::Empty,
                };
                if allow.is_some() {
                    r.headers.extend([
                        ("Access-Control-Allow-Methods", "GET, HEAD, OPTIONS".into()),
                        ("Access-Control-Allow-Headers", "Range".into()),
                        ("Access-Control-Max-Age", "600".into()),
                    ]);
                    // Chrome's Private Network Access: a public page asking for a loopback server.
                    if req.header("access-control-request-private-network") == Some("true") {
                        r.headers
                            .push(("Access-Control-Allow-Private-Network", "true".into()));
                    }
                }
                r
            }
            _ => {
                let mut r = Response::error(405);
                r.headers.push(("Allow", "GET, HEAD, OPTIONS".into()));
                r
            }
        };
        if let Some(origin) = allow {
            resp.headers.extend([
                ("Access-Control-Allow-Origin", origin),
                (
                    "Access-Control-Expose-Headers",
                    "Content-Length, Content-Range, Accept-Ranges".into(),
                ),
            ]);
        }
        resp
    }

    fn get(&self, req: &Request) -> Response {
        let segments = match request_path(&req.target) {
            Ok(s) => s,
            Err(status) => return Response::error(status),
        };
        let (root, rel) = match segments.split_first() {
            Some((first, rest)) if first == "data" => (Some(self.data.as_path()), rest),
            _ => (self.studio.as_deref(), &segments[..]),
        };
        let Some(root) = root else {
            return Response::text(
                404,
                format!(
                    "The SiLVR studio is not built; the data is under /data/. Build it in the workspace \
                     with:\n  {BUILD_STUDIO}\nand restart silvr serve.\n"
                ),
            );
        };
        let path = match resolve(root, rel) {
            Ok(p) => p,
            Err(status) => return Response::error(status),
        };
        let file = match File::open(&path) {
            Ok(f) => f,
            Err(e) => return Response::error(io_status(&e)),
        };
        let len = match file.metadata() {
            Ok(m) if m.is_file() => m.len(),
            Ok(_) => return Response::error(404),
            Err(e) => return Response::error(io_status(&e)),
        };
        let mut headers = vec![("Content-Type", mime(&path).into())];
        // If-Range names a version we never handed out (no validators): send the whole file.
        let range = match req.header("range") {
            Some(r) if req.header("if-range").is_none() => parse_range(r, len),
            _ => ByteRange::Full,
        };
        let (status, start, count) = match range {
            ByteRange::Full => (200, 0, len),
            ByteRange::Part { start, end } => {
                headers.push(("Content-Range", format!("bytes {start}-{end}/{len}")));
                (206, start, end - start + 1)
            }
            ByteRange::Unsatisfiable => {
                let mut r = Response::error(416);
                r.headers.push(("Content-Range", format!("bytes */{len}")));
                return r;
            }
        };
        Response {
            status,
            headers,
            body: Body::File {
                file,
                start,
                len: count,
            },
        }
    }
}

/// Reads the request head: `Err(None)` when the client went away or sent nothing, `Err(Some(status))`
/// for a head to answer with an error (400 malformed, 408 too slow, 431 too large).
fn read_head(conn: &mut TcpStream) -> Result<Request, Option<u16>> {
    let deadline = Instant::now() + HEAD_TIMEOUT;
    let mut buf = Vec::with_capacity(1024);
    let mut chunk = [0u8; 4096];
    loop {
        if let Some(end) = head_end(&buf) {
            if end > MAX_HEAD_BYTES {
                return Err(Some(431));
            }
            return parse_head(&buf[..end]).map_err(Some);
        }
        if buf.len() > MAX_HEAD_BYTES {
            return Err(Some(431));
        }
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() || conn.set_read_timeout(Some(left)).is_err() {
            return Err((!buf.is_empty()).then_some(408));
        }
        match conn.read(&mut chunk) {
            Ok(0) => return Err(None),
            Ok(n) => buf.extend_from_slice(&chunk[..n]),
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) =>
            {
                return Err((!buf.is_empty()).then_some(408));
            }
            Err(_) => return Err(None),
        }
    }
}

/// End of the head (after its blank line), for CRLF and bare-LF line ends.
fn head_end(buf: &[u8]) -> Option<usize> {
    let crlf = buf.windows(4).position(|w| w == b"\r\n\r\n").map(|i| i + 4);
    let lf = buf.windows(2).position(|w| w == b"\n\n").map(|i| i + 2);
    match (crlf, lf) {
        (Some(a), Some(b)) => Some(a.min(b)),
        (a, b) => a.or(b),
    }
}

/// Parses a request head; errors are the status to answer with.
fn parse_head(head: &[u8]) -> Result<Request, u16> {
    let text = String::from_utf8_lossy(head);
    // Blank lines before the request line are to be ignored (RFC 9112 §2.2).
    let mut lines = text
        .trim_start_matches(['\r', '\n'])
        .split('\n')
        .map(|l| l.strip_suffix('\r').unwrap_or(l));
    let request_line = lines.next().ok_or(400u16)?;
    let mut parts = request_line.split(' ');
    let (Some(method), Some(target), Some(version), None) =
        (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return Err(400);
    };
    let token = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_graphic());
    if !token(method) || !token(target) || !version.starts_with("HTTP/") {
        return Err(400);
    }
    if !version.starts_with("HTTP/1.") {
        return Err(505);
    }
    let mut headers = Vec::new();
    for line in lines.take_while(|l| !l.is_empty()) {
        let (name, value) = line.split_once(':').ok_or(400u16)?;
        if !token(name) {
            return Err(400);
        }
        headers.push((name.to_ascii_lowercase(), value.trim().to_string()));
    }
    Ok(Request {
        method: method.to_string(),
        target: target.to_string(),
        headers,
    })
}

/// The file path segments a request target names, decoded and checked: `..`, NUL, backslashes, empty
/// segments (`//`: an absolute path once a prefix is cut) and anything that is not a plain file name are
/// refused. Errors are the status to answer with (400 malformed, 403 refused).
fn request_path(target: &str) -> Result<Vec<String>, u16> {
    // Absolute form (`GET http://host/path`), which HTTP/1.1 servers must accept.
    let target = match target.split_once("://") {
        Some((scheme, rest)) if !scheme.contains('/') => rest.find('/').map_or("/", |i| &rest[i..]),
        _ => target,
    };
    let path = target.split(['?', '#']).next().unwrap_or_default();
    let Some(path) = path.strip_prefix('/') else {
        return Err(400);
    };
    let decoded = decode_bytes(path).ok_or(400u16)?;
    let decoded = String::from_utf8(decoded).map_err(|_| 400u16)?;
    if decoded.contains('\0') {
        return Err(400);
    }
    if decoded.contains('\\') {
        return Err(403);
    }
    let parts: Vec<&str> = decoded.split('/').collect();
    let mut segments = Vec::new();
    for (i, seg) in parts.iter().enumerate() {
        match *seg {
            // A trailing slash names a folder (its index.html); an empty path is the root.
            "" if i + 1 == parts.len() => {}
            "" | ".." => return Err(403),
            "." => {}
            _ => {
                let mut components = Path::new(seg).components();
                if !matches!(
                    (components.next(), components.next()),
                    (Some(Component::Normal(_)), None)
                ) {
                    return Err(403);
                }
                segments.push(seg.to_string());
            }
        }
    }
    Ok(segments)
}

/// The canonical file `segments` names under `root` (a folder's `index.html`), refused (403) when it
/// leaves the root, e.g. through a symlink.
fn resolve(root: &Path, segments: &[String]) -> Result<PathBuf, u16> {
    let mut path = root.to_path_buf();
    path.extend(segments);
    let mut path = path.canonicalize().map_err(|e| io_status(&e))?;
    if path.is_dir() {
        path = path
            .join("index.html")
            .canonicalize()
            .map_err(|e| io_status(&e))?;
    }
    if !path.starts_with(root) {
        return Err(403);
    }
    Ok(path)
}

fn io_status(e: &io::Error) -> u16 {
    match e.kind() {
        io::ErrorKind::PermissionDenied => 403,
        _ => 404,
    }
}

/// A `Range` header's meaning for a file of `len` bytes.
#[derive(Debug, PartialEq, Eq)]
enum ByteRange {
    /// No usable range: the whole file (200). Also for several ranges, which we may answer whole.
    Full,
    /// Bytes `start..=end` (206).
    Part { start: u64, end: u64 },
    /// 416.
    Unsatisfiable,
}

/// Parses a single byte range (`bytes=a-b`, `bytes=a-`, `bytes=-n`). A syntactically invalid header is
/// ignored (RFC 9110 §14.2), so it means the whole file; one that starts past the end is unsatisfiable.
fn parse_range(value: &str, len: u64) -> ByteRange {
    let Some((unit, set)) = value.split_once('=') else {
        return ByteRange::Full;
    };
    if !unit.trim().eq_ignore_ascii_case("bytes") || set.contains(',') {
        return ByteRange::Full;
    }
    let Some((a, b)) = set.split_once('-') else {
        return ByteRange::Full;
    };
    let (a, b) = (a.trim(), b.trim());
    if a.is_empty() {
        let Some(n) = digits(b) else {
            return ByteRange::Full;
        };
        if n == 0 || len == 0 {
            return ByteRange::Unsatisfiable;
        }
        return ByteRange::Part {
            start: len - n.min(len),
            end: len - 1,
        };
    }
    let Some(start) = digits(a) else {
        return ByteRange::Full;
    };
    let end = if b.is_empty() {
        u64::MAX
    } else {
        match digits(b) {
            Some(e) if e >= start => e,
            _ => return ByteRange::Full,
        }
    };
    if start >= len {
        return ByteRange::Unsatisfiable;
    }
    ByteRange::Part {
        start,
        end: end.min(len - 1),
    }
}

/// A decimal number; too many digits saturate (such a position is past any file's end).
fn digits(s: &str) -> Option<u64> {
    if s.is_empty() || !s.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some(s.bytes().fold(0u64, |n, d| {
        n.saturating_mul(10).saturating_add(u64::from(d - b'0'))
    }))
}

/// Content types by extension. `.wasm` must be `application/wasm` for streaming compilation; PLY and
/// unknown files are opaque bytes (with `nosniff`, a browser never renders them as a page).
fn mime(path: &Path) -> &'static str {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or_default()
        .to_ascii_lowercase();
    match ext.as_str() {
        "html" | "htm" => "text/html; charset=utf-8",
        "js" | "mjs" => "text/javascript",
        "wasm" => "application/wasm",
        "css" => "text/css",
        "json" => "application/json",
        "png" => "image/png",
        "jpg" | "jpeg" => "image/jpeg",
        _ => "application/octet-stream",
    }
}

fn reason(status: u16) -> &'static str {
    match status {
        200 => "OK",
        204 => "No Content",
        206 => "Partial Content",
        400 => "Bad Request",
        403 => "Forbidden",
        404 => "Not Found",
        405 => "Method Not Allowed",
        408 => "Request Timeout",
        416 => "Range Not Satisfiable",
        421 => "Misdirected Request",
        431 => "Request Header Fields Too Large",
        503 => "Service Unavailable",
        505 => "HTTP Version Not Supported",
        _ => "Error",
    }
}

/// Writes the response (the head only for HEAD); returns the body bytes sent. Files are streamed (on
/// Linux `io::copy` hands them to the kernel), never read whole.
fn write_response(conn: &mut TcpStream, resp: Response, head_only: bool) -> io::Result<u64> {
    let length = match &resp.body {
        Body::Empty => None,
        Body::Text(t) => Some(t.len() as u64),
        Body::File { len, .. } => Some(*len),
    };
    let mut head = format!("HTTP/1.1 {} {}\r\n", resp.status, reason(resp.status));
    for (name, value) in &resp.headers {
        head.push_str(&format!("{name}: {value}\r\n"));
    }
    if let Some(n) = length {
        head.push_str(&format!("Content-Length: {n}\r\n"));
    }
    head.push_str(
        "Accept-Ranges: bytes\r\nCache-Control: no-cache\r\nVary: Origin\r\n\
         X-Content-Type-Options: nosniff\r\nConnection: close\r\n\r\n",
    );
    if head_only {
        conn.write_all(head.as_bytes())?;
        return Ok(0);
    }
    match resp.body {
        Body::Empty => {
            conn.write_all(head.as_bytes())?;
            Ok(0)
        }
        Body::Text(t) => {
            head.push_str(&t);
            conn.write_all(head.as_bytes())?;
            Ok(t.len() as u64)
        }
        Body::File {
            mut file,
            start,
            len,
        } => {
            conn.write_all(head.as_bytes())?;
            file.seek(SeekFrom::Start(start))?;
            io::copy(&mut file.take(len), conn)
        }
    }
}

/// Closes gracefully: half-close, then drain what the client still sends for a moment, so that closing
/// with unread bytes does not reset the connection before the client has read the response.
fn finish(mut conn: TcpStream) {
    let _ = conn.flush();
    if conn.shutdown(Shutdown::Write).is_err() {
        return;
    }
    let _ = conn.set_read_timeout(Some(Duration::from_secs(1)));
    let mut sink = [0u8; 4096];
    let mut drained = 0;
    while drained < 256 * 1024 {
        match conn.read(&mut sink) {
            Ok(0) | Err(_) => break,
            Ok(n) => drained += n,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::net::Ipv4Addr;

    const LOCAL: IpAddr = IpAddr::V4(Ipv4Addr::LOCALHOST);

    #[test]
    fn ranges_of_every_form() {
        use ByteRange::*;
        let p = |start, end| Part { start, end };
        assert_eq!(parse_range("bytes=10-19", 100), p(10, 19));
        assert_eq!(parse_range("bytes=0-0", 100), p(0, 0));
        assert_eq!(parse_range("bytes=90-", 100), p(90, 99));
        assert_eq!(parse_range("bytes=-5", 100), p(95, 99));
        assert_eq!(
            parse_range("bytes=-500", 100),
            p(0, 99),
            "suffix longer than the file"
        );
        assert_eq!(parse_range("bytes=50-1000", 100), p(50, 99), "end clamped");
        assert_eq!(
            parse_range("Bytes = 1 - 2", 100),
            p(1, 2),
            "spaces, unit case"
        );
        assert_eq!(parse_range("bytes=99-", 100), p(99, 99));
        assert_eq!(
            parse_range("bytes=5-99999999999999999999999", 100),
            p(5, 99),
            "huge end saturates"
        );
    }

    #[test]
    fn invalid_ranges_mean_the_whole_file() {
        for r in [
            "",
            "bytes",
            "bytes=",
            "bytes=-",
            "bytes=a-b",
            "bytes=5",
            "bytes=9-3",
            "bytes=1-2-3",
            "bytes=+1-2",
            "bytes=0x10-",
            "items=0-1",
            "bytes=0-1,5-6",
            "bytes=0-1,",
        ] {
            assert_eq!(parse_range(r, 100), ByteRange::Full, "{r:?}");
        }
    }

    #[test]
    fn unsatisfiable_ranges() {
        for (r, len) in [
            ("bytes=100-", 100),
            ("bytes=100-200", 100),
            ("bytes=99999999999999999999999-", 100),
            ("bytes=-0", 100),
            ("bytes=0-", 0),
            ("bytes=-1", 0),
        ] {
            assert_eq!(
                parse_range(r, len),
                ByteRange::Unsatisfiable,
                "{r:?} of {len}"
            );
        }
    }

    #[test]
    fn request_paths_are_decoded_into_plain_segments() {
        let ok = |t: &str| request_path(t).unwrap();
        assert_eq!(ok("/"), Vec::<String>::new());
        assert_eq!(ok("/index.html"), ["index.html"]);
        assert_eq!(ok("/data/sub/x.ply?v=1#frag"), ["data", "sub", "x.ply"]);
        assert_eq!(ok("/data/sub/"), ["data", "sub"]);
        assert_eq!(ok("/data/./a%20b.ply"), ["data", "a b.ply"]);
        assert_eq!(ok("/data/caf%C3%A9"), ["data", "café"]);
        assert_eq!(
            ok("/a..b/c..."),
            ["a..b", "c..."],
            "dots inside names are fine"
        );
        assert_eq!(ok("http://127.0.0.1:8080/data/x"), ["data", "x"]);
    }

    #[test]
    fn traversal_and_odd_bytes_are_refused() {
        for (t, status) in [
            ("/data/../secret", 403),
            ("/../secret", 403),
            ("/data/%2e%2e/secret", 403),
            ("/data/%2E%2E/secret", 403),
            ("/data/sub/%2e%2e%2f%2e%2e%2fsecret", 403),
            ("/data/..%5csecret", 403),
            ("/data/a%5cb", 403),
            ("/data\\..\\secret", 403),
            ("//etc/passwd", 403),
            ("/data//etc/passwd", 403),
            ("/data/%2fetc%2fpasswd", 403),
            ("/data/x%00.ply", 400),
            ("/data/%zz", 400),
            ("/data/%4", 400),
            ("/data/%ff", 400),
            ("data/x", 400),
            ("*", 400),
        ] {
            assert_eq!(request_path(t), Err(status), "{t}");
        }
    }

    #[test]
    fn percent_encoding_keeps_only_the_unreserved_set() {
        assert_eq!(encode("AZaz09-._~"), "AZaz09-._~");
        assert_eq!(
            encode("http://127.0.0.1:8080/data/silvr/points.ply"),
            "http%3A%2F%2F127.0.0.1%3A8080%2Fdata%2Fsilvr%2Fpoints.ply"
        );
        assert_eq!(encode("a b&c=d#e%"), "a%20b%26c%3Dd%23e%25");
        assert_eq!(encode("é"), "%C3%A9");
        assert_eq!(
            decode_bytes(&encode("a b/é%")).unwrap(),
            "a b/é%".as_bytes()
        );
    }

    #[test]
    fn the_link_holds_the_encoded_data_urls() {
        let one = [PathBuf::from("silvr/points.ply")];
        assert_eq!(
            studio_link("127.0.0.1", 8080, &one),
            "http://127.0.0.1:8080/#src=http%3A%2F%2F127.0.0.1%3A8080%2Fdata%2Fsilvr%2Fpoints.ply"
        );
        let two = [PathBuf::from("a.ply"), PathBuf::from("my dir/b.ply")];
        assert_eq!(
            studio_link("127.0.0.1", 1, &two),
            "http://127.0.0.1:1/#src=http%3A%2F%2F127.0.0.1%3A1%2Fdata%2Fa.ply\
             &src=http%3A%2F%2F127.0.0.1%3A1%2Fdata%2Fmy%2520dir%2Fb.ply"
        );
        assert_eq!(studio_link("127.0.0.1", 1, &[]), "http://127.0.0.1:1/");
        assert_eq!(link_host(IpAddr::V4(Ipv4Addr::UNSPECIFIED)), "127.0.0.1");
        assert_eq!(link_host(LOCAL), "127.0.0.1");
        assert_eq!(link_host("192.168.1.5".parse().unwrap()), "192.168.1.5");
        assert_eq!(link_host("::".parse().unwrap()), "[::1]");
    }

    #[test]
    fn cors_allows_only_the_servers_own_and_listed_origins() {
        let cors = Cors::new(LOCAL, 8080, &[]).unwrap();
        for own in [
            "http://127.0.0.1:8080",
            "http://localhost:8080",
            "http://LOCALHOST:8080",
            "http://[::1]:8080",
        ] {
            assert_eq!(cors.allow(Some(own)).as_deref(), Some(own));
        }
        for foreign in [
            "http://evil.example",
            "http://127.0.0.1:8081",
            "https://127.0.0.1:8080",
            "http://localhost:8080.evil.example",
            "null",
            "",
        ] {
            assert_eq!(cors.allow(Some(foreign)), None, "{foreign}");
        }
        assert_eq!(cors.allow(None), None);

        let cors = Cors::new(LOCAL, 8080, &["https://studio.example/".into()]).unwrap();
        assert_eq!(
            cors.allow(Some("https://studio.example")).as_deref(),
            Some("https://studio.example")
        );
        assert_eq!(cors.allow(Some("http://evil.example")), None);

        let cors = Cors::new(LOCAL, 8080, &["*".into()]).unwrap();
        assert_eq!(
            cors.allow(Some("http://evil.example")).as_deref(),
            Some("*")
        );
        assert_eq!(
            cors.allow(Some("http://localhost:8080")).as_deref(),
            Some("http://localhost:8080")
        );

        // A LAN bind: its own address only, not the loopback names of other local servers' pages.
        let lan: IpAddr = "192.168.1.5".parse().unwrap();
        // DNS rebinding: a loopback server refuses requests addressed to other names.
        let local = Cors::new(LOCAL, 8080, &[]).unwrap();
        assert!(local.host_ok(Some("127.0.0.1:8080")) && local.host_ok(Some("LOCALHOST:8080")));
        assert!(local.host_ok(Some("[::1]:8080")) && local.host_ok(None));
        assert!(!local.host_ok(Some("evil.example:8080")));
        assert!(!local.host_ok(Some("127.0.0.1:9999")));
        let cors = Cors::new(lan, 9000, &[]).unwrap();
        assert!(cors.host_ok(Some("192.168.1.5:9000")) && cors.host_ok(Some("anything:1")));
        assert!(cors.allow(Some("http://192.168.1.5:9000")).is_some());
        assert_eq!(cors.allow(Some("http://localhost:9000")), None);
        assert!(Cors::new(LOCAL, 8080, &["studio.example".into()]).is_err());
    }

    #[test]
    fn request_heads_parse_or_fail_with_a_status() {
        let r = parse_head(b"GET /x HTTP/1.1\r\nHost: a\r\nRange:  bytes=0-1 \r\n\r\n").unwrap();
        assert_eq!((r.method.as_str(), r.target.as_str()), ("GET", "/x"));
        assert_eq!(r.header("range"), Some("bytes=0-1"));
        assert_eq!(r.header("host"), Some("a"));
        assert!(parse_head(b"\r\nHEAD / HTTP/1.0\n\n").is_ok());
        for (head, status) in [
            (&b"\r\n\r\n"[..], 400),
            (b"GET\r\n\r\n", 400),
            (b"GET / HTTP/1.1 extra\r\n\r\n", 400),
            (b"GET /  HTTP/1.1\r\n\r\n", 400),
            (b"GET / FTP/1.1\r\n\r\n", 400),
            (b"GET / HTTP/2.0\r\n\r\n", 505),
            (b"GET / HTTP/1.1\r\nno colon\r\n\r\n", 400),
            (b"GET / HTTP/1.1\r\n: empty name\r\n\r\n", 400),
            (b"G\xffT / HTTP/1.1\r\n\r\n", 400),
        ] {
            assert_eq!(
                parse_head(head).map(|_| ()),
                Err(status),
                "{}",
                String::from_utf8_lossy(head)
            );
        }
        assert_eq!(head_end(b"GET / HTTP/1.1\r\n\r\nbody"), Some(18));
        assert_eq!(head_end(b"GET / HTTP/1.1\n\n"), Some(16));
        assert_eq!(head_end(b"GET / HTTP/1.1\r\n"), None);
    }

    #[test]
    fn mime_types() {
        for (name, mime_type) in [
            ("index.html", "text/html; charset=utf-8"),
            ("app.js", "text/javascript"),
            ("app_bg.WASM", "application/wasm"),
            ("style.css", "text/css"),
            ("report.json", "application/json"),
            ("view.png", "image/png"),
            ("points.ply", "application/octet-stream"),
            ("README", "application/octet-stream"),
        ] {
            assert_eq!(mime(Path::new(name)), mime_type, "{name}");
        }
    }

    #[test]
    fn shell_quoting() {
        assert_eq!(shell_quote("/a/b-c_1.x"), "/a/b-c_1.x");
        assert_eq!(shell_quote("/my dir/it's"), r"'/my dir/it'\''s'");
        assert_eq!(shell_quote(""), "''");
    }
}
