//! NumPy `.npy` arrays and `.npz` archives (a zip of `.npy` files, stored or deflated), as far as point
//! clouds need them: little- or big-endian `f4`/`f8` arrays in C order. The DGP / Parallel Domain / TRI
//! datasets store each lidar sweep this way. Untrusted input: every offset is checked, every size is
//! checked against the bytes present (or the size an entry declares) and [`MAX_ARRAY_BYTES`] before
//! anything is allocated or inflated, and errors name the file.

use std::io::Read;

/// Why an array could not be read.
#[derive(Debug, thiserror::Error)]
#[error("{file}: {reason}")]
pub struct NpzError {
    pub file: String,
    pub reason: String,
}

fn err(file: &str, reason: impl Into<String>) -> NpzError {
    NpzError {
        file: file.to_string(),
        reason: reason.into(),
    }
}

/// A 2-D (or 1-D, as one column) array of numbers as f64, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct Array2 {
    pub rows: usize,
    pub cols: usize,
    pub data: Vec<f64>,
}

impl Array2 {
    pub fn row(&self, i: usize) -> &[f64] {
        &self.data[i * self.cols..(i + 1) * self.cols]
    }
}

/// Largest array one `.npy` may hold (its data bytes, shape × dtype), whatever a file claims: a lidar
/// sweep is a few MiB, and this keeps a hostile file well inside a browser's 4 GiB heap. An `.npz`
/// entry that declares more uncompressed bytes than this (plus [`MAX_HEADER`]) is refused before
/// anything is inflated.
pub const MAX_ARRAY_BYTES: u64 = 1 << 30;
/// Longest `.npy` header accepted (numpy writes ~128 bytes, and refuses more than 10 000 by default).
pub const MAX_HEADER: usize = 1 << 16;

/// `len` bytes of `b` at `at`, with checked offsets.
fn slice(b: &[u8], at: usize, len: usize) -> Option<&[u8]> {
    b.get(at..at.checked_add(len)?)
}

fn u16le(b: &[u8], at: usize) -> Option<u16> {
    Some(u16::from_le_bytes(slice(b, at, 2)?.try_into().ok()?))
}

fn u32le(b: &[u8], at: usize) -> Option<u32> {
    Some(u32::from_le_bytes(slice(b, at, 4)?.try_into().ok()?))
}

/// Reads into `buf` until it is full or the stream ends; the number of bytes read.
fn read_full(r: &mut impl Read, buf: &mut [u8], file: &str) -> Result<usize, NpzError> {
    let mut n = 0;
    while n < buf.len() {
        match r.read(&mut buf[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(err(file, format!("cannot be read: {e}"))),
        }
    }
    Ok(n)
}

/// Parses one `.npy` file.
pub fn parse_npy(bytes: &[u8], file: &str) -> Result<Array2, NpzError> {
    read_npy(&mut &bytes[..], bytes.len() as u64, "present", file)
}

/// Reads one `.npy` from `r`, which holds at most `limit` bytes (`bound` says why, for messages). The
/// array's size (shape × dtype) is checked against `limit` and [`MAX_ARRAY_BYTES`] before its buffer
/// is reserved, and its data is read through `take`, so a stream longer than it says is never read
/// past the array.
fn read_npy(r: &mut impl Read, limit: u64, bound: &str, file: &str) -> Result<Array2, NpzError> {
    let mut pre = [0u8; 12];
    let got = read_full(r, &mut pre[..10], file)?;
    if got < 10 || &pre[..6] != b"\x93NUMPY" {
        return Err(err(file, "not a .npy array (bad magic)"));
    }
    let (header_len, start) = match pre[6] {
        1 => (u16le(&pre, 8).unwrap_or(0) as usize, 10),
        2 | 3 => {
            if read_full(r, &mut pre[10..12], file)? < 2 {
                return Err(err(file, "truncated .npy header"));
            }
            (u32le(&pre, 8).unwrap_or(u32::MAX) as usize, 12)
        }
        v => return Err(err(file, format!(".npy version {v} is not supported"))),
    };
    if header_len > MAX_HEADER {
        return Err(err(
            file,
            format!(".npy header of {header_len} bytes (more than {MAX_HEADER})"),
        ));
    }
    let mut header = vec![0u8; header_len];
    if read_full(r, &mut header, file)? < header_len {
        return Err(err(file, "truncated .npy header"));
    }
    let header = std::str::from_utf8(&header).map_err(|_| err(file, ".npy header is not text"))?;
    let field = |key: &str| -> Option<&str> {
        let at = header.find(&format!("'{key}'"))? + key.len() + 2;
        let rest = header[at..].trim_start().strip_prefix(':')?.trim_start();
        Some(rest)
    };
    let descr = field("descr")
        .and_then(|r| r.strip_prefix('\''))
        .and_then(|r| r.split('\'').next())
        .ok_or_else(|| err(file, "no 'descr' in the .npy header"))?;
    let (big, size) = match descr {
        "<f8" | "=f8" | "|f8" => (false, 8),
        ">f8" => (true, 8),
        "<f4" | "=f4" | "|f4" => (false, 4),
        ">f4" => (true, 4),
        d => {
            return Err(err(
                file,
                format!("dtype {d:?} is not supported (float32 or float64)"),
            ))
        }
    };
    if field("fortran_order").is_some_and(|r| r.starts_with("True")) {
        return Err(err(file, "Fortran-order arrays are not supported"));
    }
    let shape_text = field("shape")
        .and_then(|r| r.strip_prefix('('))
        .and_then(|r| r.split(')').next())
        .ok_or_else(|| err(file, "no 'shape' in the .npy header"))?;
    let dims: Vec<u64> = shape_text
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<u64>())
        .collect::<Result<_, _>>()
        .map_err(|_| err(file, format!("bad shape ({shape_text})")))?;
    let (rows, cols) = match dims.as_slice() {
        [n] => (*n, 1),
        [r, c] => (*r, *c),
        d => {
            return Err(err(
                file,
                format!("a {}-D array is not a point list", d.len()),
            ))
        }
    };
    let left = limit.saturating_sub((start + header_len) as u64);
    let body = rows
        .checked_mul(cols)
        .and_then(|n| n.checked_mul(size as u64))
        .filter(|&b| b <= left)
        .ok_or_else(|| {
            err(
                file,
                format!("shape ({rows}, {cols}) needs more than the {left} bytes {bound}"),
            )
        })?;
    if body > MAX_ARRAY_BYTES {
        return Err(err(
            file,
            format!(
                "shape ({rows}, {cols}) is {body} bytes, more than the {} MiB an array may hold",
                MAX_ARRAY_BYTES >> 20
            ),
        ));
    }
    // Both fit in usize now: at most MAX_ARRAY_BYTES.
    let n = (body / size as u64) as usize;
    let mut data: Vec<f64> = Vec::new();
    data.try_reserve_exact(n).map_err(|_| {
        err(
            file,
            format!("shape ({rows}, {cols}) does not fit in memory"),
        )
    })?;
    let mut r = r.take(body);
    let mut chunk = vec![0u8; 64 << 10];
    while data.len() < n {
        let want = ((n - data.len()) * size).min(chunk.len());
        let got = read_full(&mut r, &mut chunk[..want], file)?;
        if got < want {
            return Err(err(
                file,
                format!(
                    "truncated: the data ends {} bytes into the {body} the shape needs",
                    data.len() * size + got
                ),
            ));
        }
        data.extend(chunk[..want].chunks_exact(size).map(|c| match (size, big) {
            (8, false) => f64::from_le_bytes(c.try_into().expect("8 bytes")),
            (8, true) => f64::from_be_bytes(c.try_into().expect("8 bytes")),
            (_, false) => f32::from_le_bytes(c.try_into().expect("4 bytes")) as f64,
            (_, true) => f32::from_be_bytes(c.try_into().expect("4 bytes")) as f64,
        }));
    }
    Ok(Array2 {
        rows: rows as usize,
        cols: cols as usize,
        data,
    })
}

/// The array named `name` (e.g. `data` for `data.npy`) of an `.npz` archive. Offsets are checked
/// everywhere; a deflated entry is inflated as a stream bounded by its declared uncompressed size, the
/// array's shape and [`MAX_ARRAY_BYTES`], so a zip bomb stops at the bound.
pub fn parse_npz(bytes: &[u8], name: &str, file: &str) -> Result<Array2, NpzError> {
    // The central directory lists every entry with reliable sizes (local headers may defer them).
    let eocd = (0..bytes.len().saturating_sub(21))
        .rev()
        .take(65_557)
        .find(|&i| bytes[i..].starts_with(b"PK\x05\x06"))
        .ok_or_else(|| err(file, "not a zip archive (no end of central directory)"))?;
    let entries = u16le(bytes, eocd + 10).unwrap_or(0) as usize;
    let mut at = u32le(bytes, eocd + 16).unwrap_or(u32::MAX) as usize;
    let want = format!("{name}.npy");
    let corrupt = || err(file, "corrupt zip central directory");
    for _ in 0..entries {
        if !bytes
            .get(at..)
            .is_some_and(|b| b.starts_with(b"PK\x01\x02"))
        {
            return Err(corrupt());
        }
        let method = u16le(bytes, at + 10).ok_or_else(corrupt)?;
        let csize = u32le(bytes, at + 20).ok_or_else(corrupt)? as usize;
        let usize_ = u32le(bytes, at + 24).ok_or_else(corrupt)? as u64;
        let nlen = u16le(bytes, at + 28).ok_or_else(corrupt)? as usize;
        let elen = u16le(bytes, at + 30).ok_or_else(corrupt)? as usize;
        let clen = u16le(bytes, at + 32).ok_or_else(corrupt)? as usize;
        let local = u32le(bytes, at + 42).ok_or_else(corrupt)? as usize;
        let entry_name = slice(bytes, at + 46, nlen).ok_or_else(corrupt)?;
        if entry_name == want.as_bytes() {
            let inner = format!("{file}/{want}");
            let lh = slice(bytes, local, 30)
                .filter(|h| h.starts_with(b"PK\x03\x04"))
                .ok_or_else(|| err(file, format!("{want}: bad local header")))?;
            let data = (local + 30)
                .checked_add(u16le(lh, 26).unwrap_or(0) as usize)
                .and_then(|a| a.checked_add(u16le(lh, 28).unwrap_or(0) as usize))
                .and_then(|a| slice(bytes, a, csize))
                .ok_or_else(|| err(file, format!("{want}: truncated ({csize} bytes expected)")))?;
            return match method {
                0 => read_npy(&mut &data[..], data.len() as u64, "present", &inner),
                8 => {
                    if usize_ > MAX_ARRAY_BYTES + MAX_HEADER as u64 {
                        return Err(err(
                            &inner,
                            format!(
                                "declares {usize_} bytes uncompressed, more than the {} MiB an array \
                                 may hold",
                                MAX_ARRAY_BYTES >> 20
                            ),
                        ));
                    }
                    // Deflate cannot expand past 1032:1 (zlib's technical notes): a declared size beyond
                    // that of the compressed bytes present is a lie, refused before the array is reserved
                    // (which the declared size would otherwise bound alone: a 1 KB file, 1 GiB reserved).
                    let most = (csize as u64).saturating_mul(MAX_DEFLATE_RATIO) + 64;
                    if usize_ > most {
                        return Err(err(
                            &inner,
                            format!(
                                "declares {usize_} bytes uncompressed from {csize} deflated, more than \
                                 deflate can expand them to ({most})"
                            ),
                        ));
                    }
                    let mut z = flate2::read::DeflateDecoder::new(data).take(usize_);
                    read_npy(&mut z, usize_, "its zip entry declares", &inner)
                }
                m => Err(err(
                    file,
                    format!("{want}: zip compression method {m} is not supported"),
                )),
            };
        }
        at = nlen
            .checked_add(elen)
            .and_then(|n| n.checked_add(clen))
            .and_then(|n| n.checked_add(46))
            .and_then(|n| at.checked_add(n))
            .ok_or_else(corrupt)?;
    }
    Err(err(file, format!("no {want} in the archive")))
}

/// Deflate's largest expansion: 258-byte matches coded in 2 bits each, 1032:1.
const MAX_DEFLATE_RATIO: u64 = 1032;

#[cfg(test)]
mod tests {
    use super::*;

    fn npy(descr: &str, shape: &str, body: &[u8]) -> Vec<u8> {
        let mut h = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
        while (10 + h.len() + 1) % 64 != 0 {
            h.push(' ');
        }
        h.push('\n');
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        b.extend_from_slice(&(h.len() as u16).to_le_bytes());
        b.extend_from_slice(h.as_bytes());
        b.extend_from_slice(body);
        b
    }

    /// A stored (method 0) or deflated (method 8) single-entry zip.
    fn zip(name: &str, content: &[u8], deflate: bool) -> Vec<u8> {
        let data = if deflate {
            deflated([content])
        } else {
            content.to_vec()
        };
        zip_raw(name, deflate, &data, content.len() as u32)
    }

    /// The raw deflate stream of the concatenated `parts` (a bomb's gigabytes never held at once).
    fn deflated<'a>(parts: impl IntoIterator<Item = &'a [u8]>) -> Vec<u8> {
        let mut e = flate2::write::DeflateEncoder::new(Vec::new(), flate2::Compression::new(6));
        for p in parts {
            std::io::Write::write_all(&mut e, p).unwrap();
        }
        e.finish().unwrap()
    }

    /// A single-entry zip of `data` as it is (deflated or stored) that declares `declared` bytes
    /// uncompressed.
    fn zip_raw(name: &str, deflate: bool, data: &[u8], declared: u32) -> Vec<u8> {
        let method: u16 = if deflate { 8 } else { 0 };
        let mut z = b"PK\x03\x04".to_vec();
        z.extend_from_slice(&[20, 0, 0, 0]);
        z.extend_from_slice(&method.to_le_bytes());
        z.extend_from_slice(&[0; 8]); // time, date, crc (unchecked)
        z.extend_from_slice(&(data.len() as u32).to_le_bytes());
        z.extend_from_slice(&declared.to_le_bytes());
        z.extend_from_slice(&(name.len() as u16).to_le_bytes());
        z.extend_from_slice(&0u16.to_le_bytes());
        z.extend_from_slice(name.as_bytes());
        z.extend_from_slice(data);
        let cd = z.len();
        z.extend_from_slice(b"PK\x01\x02");
        z.extend_from_slice(&[20, 0, 20, 0, 0, 0]);
        z.extend_from_slice(&method.to_le_bytes());
        z.extend_from_slice(&[0; 8]);
        z.extend_from_slice(&(data.len() as u32).to_le_bytes());
        z.extend_from_slice(&declared.to_le_bytes());
        z.extend_from_slice(&(name.len() as u16).to_le_bytes());
        z.extend_from_slice(&[0; 12]);
        z.extend_from_slice(&0u32.to_le_bytes()); // local header offset
        z.extend_from_slice(name.as_bytes());
        let cd_len = z.len() - cd;
        z.extend_from_slice(b"PK\x05\x06");
        z.extend_from_slice(&[0; 4]);
        z.extend_from_slice(&1u16.to_le_bytes());
        z.extend_from_slice(&1u16.to_le_bytes());
        z.extend_from_slice(&(cd_len as u32).to_le_bytes());
        z.extend_from_slice(&(cd as u32).to_le_bytes());
        z.extend_from_slice(&0u16.to_le_bytes());
        z
    }

    /// Claims of sizes beyond what is there are refused before inflating or reserving; a stream that
    /// inflates past the array is never read past it.
    #[test]
    fn absurd_sizes_and_zip_bombs_are_bounded() {
        let header = npy("<f8", "(1250000000,)", &[]); // 10 GB of f64
                                                       // The entry declares 4 GiB uncompressed: refused before a byte is inflated.
        let z = zip_raw("data.npy", true, &deflated([&header[..]]), u32::MAX);
        let e = parse_npz(&z, "data", "big.npz").unwrap_err().to_string();
        assert!(
            e.starts_with("big.npz/data.npy: declares 4294967295 bytes"),
            "{e}"
        );
        // A small declared size, a header claiming 10 GB, and a stream that really inflates to 64 MiB.
        let zeros = vec![0u8; 1 << 20];
        let bomb = deflated(std::iter::once(&header[..]).chain((0..64).map(|_| &zeros[..])));
        assert!(bomb.len() < 200 << 10, "{}", bomb.len());
        let z = zip_raw("data.npy", true, &bomb, 1000);
        let e = parse_npz(&z, "data", "bomb.npz").unwrap_err().to_string();
        assert!(
            e.contains("bomb.npz/data.npy") && e.contains("needs more than the 872 bytes its zip"),
            "{e}"
        );
        // An honest-looking header of 100 M values (800 MB, under the cap) declared as the entry's size
        // over a few hundred deflated bytes: refused by deflate's ratio before 800 MB are reserved.
        let big = npy("<f8", "(100000000,)", &[]);
        let small_z = deflated([&big[..]]);
        let z = zip_raw("data.npy", true, &small_z, (big.len() + 800_000_000) as u32);
        let e = parse_npz(&z, "data", "r.npz").unwrap_err().to_string();
        assert!(
            e.starts_with("r.npz/data.npy: declares 800000128 bytes uncompressed from")
                && e.contains("deflate can expand"),
            "{e}"
        );
        // Stored, the same claim is refused against the bytes present.
        let z = zip("data.npy", &header, false);
        let e = parse_npz(&z, "data", "s.npz").unwrap_err().to_string();
        assert!(e.contains("needs more than the 0 bytes present"), "{e}");
        // Within the cap an honest header of 2 values over a 64 MiB stream: only 16 bytes are read.
        let small = npy("<f8", "(2,)", &[0; 16]);
        let bomb = deflated(std::iter::once(&small[..]).chain((0..64).map(|_| &zeros[..])));
        let z = zip_raw("data.npy", true, &bomb, small.len() as u32);
        assert_eq!(parse_npz(&z, "data", "b.npz").unwrap().data, vec![0.0, 0.0]);
        // Declared larger than the stream: truncated, an error.
        let z = zip_raw(
            "data.npy",
            true,
            &deflated([&small[..100]]),
            small.len() as u32,
        );
        let e = parse_npz(&z, "data", "t.npz").unwrap_err().to_string();
        assert!(
            e.contains("t.npz/data.npy") && e.contains("truncated"),
            "{e}"
        );
        // Hostile offsets and lengths (every field at its maximum) are errors, not overflows.
        let mut z = zip("data.npy", &small, false);
        let cd = z.len() - 22 - 46 - "data.npy".len();
        // Local header offset, name length, compressed size; the central directory's offset.
        for (at, len) in [(cd + 42, 4), (cd + 28, 2), (cd + 20, 4), (z.len() - 6, 4)] {
            let mut h = z.clone();
            h[at..at + len].fill(0xff);
            let r = parse_npz(&h, "data", "h.npz");
            assert!(r.is_err(), "field at {at} of {}: {r:?}", z.len());
        }
        z[30 - 4..30].fill(0xff); // the local header's name and extra lengths
        assert!(parse_npz(&z, "data", "h.npz").is_err());
    }

    #[test]
    fn arrays_round_trip_and_bad_files_are_errors() {
        let vals: Vec<f64> = (0..8).map(|i| i as f64 * 0.5 - 1.0).collect();
        let body: Vec<u8> = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
        let a = parse_npy(&npy("<f8", "(2, 4)", &body), "a.npy").unwrap();
        assert_eq!((a.rows, a.cols), (2, 4));
        assert_eq!(a.data, vals);
        assert_eq!(a.row(1), &vals[4..]);
        let body32: Vec<u8> = vals
            .iter()
            .flat_map(|v| (*v as f32).to_be_bytes())
            .collect();
        let b = parse_npy(&npy(">f4", "(8,)", &body32), "b.npy").unwrap();
        assert_eq!((b.rows, b.cols, b.data.clone()), (8, 1, vals.clone()));
        for deflate in [false, true] {
            let z = zip("data.npy", &npy("<f8", "(2, 4)", &body), deflate);
            assert_eq!(parse_npz(&z, "data", "s.npz").unwrap(), a);
            let e = parse_npz(&z, "other", "s.npz").unwrap_err().to_string();
            assert!(e.contains("s.npz") && e.contains("other.npy"), "{e}");
            // Every truncation is an error, never a panic.
            for n in 0..z.len() {
                assert!(parse_npz(&z[..n], "data", "s.npz").is_err(), "prefix {n}");
            }
        }
        for (bytes, want) in [
            (npy("<i8", "(2, 4)", &body), "not supported"),
            (npy("<f8", "(3, 4)", &body), "needs more than"),
            (npy("<f8", "(2, 2, 2)", &body), "3-D"),
            (
                npy("<f8", "(18446744073709551615, 4)", &body),
                "needs more than",
            ),
            (b"PK\x03\x04junk".to_vec(), "bad magic"),
        ] {
            let e = parse_npy(&bytes, "x.npy").unwrap_err().to_string();
            assert!(e.contains(want), "{e}");
        }
    }

    fn seed_dir() -> std::path::PathBuf {
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/seeds/npz")
    }

    /// The npz fuzz target's seeds: a stored and a deflated archive of a 3×4 float64 array (a lidar
    /// sweep's layout), and a bare big-endian float32 `.npy`.
    fn seeds() -> Vec<(&'static str, Vec<u8>)> {
        let body: Vec<u8> = (0..12)
            .flat_map(|i| (i as f64 * 0.25).to_le_bytes())
            .collect();
        let arr = npy("<f8", "(3, 4)", &body);
        let body32: Vec<u8> = (0..5).flat_map(|i| (i as f32).to_be_bytes()).collect();
        vec![
            ("stored.npz", zip("data.npy", &arr, false)),
            ("deflated.npz", zip("data.npy", &arr, true)),
            ("be_f4.npy", npy(">f4", "(5,)", &body32)),
        ]
    }

    /// Regenerate with `cargo test -p silvr-core --lib write_npz_fuzz_seeds -- --ignored`.
    #[test]
    #[ignore]
    fn write_npz_fuzz_seeds() {
        std::fs::create_dir_all(seed_dir()).unwrap();
        for (name, bytes) in seeds() {
            std::fs::write(seed_dir().join(name), bytes).unwrap();
        }
    }

    #[test]
    fn the_npz_fuzz_seeds_are_current_and_parse() {
        for (name, bytes) in seeds() {
            assert_eq!(
                std::fs::read(seed_dir().join(name)).unwrap(),
                bytes,
                "{name}"
            );
            let a = if name.ends_with(".npz") {
                parse_npz(&bytes, "data", name)
            } else {
                parse_npy(&bytes, name)
            };
            assert!(a.unwrap().rows >= 3, "{name}");
        }
    }
}
