//! The HTTP/1.1 request side of `silvr serve`: the request head, the path a target names, byte ranges.
//!
//! Every byte here comes from the network, so each function is total: a malformed input is an error
//! status (or, for `Range`, the whole file), never a panic. Kept apart from the server so that the fuzz
//! target `http_head` (fuzz/) can reach it through the `silvr` library.

use std::path::{Component, Path};

// The studio's own percent-decoding (one codec for the links serve prints and the paths it reads).
use silvr_worker::view::decode_bytes;

/// A parsed request head (header names lower-cased).
#[derive(Debug)]
pub struct Request {
    pub method: String,
    pub target: String,
    pub headers: Vec<(String, String)>,
}

impl Request {
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_str())
    }
}

/// End of the head (after its blank line), for CRLF and bare-LF line ends.
pub fn head_end(buf: &[u8]) -> Option<usize> {
    let crlf = buf.windows(4).position(|w| w == b"\r\n\r\n").map(|i| i + 4);
    let lf = buf.windows(2).position(|w| w == b"\n\n").map(|i| i + 2);
    match (crlf, lf) {
        (Some(a), Some(b)) => Some(a.min(b)),
        (a, b) => a.or(b),
    }
}

/// Parses a request head; errors are the status to answer with.
pub fn parse_head(head: &[u8]) -> Result<Request, u16> {
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
pub fn request_path(target: &str) -> Result<Vec<String>, u16> {
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

/// A `Range` header's meaning for a file of `len` bytes.
#[derive(Debug, PartialEq, Eq)]
pub enum ByteRange {
    /// No usable range: the whole file (200). Also for several ranges, which we may answer whole.
    Full,
    /// Bytes `start..=end` (206).
    Part { start: u64, end: u64 },
    /// 416.
    Unsatisfiable,
}

/// Parses a single byte range (`bytes=a-b`, `bytes=a-`, `bytes=-n`). A syntactically invalid header is
/// ignored (RFC 9110 §14.2), so it means the whole file; one that starts past the end is unsatisfiable.
pub fn parse_range(value: &str, len: u64) -> ByteRange {
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

#[cfg(test)]
mod tests {
    use super::*;

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
}
