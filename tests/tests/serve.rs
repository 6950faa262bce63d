//! `silvr serve` end to end: the real binary on a free port, spoken to in raw HTTP/1.1, so that what is
//! checked is exactly what goes over the wire (status lines, headers, bytes).

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{self, Receiver};
use std::time::Duration;

use silvr_tests::build_silvr;

/// A running `silvr serve`, killed when dropped (also when a test panics).
struct Server {
    child: Child,
    port: u16,
    /// `serving the studio from ... at http://127.0.0.1:PORT/`.
    first_line: String,
    stdout: Receiver<String>,
    stderr: Receiver<String>,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Server {
    /// Starts `silvr serve DATA --port 0 ARGS...` and reads the port from its first line.
    fn start(data: &Path, args: &[&str]) -> Server {
        let mut child = Command::new(build_silvr())
            .arg("serve")
            .arg(data)
            .args(["--port", "0"])
            .args(args)
            .env_remove("SILVR_STUDIO_DIST")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        // Lines through channels: a test never blocks on a server that printed less than expected.
        let stdout = lines(child.stdout.take().unwrap());
        let stderr = lines(child.stderr.take().unwrap());
        let mut server = Server {
            child,
            port: 0,
            first_line: String::new(),
            stdout,
            stderr,
        };
        let first = server.line();
        // `... at http://HOST:PORT/` (HOST: the bind address).
        let port = first
            .rsplit_once(" at http://")
            .and_then(|(_, url)| url.strip_suffix('/'))
            .and_then(|hp| hp.rsplit_once(':'))
            .and_then(|(_, p)| p.parse().ok());
        server.port = port.unwrap_or_else(|| panic!("no port in the first line: {first:?}"));
        assert!(first.starts_with("serving the studio from "), "{first}");
        server.first_line = first;
        server
    }

    /// Waits for a stderr line containing `needle` (at most 20 lines, 10 s each).
    fn stderr_has(&self, needle: &str) -> bool {
        for _ in 0..20 {
            match self.stderr.recv_timeout(Duration::from_secs(10)) {
                Ok(l) if l.contains(needle) => return true,
                Ok(_) => {}
                Err(_) => return false,
            }
        }
        false
    }

    /// The next stdout line (the test fails after 30 s without one).
    fn line(&self) -> String {
        self.stdout
            .recv_timeout(Duration::from_secs(30))
            .unwrap_or_else(|_| panic!("silvr serve printed no further line"))
    }

    fn get(&self, path: &str) -> Reply {
        self.send(&format!("GET {path} HTTP/1.1\r\nHost: x\r\n\r\n"))
    }

    fn get_with(&self, path: &str, header: &str) -> Reply {
        self.send(&format!(
            "GET {path} HTTP/1.1\r\nHost: x\r\n{header}\r\n\r\n"
        ))
    }

    /// Sends `request`, its `Host: x` addressed to this server (a loopback server refuses other names).
    fn send(&self, request: &str) -> Reply {
        let request = request.replace("Host: x\r\n", &format!("Host: 127.0.0.1:{}\r\n", self.port));
        send_bytes(self.port, request.as_bytes())
    }
}

fn lines(stream: impl Read + Send + 'static) -> Receiver<String> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stream).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    rx
}

/// One response: status, headers (names lower-cased) and body.
struct Reply {
    status: u16,
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Reply {
    fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_str())
    }
}

/// Writes a raw request and reads the response up to the server's close.
fn send_bytes(port: u16, request: &[u8]) -> Reply {
    let mut conn = TcpStream::connect(("127.0.0.1", port)).unwrap();
    conn.set_read_timeout(Some(Duration::from_secs(20)))
        .unwrap();
    conn.write_all(request).unwrap();
    let mut raw = Vec::new();
    conn.read_to_end(&mut raw).unwrap();
    parse_reply(&raw)
}

fn parse_reply(raw: &[u8]) -> Reply {
    let end = raw
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .unwrap_or_else(|| panic!("no response head in {:?}", String::from_utf8_lossy(raw)));
    let head = std::str::from_utf8(&raw[..end]).unwrap();
    let mut lines = head.split("\r\n");
    let status_line = lines.next().unwrap();
    assert!(status_line.starts_with("HTTP/1.1 "), "{status_line}");
    let status = status_line[9..12].parse().unwrap();
    let headers = lines
        .map(|l| {
            let (n, v) = l.split_once(':').unwrap();
            (n.to_ascii_lowercase(), v.trim().to_string())
        })
        .collect();
    Reply {
        status,
        headers,
        body: raw[end + 4..].to_vec(),
    }
}

/// A studio build, and a data folder with a nested PLY, next to a secret it must never hand out.
struct Fixture {
    _tmp: tempfile::TempDir,
    studio: std::path::PathBuf,
    data: std::path::PathBuf,
    ply: Vec<u8>,
}

const INDEX: &str = "<!doctype html><title>SiLVR Studio</title>";
const SECRET: &[u8] = b"TOP SECRET: outside the served folder";

fn fixture() -> Fixture {
    let tmp = tempfile::tempdir().unwrap();
    let studio = tmp.path().join("dist");
    let data = tmp.path().join("data");
    std::fs::create_dir_all(&studio).unwrap();
    std::fs::create_dir_all(data.join("sub")).unwrap();
    std::fs::write(studio.join("index.html"), INDEX).unwrap();
    std::fs::write(studio.join("app_bg.wasm"), b"\0asm\x01\0\0\0").unwrap();
    let ply: Vec<u8> = (0..100u32).map(|i| (i * 7 + 3) as u8).collect();
    std::fs::write(data.join("sub").join("x.ply"), &ply).unwrap();
    std::fs::write(tmp.path().join("secret"), SECRET).unwrap();
    #[cfg(unix)]
    std::os::unix::fs::symlink(tmp.path().join("secret"), data.join("escape.ply")).unwrap();
    Fixture {
        studio,
        data,
        ply,
        _tmp: tmp,
    }
}

#[test]
fn serve_hands_out_the_studio_and_the_data_and_nothing_else() {
    let f = fixture();
    let studio = f.studio.to_str().unwrap();
    let mut server = Server::start(
        &f.data,
        &[
            "--studio",
            studio,
            "--allow-origin",
            "http://studio.example",
        ],
    );
    let port = server.port;
    let len = f.ply.len();

    // The printed link opens the nested PLY (and not the symlink out of the folder).
    let data = f.data.canonicalize().unwrap();
    assert!(
        server.first_line.contains(&data.display().to_string()),
        "{}",
        server.first_line
    );
    let encoded = format!("http%3A%2F%2F127.0.0.1%3A{port}%2Fdata%2Fsub%2Fx.ply");
    let open = server.line();
    assert_eq!(
        open,
        format!("open: http://127.0.0.1:{port}/#src={encoded}")
    );
    let per_file = server.line();
    assert_eq!(
        per_file,
        format!("  sub/x.ply: http://127.0.0.1:{port}/#src={encoded}")
    );

    // The studio: index.html for `/`, wasm with the type streaming compilation needs.
    let r = server.get("/");
    assert_eq!(r.status, 200);
    assert_eq!(r.header("content-type"), Some("text/html; charset=utf-8"));
    assert_eq!(r.body, INDEX.as_bytes());
    let r = server.get("/app_bg.wasm");
    assert_eq!(r.status, 200);
    assert_eq!(r.header("content-type"), Some("application/wasm"));
    assert_eq!(server.get("/missing.js").status, 404);

    // The data, whole and in ranges.
    let r = server.get("/data/sub/x.ply");
    assert_eq!(r.status, 200);
    assert_eq!(r.body, f.ply);
    assert_eq!(r.header("content-length"), Some(len.to_string().as_str()));
    assert_eq!(r.header("content-type"), Some("application/octet-stream"));
    assert_eq!(r.header("accept-ranges"), Some("bytes"));
    assert_eq!(r.header("cache-control"), Some("no-cache"));
    let r = server.get_with("/data/sub/x.ply", "Range: bytes=10-19");
    assert_eq!(r.status, 206);
    assert_eq!(r.body, &f.ply[10..20]);
    assert_eq!(r.header("content-length"), Some("10"));
    assert_eq!(
        r.header("content-range"),
        Some(format!("bytes 10-19/{len}").as_str())
    );
    let r = server.get_with("/data/sub/x.ply", "Range: bytes=-5");
    assert_eq!(r.status, 206);
    assert_eq!(r.body, &f.ply[len - 5..]);
    assert_eq!(
        r.header("content-range"),
        Some(format!("bytes {}-{}/{len}", len - 5, len - 1).as_str())
    );
    let r = server.get_with("/data/sub/x.ply", "Range: bytes=90-");
    assert_eq!((r.status, r.body.as_slice()), (206, &f.ply[90..]));
    let r = server.get_with("/data/sub/x.ply", &format!("Range: bytes={len}-"));
    assert_eq!(r.status, 416);
    assert_eq!(
        r.header("content-range"),
        Some(format!("bytes */{len}").as_str())
    );
    let r = server.get_with("/data/sub/x.ply", "Range: bytes=0-1,5-6");
    assert_eq!((r.status, &r.body), (200, &f.ply), "several ranges: whole");

    // HEAD: the length, no body.
    let r = server.send("HEAD /data/sub/x.ply HTTP/1.1\r\nHost: x\r\n\r\n");
    assert_eq!(r.status, 200);
    assert_eq!(r.header("content-length"), Some(len.to_string().as_str()));
    assert!(r.body.is_empty());

    // Nothing outside the folder, however it is spelled.
    for path in [
        "/data/../secret",
        "/data/%2e%2e/secret",
        "/data/sub/%2E%2E/%2e%2e/secret",
        "/data/..%2fsecret",
        "/data/..%5csecret",
        "/data/%2fetc%2fpasswd",
        "/../secret",
        "/data/escape.ply",
    ] {
        let r = server.get(path);
        assert!(matches!(r.status, 400 | 403 | 404), "{path}: {}", r.status);
        assert!(
            !r.body.windows(SECRET.len()).any(|w| w == SECRET),
            "{path} leaked the secret"
        );
    }
    #[cfg(unix)]
    assert_eq!(server.get("/data/escape.ply").status, 403, "symlink out");
    assert_eq!(server.get("/data/x%00.ply").status, 400);

    // Other methods.
    let r = server.send("POST /data/sub/x.ply HTTP/1.1\r\nHost: x\r\nContent-Length: 0\r\n\r\n");
    assert_eq!(r.status, 405);
    assert_eq!(r.header("allow"), Some("GET, HEAD, OPTIONS"));

    // CORS: the server's own origins and the listed one, never a foreign website.
    for origin in [
        format!("http://127.0.0.1:{port}"),
        format!("http://localhost:{port}"),
        "http://studio.example".to_string(),
    ] {
        let r = server.get_with("/data/sub/x.ply", &format!("Origin: {origin}"));
        assert_eq!(r.status, 200);
        assert_eq!(
            r.header("access-control-allow-origin"),
            Some(origin.as_str())
        );
        assert_eq!(r.header("vary"), Some("Origin"));
        assert_eq!(
            r.header("access-control-expose-headers"),
            Some("Content-Length, Content-Range, Accept-Ranges")
        );
    }
    // DNS rebinding: a request addressed to another name is refused, whatever its origin.
    let r = send_bytes(
        server.port,
        format!(
            "GET /data/sub/x.ply HTTP/1.1\r\nHost: evil.example:{}\r\n\r\n",
            server.port
        )
        .as_bytes(),
    );
    assert_eq!(r.status, 421);
    let r = server.get_with("/data/sub/x.ply", "Origin: http://evil.example");
    assert_eq!(r.header("access-control-allow-origin"), None);
    let preflight = |origin: &str| {
        server.send(&format!(
            "OPTIONS /data/sub/x.ply HTTP/1.1\r\nHost: x\r\nOrigin: {origin}\r\n\
             Access-Control-Request-Method: GET\r\nAccess-Control-Request-Headers: range\r\n\r\n"
        ))
    };
    let r = preflight("http://studio.example");
    assert_eq!(r.status, 204);
    assert_eq!(
        r.header("access-control-allow-origin"),
        Some("http://studio.example")
    );
    assert_eq!(
        r.header("access-control-allow-methods"),
        Some("GET, HEAD, OPTIONS")
    );
    assert_eq!(
        r.header("access-control-allow-headers"),
        Some("Range, X-Silvr-Token")
    );
    let r = preflight("http://evil.example");
    assert_eq!(r.header("access-control-allow-origin"), None);
    assert_eq!(r.header("access-control-allow-methods"), None);

    // Malformed and oversized requests get an answer, and the server lives on.
    assert_eq!(server.send("garbage\r\n\r\n").status, 400);
    assert_eq!(
        server.send("GET / HTTP/1.1\r\nno colon\r\n\r\n").status,
        400
    );
    let huge = format!(
        "GET / HTTP/1.1\r\nHost: x\r\nX-Big: {}\r\n\r\n",
        "a".repeat(20_000)
    );
    assert_eq!(server.send(&huge).status, 431);
    assert_eq!(server.get("/").status, 200);

    // More than 64 connections at once: the next one is told to come back, then all is well again.
    let idle: Vec<TcpStream> = (0..64)
        .map(|_| TcpStream::connect(("127.0.0.1", port)).unwrap())
        .collect();
    assert_eq!(server.get("/").status, 503);
    drop(idle);
    let mut status = 0;
    for _ in 0..50 {
        status = server.get("/").status;
        if status == 200 {
            break;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    assert_eq!(status, 200, "connections are freed");

    // Still running: nothing above crashed it.
    assert!(server.child.try_wait().unwrap().is_none());
    assert!(
        server.stderr.try_iter().all(|l| !l.contains("panicked")),
        "a request panicked a thread"
    );
}

#[test]
fn without_a_built_studio_the_data_is_still_served_and_the_build_is_explained() {
    let f = fixture();
    let empty = f.studio.parent().unwrap().join("empty-dist");
    std::fs::create_dir_all(&empty).unwrap();
    let server = Server::start(&f.data, &["--studio", empty.to_str().unwrap()]);
    assert!(
        server.first_line.contains("(not built)"),
        "{}",
        server.first_line
    );
    assert!(server.line().starts_with("open: "));
    let mut warned = false;
    for _ in 0..20 {
        match server.stderr.recv_timeout(Duration::from_secs(10)) {
            Ok(l) if l.contains("trunk build --release") => {
                warned = true;
                break;
            }
            Ok(_) => {}
            Err(_) => break,
        }
    }
    assert!(warned, "no build instructions on stderr");
    assert_eq!(server.get("/").status, 404);
    let r = server.get("/data/sub/x.ply");
    assert_eq!((r.status, &r.body), (200, &f.ply));
}

#[test]
fn serving_a_missing_folder_is_a_clear_error() {
    let tmp = tempfile::tempdir().unwrap();
    let missing = tmp.path().join("no-such-run");
    let out = Command::new(build_silvr())
        .arg("serve")
        .arg(&missing)
        .args(["--port", "0"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no-such-run"), "{err}");
    assert!(!err.contains("panicked"), "{err}");

    let file = tmp.path().join("a-file");
    std::fs::write(&file, b"x").unwrap();
    let out = Command::new(build_silvr())
        .arg("serve")
        .arg(&file)
        .args(["--port", "0"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("a-file") && err.contains("not a folder"),
        "{err}"
    );
}

/// Runs `silvr serve DATA --port 0 ARGS...`, which must exit with status 1 within 30 s (a command that
/// should have been refused would serve forever: it is killed and the test fails).
fn refused(data: &Path, args: &[&str]) -> std::process::Output {
    let mut child = Command::new(build_silvr())
        .arg("serve")
        .arg(data)
        .args(["--port", "0"])
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    while child.try_wait().unwrap().is_none() {
        if std::time::Instant::now() > deadline {
            let _ = child.kill();
            let out = child.wait_with_output().unwrap();
            panic!(
                "silvr serve {args:?} was accepted (still serving after 30 s): {}",
                String::from_utf8_lossy(&out.stdout)
            );
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let out = child.wait_with_output().unwrap();
    assert_eq!(out.status.code(), Some(1), "{args:?}");
    out
}

/// Whether `haystack` contains `needle` anywhere.
fn contains(haystack: &[u8], needle: &[u8]) -> bool {
    haystack.windows(needle.len()).any(|w| w == needle)
}

#[test]
fn files_under_data_are_inert_downloads_never_pages_or_scripts() {
    let f = fixture();
    let page = b"<!doctype html><script>window.__pwned = localStorage</script>";
    std::fs::write(f.data.join("page.html"), page).unwrap();
    std::fs::write(f.data.join("evil.js"), b"self.__pwned = 1").unwrap();
    std::fs::write(f.data.join("evil.mjs"), b"self.__pwned = 1").unwrap();
    std::fs::write(f.data.join("image.svg"), b"<svg onload=\"alert(1)\"/>").unwrap();
    std::fs::write(f.data.join("report.json"), b"{\"ok\":true}").unwrap();
    std::fs::write(f.data.join("view.png"), b"\x89PNG\r\n\x1a\n").unwrap();
    std::fs::create_dir_all(f.data.join("site")).unwrap();
    std::fs::write(f.data.join("site").join("index.html"), page).unwrap();
    let server = Server::start(&f.data, &["--studio", f.studio.to_str().unwrap()]);

    for (path, content_type) in [
        ("/data/page.html", "application/octet-stream"),
        ("/data/site/", "application/octet-stream"),
        ("/data/evil.js", "application/octet-stream"),
        ("/data/evil.mjs", "application/octet-stream"),
        ("/data/image.svg", "application/octet-stream"),
        ("/data/sub/x.ply", "application/octet-stream"),
        // Types the studio or a person may read as data keep theirs: no browser runs script from them.
        ("/data/report.json", "application/json"),
        ("/data/view.png", "image/png"),
    ] {
        let r = server.get(path);
        assert_eq!(r.status, 200, "{path}");
        assert_eq!(r.header("content-type"), Some(content_type), "{path}");
        assert_eq!(
            r.header("content-disposition"),
            Some("attachment"),
            "{path}"
        );
        assert_eq!(
            r.header("content-security-policy"),
            Some("sandbox"),
            "{path}"
        );
        assert_eq!(
            r.header("x-content-type-options"),
            Some("nosniff"),
            "{path}"
        );
    }
    // The bytes themselves are untouched (the studio reads PLYs from here, ranges included).
    assert_eq!(server.get("/data/page.html").body, page);
    let r = server.get_with("/data/sub/x.ply", "Range: bytes=10-19");
    assert_eq!((r.status, r.body.as_slice()), (206, &f.ply[10..20]));
    assert_eq!(r.header("content-disposition"), Some("attachment"));
    // The studio's own page is still a page.
    let r = server.get("/");
    assert_eq!(r.header("content-type"), Some("text/html; charset=utf-8"));
    assert_eq!(r.header("content-disposition"), None);
    assert_eq!(r.header("content-security-policy"), None);
}

#[test]
fn any_origin_and_null_are_refused_without_allow_any_origin() {
    let f = fixture();
    for origin in ["*", "null"] {
        let out = refused(&f.data, &["--allow-origin", origin]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains("--allow-any-origin"), "{err}");
        assert!(!err.contains("panicked"), "{err}");
    }

    // With the flag: a warning, and `null` may read, but is never granted private-network access; an
    // origin the user named is.
    let server = Server::start(
        &f.data,
        &[
            "--allow-origin",
            "null",
            "--allow-any-origin",
            "--allow-origin",
            "http://studio.example",
        ],
    );
    assert!(server.stderr_has("warning: --allow-any-origin"));
    let r = server.get_with("/data/sub/x.ply", "Origin: null");
    assert_eq!(r.status, 200);
    assert_eq!(r.header("access-control-allow-origin"), Some("null"));
    let preflight = |origin: &str| {
        server.send(&format!(
            "OPTIONS /data/sub/x.ply HTTP/1.1\r\nHost: x\r\nOrigin: {origin}\r\n\
             Access-Control-Request-Method: GET\r\nAccess-Control-Request-Private-Network: true\r\n\r\n"
        ))
    };
    let r = preflight("null");
    assert_eq!(r.header("access-control-allow-origin"), Some("null"));
    assert_eq!(r.header("access-control-allow-private-network"), None);
    let r = preflight("http://studio.example");
    assert_eq!(
        r.header("access-control-allow-origin"),
        Some("http://studio.example")
    );
    assert_eq!(
        r.header("access-control-allow-private-network"),
        Some("true")
    );
    assert_eq!(
        r.header("access-control-allow-headers"),
        Some("Range, X-Silvr-Token")
    );

    let server = Server::start(&f.data, &["--allow-origin", "*", "--allow-any-origin"]);
    let r = server.get_with("/data/sub/x.ply", "Origin: http://evil.example");
    assert_eq!(r.header("access-control-allow-origin"), Some("*"));
    let r = server.send(
        "OPTIONS /data/sub/x.ply HTTP/1.1\r\nHost: x\r\nOrigin: http://evil.example\r\n\
         Access-Control-Request-Method: GET\r\nAccess-Control-Request-Private-Network: true\r\n\r\n",
    );
    assert_eq!(r.header("access-control-allow-origin"), Some("*"));
    assert_eq!(r.header("access-control-allow-private-network"), None);
}

#[test]
fn dotfiles_and_dot_folders_are_not_served() {
    let f = fixture();
    const KEY: &[u8] = b"-----BEGIN OPENSSH PRIVATE KEY-----";
    for rel in [
        ".git/config",
        ".ssh/id_ed25519",
        ".env",
        "sub/.hidden.ply",
        "sub/.x/y.ply",
    ] {
        let path = f.data.join(rel);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, KEY).unwrap();
    }
    std::fs::write(f.studio.join(".env"), KEY).unwrap();
    // A plain name that leads into a dot-folder is refused as well.
    #[cfg(unix)]
    std::os::unix::fs::symlink(f.data.join(".ssh/id_ed25519"), f.data.join("key.ply")).unwrap();
    let server = Server::start(&f.data, &["--studio", f.studio.to_str().unwrap()]);
    for _ in 0..2 {
        let line = server.line();
        assert!(!line.contains(".hidden") && !line.contains(".x"), "{line}");
    }
    let mut paths = vec![
        "/data/.git/config",
        "/data/.ssh/id_ed25519",
        "/data/.env",
        "/data/sub/.hidden.ply",
        "/data/sub/.x/y.ply",
        "/data/%2egit/config",
        "/data/%2Essh/id_ed25519",
        "/data/sub/./.hidden.ply",
        "/.env",
    ];
    if cfg!(unix) {
        paths.push("/data/key.ply");
    }
    for path in paths {
        let r = server.get(path);
        assert_eq!(r.status, 404, "{path}");
        assert!(!contains(&r.body, KEY), "{path} leaked the key");
    }
    assert_eq!(server.get("/data/sub/x.ply").status, 200);
}

#[cfg(unix)]
#[test]
fn fifos_are_refused_without_blocking_a_connection() {
    let f = fixture();
    for name in ["pipe.ply", "pipe"] {
        let status = Command::new("mkfifo")
            .arg(f.data.join(name))
            .status()
            .unwrap();
        assert!(status.success(), "mkfifo");
    }
    let server = Server::start(&f.data, &[]);
    for path in ["/data/pipe.ply", "/data/pipe"] {
        let t = std::time::Instant::now();
        // Opening a FIFO waits for a writer: a server that opens it never answers (the read times out).
        let r = server.get(path);
        assert_eq!(r.status, 403, "{path}");
        assert!(
            t.elapsed() < Duration::from_secs(5),
            "{path}: {:?}",
            t.elapsed()
        );
    }
    assert_eq!(server.get("/data/sub/x.ply").status, 200);
}

/// The token in a printed link (`http://HOST:PORT/?token=TOKEN#...`).
fn link_token(line: &str) -> String {
    let (_, rest) = line
        .split_once("?token=")
        .unwrap_or_else(|| panic!("no token in the link: {line}"));
    rest.split(['#', '&']).next().unwrap().to_string()
}

#[test]
fn off_loopback_the_data_needs_the_token_and_any_host_is_answered() {
    let f = fixture();
    let server = Server::start(
        &f.data,
        &["--bind", "0.0.0.0", "--studio", f.studio.to_str().unwrap()],
    );
    assert!(
        server.first_line.contains("at http://0.0.0.0:"),
        "{}",
        server.first_line
    );
    let open = server.line();
    let port = server.port;
    assert!(
        open.starts_with(&format!("open: http://127.0.0.1:{port}/?token=")),
        "{open}"
    );
    let token = link_token(&open);
    assert_eq!(token.len(), 32, "{token}");
    assert!(token.bytes().all(|b| b.is_ascii_hexdigit()), "{token}");
    // The token is in the query only: the hash (the part a share link carries) has none.
    let hash = open.split_once('#').unwrap().1;
    assert!(!hash.contains(&token), "{open}");
    assert!(server.stderr_has("the link is the key"));

    // As a LAN browser addresses it (its IP or a host name), or as `curl -H 'Host: localhost'` would.
    let ask = |host: &str, path: &str, extra: &str| {
        send_bytes(
            port,
            format!("GET {path} HTTP/1.1\r\nHost: {host}\r\n{extra}\r\n").as_bytes(),
        )
    };
    for host in [
        format!("192.168.77.7:{port}"),
        format!("lab-node-3:{port}"),
        format!("localhost:{port}"),
    ] {
        // The studio's code is public: no token, and no 421.
        let r = ask(&host, "/", "");
        let body = String::from_utf8_lossy(&r.body);
        assert_eq!(r.status, 200, "{host}: {body}");
        assert_eq!(body, INDEX, "{host}");
        let r = ask(&host, "/app_bg.wasm", "");
        assert_eq!(r.status, 200, "{host}");

        let mut wrong = token.clone().into_bytes();
        wrong[31] = if wrong[31] == b'0' { b'1' } else { b'0' };
        let wrong = String::from_utf8(wrong).unwrap();
        for (what, extra) in [
            ("no token", String::new()),
            ("a wrong token", format!("X-Silvr-Token: {wrong}\r\n")),
            ("a prefix", format!("X-Silvr-Token: {}\r\n", &token[..31])),
            ("a longer one", format!("X-Silvr-Token: {token}0\r\n")),
            ("an empty one", "X-Silvr-Token: \r\n".to_string()),
        ] {
            for path in ["/data/sub/x.ply", "/data/no-such-file.ply"] {
                let r = ask(&host, path, &extra);
                assert_eq!(r.status, 401, "{host} {path} with {what}");
                assert_eq!(r.header("www-authenticate"), Some("X-Silvr-Token"));
                assert!(!contains(&r.body, &f.ply), "{what} read the data");
                let body = String::from_utf8_lossy(&r.body);
                assert!(body.contains("X-Silvr-Token"), "{what}: {body}");
            }
        }
        // The token in the request's query is not the key (only the header is: URLs end up in logs).
        let r = ask(&host, &format!("/data/sub/x.ply?token={token}"), "");
        assert_eq!(r.status, 401, "{host}: query token");

        let r = ask(
            &host,
            "/data/sub/x.ply",
            &format!("X-Silvr-Token: {token}\r\n"),
        );
        assert_eq!(
            (r.status, &r.body),
            (200, &f.ply),
            "{host}: the right token"
        );
        let r = ask(
            &host,
            "/data/sub/x.ply",
            &format!("x-silvr-token: {token}\r\nRange: bytes=-5\r\n"),
        );
        assert_eq!(
            (r.status, r.body.as_slice()),
            (206, &f.ply[f.ply.len() - 5..])
        );
    }
}

#[test]
fn a_token_the_user_gives_is_required_on_loopback_too() {
    let f = fixture();
    let token = "lab-key_0123456789";
    let server = Server::start(&f.data, &["--token", token]);
    let open = server.line();
    assert_eq!(link_token(&open), token, "{open}");
    assert_eq!(server.get("/data/sub/x.ply").status, 401);
    let r = server.get_with("/data/sub/x.ply", &format!("X-Silvr-Token: {token}"));
    assert_eq!((r.status, &r.body), (200, &f.ply));
    // Loopback keeps its DNS-rebinding check.
    let r = send_bytes(
        server.port,
        format!(
            "GET / HTTP/1.1\r\nHost: evil.example:{}\r\n\r\n",
            server.port
        )
        .as_bytes(),
    );
    assert_eq!(r.status, 421);

    let out = refused(&f.data, &["--token", "short"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--token"), "{err}");
}
