//! NumPy `.npy` arrays and `.npz` archives (a zip of `.npy` files, stored or deflated), as far as point
//! clouds need them: little- or big-endian `f4`/`f8` arrays in C order. The DGP / Parallel Domain / TRI
//! datasets store each lidar sweep this way. Untrusted input: every size is checked against the bytes
//! present before anything is allocated, and errors name the file.

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

fn u16le(b: &[u8], at: usize) -> Option<u16> {
    Some(u16::from_le_bytes(b.get(at..at + 2)?.try_into().ok()?))
}

fn u32le(b: &[u8], at: usize) -> Option<u32> {
    Some(u32::from_le_bytes(b.get(at..at + 4)?.try_into().ok()?))
}

/// Parses one `.npy` file.
pub fn parse_npy(bytes: &[u8], file: &str) -> Result<Array2, NpzError> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(err(file, "not a .npy array (bad magic)"));
    }
    let (header_len, start): (Option<usize>, usize) = match bytes[6] {
        1 => (u16le(bytes, 8).map(|v| v as usize), 10),
        2 | 3 => (u32le(bytes, 8).map(|v| v as usize), 12),
        v => return Err(err(file, format!(".npy version {v} is not supported"))),
    };
    let header_len = header_len.ok_or_else(|| err(file, "truncated .npy header"))?;
    let header = bytes
        .get(start..start.saturating_add(header_len))
        .ok_or_else(|| err(file, "truncated .npy header"))?;
    let header = std::str::from_utf8(header).map_err(|_| err(file, ".npy header is not text"))?;
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
    let dims: Vec<usize> = shape_text
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>())
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
    let body = &bytes[start + header_len..];
    let n = rows
        .checked_mul(cols)
        .filter(|n| n.checked_mul(size).is_some_and(|b| b <= body.len()))
        .ok_or_else(|| {
            err(
                file,
                format!(
                    "shape ({rows}, {cols}) needs more than the {} bytes present",
                    body.len()
                ),
            )
        })?;
    let data = body[..n * size]
        .chunks_exact(size)
        .map(|c| match (size, big) {
            (8, false) => f64::from_le_bytes(c.try_into().expect("8 bytes")),
            (8, true) => f64::from_be_bytes(c.try_into().expect("8 bytes")),
            (_, false) => f32::from_le_bytes(c.try_into().expect("4 bytes")) as f64,
            (_, true) => f32::from_be_bytes(c.try_into().expect("4 bytes")) as f64,
        })
        .collect();
    Ok(Array2 { rows, cols, data })
}

/// The array named `name` (e.g. `data` for `data.npy`) of an `.npz` archive.
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
    for _ in 0..entries {
        if !bytes
            .get(at..)
            .is_some_and(|b| b.starts_with(b"PK\x01\x02"))
        {
            return Err(err(file, "corrupt zip central directory"));
        }
        let corrupt = || err(file, "corrupt zip central directory");
        let method = u16le(bytes, at + 10).ok_or_else(corrupt)?;
        let csize = u32le(bytes, at + 20).ok_or_else(corrupt)? as usize;
        let usize_ = u32le(bytes, at + 24).ok_or_else(corrupt)? as usize;
        let nlen = u16le(bytes, at + 28).ok_or_else(corrupt)? as usize;
        let elen = u16le(bytes, at + 30).ok_or_else(corrupt)? as usize;
        let clen = u16le(bytes, at + 32).ok_or_else(corrupt)? as usize;
        let local = u32le(bytes, at + 42).ok_or_else(corrupt)? as usize;
        let entry_name = bytes.get(at + 46..at + 46 + nlen).ok_or_else(corrupt)?;
        if entry_name == want.as_bytes() {
            let lh = bytes
                .get(local..local + 30)
                .filter(|h| h.starts_with(b"PK\x03\x04"))
                .ok_or_else(|| err(file, format!("{want}: bad local header")))?;
            let data_at = local
                + 30
                + u16le(lh, 26).unwrap_or(0) as usize
                + u16le(lh, 28).unwrap_or(0) as usize;
            let data = bytes
                .get(data_at..data_at.saturating_add(csize))
                .ok_or_else(|| err(file, format!("{want}: truncated ({csize} bytes expected)")))?;
            let raw = match method {
                0 => data.to_vec(),
                8 => miniz_oxide::inflate::decompress_to_vec_with_limit(data, usize_)
                    .map_err(|e| err(file, format!("{want}: inflate failed ({e:?})")))?,
                m => {
                    return Err(err(
                        file,
                        format!("{want}: zip compression method {m} is not supported"),
                    ))
                }
            };
            return parse_npy(&raw, &format!("{file}/{want}"));
        }
        at += 46 + nlen + elen + clen;
    }
    Err(err(file, format!("no {want} in the archive")))
}

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
            miniz_oxide::deflate::compress_to_vec(content, 6)
        } else {
            content.to_vec()
        };
        let method: u16 = if deflate { 8 } else { 0 };
        let mut z = b"PK\x03\x04".to_vec();
        z.extend_from_slice(&[20, 0, 0, 0]);
        z.extend_from_slice(&method.to_le_bytes());
        z.extend_from_slice(&[0; 8]); // time, date, crc (unchecked)
        z.extend_from_slice(&(data.len() as u32).to_le_bytes());
        z.extend_from_slice(&(content.len() as u32).to_le_bytes());
        z.extend_from_slice(&(name.len() as u16).to_le_bytes());
        z.extend_from_slice(&0u16.to_le_bytes());
        z.extend_from_slice(name.as_bytes());
        z.extend_from_slice(&data);
        let cd = z.len();
        z.extend_from_slice(b"PK\x01\x02");
        z.extend_from_slice(&[20, 0, 20, 0, 0, 0]);
        z.extend_from_slice(&method.to_le_bytes());
        z.extend_from_slice(&[0; 8]);
        z.extend_from_slice(&(data.len() as u32).to_le_bytes());
        z.extend_from_slice(&(content.len() as u32).to_le_bytes());
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
}
