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
//! The request parser is `silvr::http` (a library module, so that it can be fuzzed).
//!
//! A lab runs this on shared machines and login nodes, so DIR is treated as holding anything:
//! - files under `/data/` are downloads (`Content-Disposition: attachment`, `Content-Security-Policy:
//!   sandbox`, never an HTML or script type): a page or script in DIR never runs on the studio's origin,
//!   where it could read the studio's saved checkpoints;
//! - dotfiles and dot-folders (`.git`, `.ssh`) are not served, and only regular files are opened (a FIFO
//!   or device is refused before `open`, which could block a connection thread forever);
//! - a loopback server answers only requests addressed to its loopback names (DNS rebinding); any other
//!   bind (a LAN address, `0.0.0.0`, `::`) answers every `Host` but hands `/data/` only to requests
//!   carrying its access token (`X-Silvr-Token`, 128 random bits unless `--token` gives one): the
//!   printed link carries it as `?token=`, and the studio sends it with its fetches of its own origin.
//!   A `--token` given on loopback is required there too. The studio's own files are public code and
//!   need none;
//! - CORS names origins: `*` and `null` (every sandboxed iframe) need `--allow-any-origin`.

use std::fs::File;
use std::io::{self, Read, Seek, SeekFrom, Write};
use std::net::{IpAddr, Shutdown, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use silvr::http::{head_end, parse_head, parse_range, request_path, ByteRange, Request};
// The link's encoding is the studio's own (one codec for the links serve prints and the page reads),
// and so are the token's query parameter and header.
use silvr_worker::view::{encode, TOKEN_HEADER, TOKEN_PARAM};

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
/// Random bytes of a generated access token (128 bits).
const TOKEN_BYTES: usize = 16;
/// Shortest token `--token` accepts (a guessable key is no key).
const MIN_TOKEN_CHARS: usize = 16;
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
    /// Address to listen on. Anything but loopback (a LAN address, 0.0.0.0, ::) makes DIR readable from
    /// the network to whoever has the printed link: it carries a random access token.
    #[arg(long, default_value = "127.0.0.1")]
    bind: IpAddr,
    /// Access token to require for /data/ (default: 128 random bits when --bind is not loopback, none on
    /// loopback). At least 16 characters of A-Z a-z 0-9 - . _ ~; anyone who has it can read DIR.
    #[arg(long, value_name = "TOKEN")]
    token: Option<String>,
    /// The built studio (default: $SILVR_STUDIO_DIST, else ./dist, else the dist/ of the workspace this
    /// binary was built in).
    #[arg(long)]
    studio: Option<PathBuf>,
    /// Also let pages of this origin (e.g. https://studio.example) read the files; repeatable. `*` (any
    /// website) and `null` (any sandboxed page) also need --allow-any-origin.
    #[arg(long = "allow-origin", value_name = "ORIGIN")]
    allow_origin: Vec<String>,
    /// Accept `--allow-origin '*'` and `--allow-origin null`: any website (or sandboxed page) the user
    /// visits may then read DIR off this server.
    #[arg(long)]
    allow_any_origin: bool,
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
    // Off loopback the folder is on the network: a key, unless the user gave one.
    let token = match cmd.token {
        Some(t) => Some(check_token(&t)?),
        None if !cmd.bind.is_loopback() => Some(random_token()?),
        None => None,
    };
    let listener = TcpListener::bind((cmd.bind, cmd.port)).with_context(|| {
        format!(
            "listening on {}:{} (another server on that port? --port 0 picks a free one)",
            cmd.bind, cmd.port
        )
    })?;
    let port = listener.local_addr()?.port();
    let cors = Cors::new(cmd.bind, port, &cmd.allow_origin, cmd.allow_any_origin)?;

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
    let tok = token.as_deref();
    writeln!(out, "open: {}", studio_link(&host, port, tok, &plys))?;
    for rel in &plys {
        writeln!(
            out,
            "  {}: {}",
            rel.display(),
            studio_link(&host, port, tok, std::slice::from_ref(rel))
        )?;
    }
    out.flush()?;
    drop(out);
    if plys.is_empty() {
        eprintln!(
            "note: no .ply or .copc.laz file within {PLY_SEARCH_DEPTH} levels of {}",
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
            "warning: listening on {}: anyone on the network who has the link can read everything under {}",
            cmd.bind,
            data.display()
        );
        if cmd.bind.is_unspecified() {
            eprintln!(
                "note: from another machine, put this machine's name or address in place of {host} \
                 (in the link and in its src= URLs)"
            );
        }
    }
    if token.is_some() {
        eprintln!(
            "note: the link is the key: its ?token= lets whoever has it read {} until this server stops; \
             the studio's share links leave it out (scripts: send the header {TOKEN_HEADER}: <token>)",
            data.display()
        );
    }
    if cmd.allow_any_origin {
        eprintln!(
            "warning: --allow-any-origin: any website (or sandboxed page) open in a browser that can reach \
             this server may read {}",
            data.display()
        );
    }

    let server = Arc::new(Server {
        studio: studio.root,
        data,
        cors,
        token,
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

/// `http://HOST:PORT/[?token=TOKEN]#src=<data URL>&src=...`: the studio reads its inputs from the
/// fragment, which the browser never sends to a server, and the token from the query, which its share
/// links leave out.
fn studio_link(host: &str, port: u16, token: Option<&str>, plys: &[PathBuf]) -> String {
    let srcs: Vec<String> = plys
        .iter()
        .map(|rel| format!("src={}", encode(&data_url(host, port, rel))))
        .collect();
    let query = token.map_or(String::new(), |t| format!("?{TOKEN_PARAM}={}", encode(t)));
    if srcs.is_empty() {
        format!("http://{host}:{port}/{query}")
    } else {
        format!("http://{host}:{port}/{query}#{}", srcs.join("&"))
    }
}

/// A fresh access token: [`TOKEN_BYTES`] from the operating system's generator, as hex.
fn random_token() -> Result<String> {
    let mut bytes = [0u8; TOKEN_BYTES];
    getrandom::fill(&mut bytes)
        .map_err(|e| anyhow::anyhow!("no random bytes from the OS for the access token: {e}"))?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
}

/// A `--token` as given, if it is long enough and goes into a URL and a header as it is.
fn check_token(token: &str) -> Result<String> {
    let plain = token
        .bytes()
        .all(|b| b.is_ascii_alphanumeric() || b"-._~".contains(&b));
    if !plain || token.len() < MIN_TOKEN_CHARS {
        bail!(
            "--token: expected at least {MIN_TOKEN_CHARS} characters of A-Z a-z 0-9 - . _ ~ \
             (leave it out for a random one)"
        );
    }
    Ok(token.to_string())
}

/// Equality that takes the same time wherever the first difference is (the token is a secret a client
/// could otherwise guess byte by byte from response times). Hand-rolled: eight lines, no crate for it
/// in the tree.
fn same_secret(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    let diff = a.iter().zip(b).fold(0u8, |d, (x, y)| d | (x ^ y));
    std::hint::black_box(diff) == 0
}

/// The URL of a file under DIR, each path segment percent-encoded.
fn data_url(host: &str, port: u16, rel: &Path) -> String {
    let segments: Vec<String> = rel
        .components()
        .map(|c| encode(&c.as_os_str().to_string_lossy()))
        .collect();
    format!("http://{host}:{port}/data/{}", segments.join("/"))
}

/// Whether the studio opens `name` as a map: a PLY, or a COPC file (read by byte ranges).
fn is_map(name: &str) -> bool {
    let lower = name.to_ascii_lowercase();
    lower.ends_with(".ply") || lower.ends_with(".copc.laz")
}

/// `.ply` and `.copc.laz` maps under `root` (at most [`PLY_SEARCH_DEPTH`] path components deep), relative
/// to it, sorted by path, the first [`MAX_LINKED_PLYS`]; an `X.ply` beside an `X.copc.laz` is left out (the
/// same map, which the studio streams from the COPC). Only files the server would serve: UTF-8 names,
/// inside the root.
fn find_plys(root: &Path) -> Vec<PathBuf> {
    fn walk(root: &Path, rel: &Path, depth: usize, found: &mut Vec<PathBuf>) {
        let Ok(entries) = std::fs::read_dir(root.join(rel)) else {
            return;
        };
        for entry in entries.flatten() {
            let name = entry.file_name();
            let Some(name) = name.to_str() else { continue };
            // The server does not serve dotfiles or dot-folders (`.git`, `.ssh`).
            if name.starts_with('.') {
                continue;
            }
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
            } else if is_map(name) {
                let inside = root
                    .join(&rel)
                    .canonicalize()
                    .is_ok_and(|p| p.strip_prefix(root).is_ok_and(|r| !hidden(r)) && p.is_file());
                if inside {
                    found.push(rel);
                }
            }
        }
    }
    let mut found = Vec::new();
    walk(root, Path::new(""), 1, &mut found);
    let copcs: std::collections::HashSet<PathBuf> = found
        .iter()
        .filter(|p| {
            p.to_string_lossy()
                .to_ascii_lowercase()
                .ends_with(".copc.laz")
        })
        .cloned()
        .collect();
    found.retain(|p| {
        let s = p.to_string_lossy();
        let Some(stem) = s.strip_suffix(".ply").or_else(|| s.strip_suffix(".PLY")) else {
            return true;
        };
        !copcs.contains(&PathBuf::from(format!("{stem}.copc.laz")))
    });
    // Shallow files first (a folder's own reconstructions before its sub-folders'), then by path.
    found.sort_by(|a, b| (a.components().count(), a).cmp(&(b.components().count(), b)));
    found.truncate(MAX_LINKED_PLYS);
    found
}

/// Which cross-origin pages may read the responses.
struct Cors {
    /// Allowed origins, as browsers write them (`scheme://host[:port]`): the server's own and the listed.
    origins: Vec<String>,
    /// The `--allow-origin` ones among them that name a website (not `null`): only these are granted
    /// Chrome's private-network access.
    listed: Vec<String>,
    /// `--allow-origin '*'` (with `--allow-any-origin`): any website.
    any: bool,
    /// `Host` values a loopback server answers (`None`: any).
    hosts: Option<Vec<String>>,
}

/// The CORS answer to one request's `Origin`.
#[derive(Debug, PartialEq, Eq)]
struct Allowed {
    /// `Access-Control-Allow-Origin`.
    origin: String,
    /// Whether a private-network preflight from it may be granted.
    private_network: bool,
}

impl Cors {
    /// The server's own origins (its bind address, and the loopback names when it listens on loopback),
    /// plus the `--allow-origin` ones. Never any website by default: a page elsewhere must not be able to
    /// read a user's files off a loopback server. `*` and `null` (the origin of every sandboxed iframe
    /// and `data:` page) only with `any_ok` (`--allow-any-origin`).
    fn new(bind: IpAddr, port: u16, extra: &[String], any_ok: bool) -> Result<Cors> {
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
        let mut listed = Vec::new();
        for o in extra {
            let o = o.trim().trim_end_matches('/');
            if (o == "*" || o.eq_ignore_ascii_case("null")) && !any_ok {
                bail!(
                    "--allow-origin {o} lets {} read the folder (and grants them Chrome's \
                     private-network access); add --allow-any-origin if that is what you want",
                    if o == "*" {
                        "every website the user visits"
                    } else {
                        "every sandboxed page (any website can make one)"
                    }
                );
            }
            if o == "*" {
                any = true;
            } else if o.eq_ignore_ascii_case("null") {
                origins.push("null".into());
            } else if o.contains("://") {
                origins.push(o.to_string());
                listed.push(o.to_string());
            } else {
                bail!("--allow-origin {o}: expected an origin like https://studio.example[:port]");
            }
        }
        // DNS rebinding: a website whose name is made to resolve to 127.0.0.1 would be same-origin with a
        // loopback server and read DIR without any CORS check. A loopback server answers only requests
        // addressed to its own names. Any other bind answers every name (LAN browsers use its address or
        // a host name; a wildcard one is reached by both): there the access token guards DIR.
        let hosts = bind.is_loopback().then(|| {
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
            listed,
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

    /// The CORS answer for a request with this `Origin` header, if that origin may read the answer.
    fn allow(&self, origin: Option<&str>) -> Option<Allowed> {
        if let Some(o) = origin {
            if self.origins.iter().any(|a| a.eq_ignore_ascii_case(o)) {
                return Some(Allowed {
                    origin: o.to_string(),
                    private_network: self.listed.iter().any(|a| a.eq_ignore_ascii_case(o)),
                });
            }
        }
        self.any.then(|| Allowed {
            origin: "*".into(),
            private_network: false,
        })
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
    /// The access token `/data/` requires (in the [`TOKEN_HEADER`] header), if any.
    token: Option<String>,
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
                if let Some(allowed) = &allow {
                    r.headers.extend([
                        ("Access-Control-Allow-Methods", "GET, HEAD, OPTIONS".into()),
                        (
                            "Access-Control-Allow-Headers",
                            format!("Range, {TOKEN_HEADER}"),
                        ),
                        ("Access-Control-Max-Age", "600".into()),
                    ]);
                    // Chrome's Private Network Access: a public page asking for a loopback or LAN
                    // server. Only for origins the user named, never for `*` or `null`.
                    if allowed.private_network
                        && req.header("access-control-request-private-network") == Some("true")
                    {
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
        if let Some(allowed) = allow {
            resp.headers.extend([
                ("Access-Control-Allow-Origin", allowed.origin),
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
        let (root, rel, data) = match segments.split_first() {
            Some((first, rest)) if first == "data" => (Some(self.data.as_path()), rest, true),
            _ => (self.studio.as_deref(), &segments[..], false),
        };
        // Before anything touches the file system: without the key, not even whether a file exists.
        if data {
            if let Err(refused) = self.check_token(req) {
                return refused;
            }
        }
        let Some(root) = root else {
            return Response::text(
                404,
                format!(
                    "The SiLVR studio is not built; the data is under /data/. Build it in the workspace \
                     with:\n  {BUILD_STUDIO}\nand restart silvr serve.\n"
                ),
            );
        };
        // Dotfiles and dot-folders (`.git`, `.ssh`): checked by name here, and on the canonical path
        // by `resolve` (a plain name may be a symlink into one).
        if rel.iter().any(|s| s.starts_with('.')) {
            return Response::error(404);
        }
        let path = match resolve(root, rel) {
            Ok(p) => p,
            Err(status) => return Response::error(status),
        };
        let (file, len) = match open_regular(&path) {
            Ok(f) => f,
            Err(status) => return Response::error(status),
        };
        let mut headers = if data {
            // Bytes to read, never a page: no HTML or script type, a download if navigated to, and a
            // sandbox (an opaque origin, no script) should a browser render it all the same.
            vec![
                ("Content-Type", data_mime(&path).into()),
                ("Content-Disposition", "attachment".into()),
                ("Content-Security-Policy", "sandbox".into()),
            ]
        } else {
            vec![("Content-Type", mime(&path).into())]
        };
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

    /// `Ok` when no token is required or the request carries the right one; else the 401 to answer
    /// (its own status: the studio words it as a missing or stale link, not as a refused file).
    fn check_token(&self, req: &Request) -> Result<(), Response> {
        let Some(token) = &self.token else {
            return Ok(());
        };
        let given = req.header(&TOKEN_HEADER.to_ascii_lowercase());
        if given.is_some_and(|g| same_secret(g.as_bytes(), token.as_bytes())) {
            return Ok(());
        }
        let mut r = Response::text(
            401,
            format!(
                "401 Unauthorized: {}; every file under /data/ needs this server's access token in the \
                 header {TOKEN_HEADER}. Open the whole link silvr serve printed (with its ?{TOKEN_PARAM}=) \
                 in the studio, or send the header yourself.\n",
                if given.is_some() {
                    "the access token does not match"
                } else {
                    "no access token was sent"
                }
            ),
        );
        // 401 names its scheme: here, the header.
        r.headers.push(("WWW-Authenticate", TOKEN_HEADER.into()));
        Err(r)
    }
}

/// Opens `path` if it is a regular file (with its length); FIFOs, sockets and devices are refused (403)
/// before `open`, which on a FIFO would wait for a writer forever. The file is opened non-blocking (a
/// file swapped for a FIFO between the check and the open must not block either) and checked again.
fn open_regular(path: &Path) -> Result<(File, u64), u16> {
    match std::fs::metadata(path) {
        Ok(m) if m.is_file() => {}
        Ok(_) => return Err(403),
        Err(e) => return Err(io_status(&e)),
    }
    let mut options = std::fs::OpenOptions::new();
    options.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        // Regular files ignore O_NONBLOCK: reads and sendfile behave as usual.
        options.custom_flags(libc::O_NONBLOCK);
    }
    let file = options.open(path).map_err(|e| io_status(&e))?;
    match file.metadata() {
        Ok(m) if m.is_file() => Ok((file, m.len())),
        Ok(_) => Err(403),
        Err(e) => Err(io_status(&e)),
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

/// The canonical file `segments` names under `root` (a folder's `index.html`), refused (403) when it
/// leaves the root, e.g. through a symlink, and not found (404) when it lies in or is a dotfile or
/// dot-folder of the root (a symlink to `.git/config` included).
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
    let Ok(inside) = path.strip_prefix(root) else {
        return Err(403);
    };
    if hidden(inside) {
        return Err(404);
    }
    Ok(path)
}

/// Whether a path relative to a root is, or lies in, a dotfile or dot-folder (never served).
fn hidden(rel: &Path) -> bool {
    rel.components()
        .any(|c| c.as_os_str().as_encoded_bytes().starts_with(b"."))
}

fn io_status(e: &io::Error) -> u16 {
    match e.kind() {
        io::ErrorKind::PermissionDenied => 403,
        _ => 404,
    }
}

/// Content types of the studio's files by extension. `.wasm` must be `application/wasm` for streaming
/// compilation; PLY and unknown files are opaque bytes (with `nosniff`, a browser never renders them as a
/// page).
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

/// Content types of files under `/data/`: only types a browser never runs script from (PNG, JPEG, JSON)
/// keep theirs; everything else (HTML, SVG, JS, PLY, ...) is opaque bytes.
fn data_mime(path: &Path) -> &'static str {
    match mime(path) {
        t @ ("image/png" | "image/jpeg" | "application/json") => t,
        _ => "application/octet-stream",
    }
}

fn reason(status: u16) -> &'static str {
    match status {
        200 => "OK",
        204 => "No Content",
        206 => "Partial Content",
        400 => "Bad Request",
        401 => "Unauthorized",
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
    use silvr_worker::view::decode_bytes;
    use std::net::Ipv4Addr;

    const LOCAL: IpAddr = IpAddr::V4(Ipv4Addr::LOCALHOST);

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

    /// The link opens PLY and COPC maps; a COPC beside its PLY (same name) stands for it.
    #[test]
    fn the_link_prefers_a_copc_to_its_ply() {
        let dir = std::env::temp_dir().join(format!("silvr-serve-maps-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        for f in [
            "a/points.ply",
            "a/points.copc.laz",
            "a/other.ply",
            "a/merged.laz",
            "b/map.COPC.LAZ",
        ] {
            let p = dir.join(f);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(p, b"x").unwrap();
        }
        let root = dir.canonicalize().unwrap();
        let found = find_plys(&root);
        let _ = std::fs::remove_dir_all(&dir);
        assert_eq!(
            found,
            ["a/other.ply", "a/points.copc.laz", "b/map.COPC.LAZ"].map(PathBuf::from)
        );
    }

    #[test]
    fn the_link_holds_the_encoded_data_urls() {
        let one = [PathBuf::from("silvr/points.ply")];
        assert_eq!(
            studio_link("127.0.0.1", 8080, None, &one),
            "http://127.0.0.1:8080/#src=http%3A%2F%2F127.0.0.1%3A8080%2Fdata%2Fsilvr%2Fpoints.ply"
        );
        let two = [PathBuf::from("a.ply"), PathBuf::from("my dir/b.ply")];
        assert_eq!(
            studio_link("127.0.0.1", 1, None, &two),
            "http://127.0.0.1:1/#src=http%3A%2F%2F127.0.0.1%3A1%2Fdata%2Fa.ply\
             &src=http%3A%2F%2F127.0.0.1%3A1%2Fdata%2Fmy%2520dir%2Fb.ply"
        );
        assert_eq!(
            studio_link("127.0.0.1", 1, None, &[]),
            "http://127.0.0.1:1/"
        );
        assert_eq!(link_host(IpAddr::V4(Ipv4Addr::UNSPECIFIED)), "127.0.0.1");
        assert_eq!(link_host(LOCAL), "127.0.0.1");
        assert_eq!(link_host("192.168.1.5".parse().unwrap()), "192.168.1.5");
        assert_eq!(link_host("::".parse().unwrap()), "[::1]");
    }

    #[test]
    fn the_token_is_in_the_links_query_never_its_hash() {
        let one = [PathBuf::from("a.ply")];
        assert_eq!(
            studio_link("10.0.0.2", 8080, Some("k3y-0123456789abcdef"), &one),
            "http://10.0.0.2:8080/?token=k3y-0123456789abcdef#src=http%3A%2F%2F10.0.0.2%3A8080%2Fdata%2Fa.ply"
        );
        assert_eq!(
            studio_link("10.0.0.2", 8080, Some("k3y-0123456789abcdef"), &[]),
            "http://10.0.0.2:8080/?token=k3y-0123456789abcdef"
        );
    }

    #[test]
    fn tokens_are_random_and_plain() {
        let (a, b) = (random_token().unwrap(), random_token().unwrap());
        assert_eq!(a.len(), 2 * TOKEN_BYTES, "{a}");
        assert!(a.bytes().all(|c| c.is_ascii_hexdigit()), "{a}");
        assert_ne!(a, b);
        assert_eq!(check_token(&a).unwrap(), a);
        assert!(check_token("Abc-._~0123456789").is_ok());
        for bad in [
            "",
            "short",
            "0123456789abcde",
            "0123456789abcdef&x",
            "0123456789 abcdef",
        ] {
            assert!(check_token(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn secrets_compare_whole() {
        assert!(same_secret(b"0123456789abcdef", b"0123456789abcdef"));
        assert!(!same_secret(b"0123456789abcdef", b"0123456789abcdeF"));
        assert!(!same_secret(b"0123456789abcdef", b"1123456789abcdef"));
        assert!(!same_secret(b"0123456789abcdef", b"0123456789abcde"));
        assert!(!same_secret(b"0123456789abcdef", b""));
    }

    /// The `Access-Control-Allow-Origin` a request from `origin` gets.
    fn acao(cors: &Cors, origin: &str) -> Option<String> {
        cors.allow(Some(origin)).map(|a| a.origin)
    }

    #[test]
    fn cors_allows_only_the_servers_own_and_listed_origins() {
        let cors = Cors::new(LOCAL, 8080, &[], false).unwrap();
        for own in [
            "http://127.0.0.1:8080",
            "http://localhost:8080",
            "http://LOCALHOST:8080",
            "http://[::1]:8080",
        ] {
            assert_eq!(acao(&cors, own).as_deref(), Some(own));
            assert!(!cors.allow(Some(own)).unwrap().private_network);
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

        let cors = Cors::new(LOCAL, 8080, &["https://studio.example/".into()], false).unwrap();
        assert_eq!(
            cors.allow(Some("https://studio.example")),
            Some(Allowed {
                origin: "https://studio.example".into(),
                private_network: true
            })
        );
        assert_eq!(cors.allow(Some("http://evil.example")), None);
        assert!(Cors::new(LOCAL, 8080, &["studio.example".into()], false).is_err());
    }

    #[test]
    fn any_origin_and_null_need_the_flag_and_never_get_private_network_access() {
        for o in ["*", "null", "NULL", " * "] {
            let e = Cors::new(LOCAL, 8080, &[o.into()], false).err().unwrap();
            assert!(e.to_string().contains("--allow-any-origin"), "{o}: {e}");
        }
        let cors = Cors::new(LOCAL, 8080, &["*".into()], true).unwrap();
        assert_eq!(
            cors.allow(Some("http://evil.example")),
            Some(Allowed {
                origin: "*".into(),
                private_network: false
            })
        );
        assert_eq!(
            acao(&cors, "http://localhost:8080").as_deref(),
            Some("http://localhost:8080")
        );
        let cors = Cors::new(LOCAL, 8080, &["null".into()], true).unwrap();
        assert_eq!(
            cors.allow(Some("null")),
            Some(Allowed {
                origin: "null".into(),
                private_network: false
            })
        );
        assert_eq!(cors.allow(Some("http://evil.example")), None);
    }

    #[test]
    fn the_host_check_follows_the_bind() {
        // DNS rebinding: a loopback server refuses requests addressed to other names.
        let local = Cors::new(LOCAL, 8080, &[], false).unwrap();
        assert!(local.host_ok(Some("127.0.0.1:8080")) && local.host_ok(Some("LOCALHOST:8080")));
        assert!(local.host_ok(Some("[::1]:8080")) && local.host_ok(None));
        assert!(!local.host_ok(Some("evil.example:8080")));
        assert!(!local.host_ok(Some("127.0.0.1:9999")));
        // A LAN bind answers any name (the token guards the data), and lets in its own address's pages,
        // not the loopback names of other local servers' pages.
        let lan: IpAddr = "192.168.1.5".parse().unwrap();
        let cors = Cors::new(lan, 9000, &[], false).unwrap();
        assert!(cors.host_ok(Some("192.168.1.5:9000")) && cors.host_ok(Some("anything:1")));
        assert!(cors.allow(Some("http://192.168.1.5:9000")).is_some());
        assert_eq!(cors.allow(Some("http://localhost:9000")), None);
        // A wildcard bind is reached by LAN names too.
        let any = Cors::new(IpAddr::V4(Ipv4Addr::UNSPECIFIED), 9000, &[], false).unwrap();
        assert!(any.host_ok(Some("192.168.1.5:9000")) && any.host_ok(Some("lab-node-3:9000")));
    }

    #[test]
    fn mime_types() {
        for (name, mime_type, data) in [
            (
                "index.html",
                "text/html; charset=utf-8",
                "application/octet-stream",
            ),
            (
                "x.HTM",
                "text/html; charset=utf-8",
                "application/octet-stream",
            ),
            ("app.js", "text/javascript", "application/octet-stream"),
            ("app.mjs", "text/javascript", "application/octet-stream"),
            (
                "app_bg.WASM",
                "application/wasm",
                "application/octet-stream",
            ),
            ("style.css", "text/css", "application/octet-stream"),
            ("report.json", "application/json", "application/json"),
            ("view.png", "image/png", "image/png"),
            ("view.jpeg", "image/jpeg", "image/jpeg"),
            (
                "points.ply",
                "application/octet-stream",
                "application/octet-stream",
            ),
            (
                "README",
                "application/octet-stream",
                "application/octet-stream",
            ),
        ] {
            assert_eq!(mime(Path::new(name)), mime_type, "{name}");
            assert_eq!(data_mime(Path::new(name)), data, "{name} under /data/");
        }
    }

    #[test]
    fn shell_quoting() {
        assert_eq!(shell_quote("/a/b-c_1.x"), "/a/b-c_1.x");
        assert_eq!(shell_quote("/my dir/it's"), r"'/my dir/it'\''s'");
        assert_eq!(shell_quote(""), "''");
    }
}
