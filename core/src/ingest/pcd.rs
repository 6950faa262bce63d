//! PCL's PCD format (v0.7 headers; older headers without VIEWPOINT too): `DATA ascii`, `binary` and
//! `binary_compressed` (LZF, with our own decompressor), any numeric FIELDS/SIZE/TYPE/COUNT.
//!
//! Spires-style tooling stores undistorted sweeps and TLS scans as PCD with the sensor pose in VIEWPOINT,
//! so the reader keeps it. Like the PLY reader it never panics on malformed input, every error names the
//! file, and a header claiming more points than the data could hold is refused before allocating.

use std::path::Path;

use glam::{DQuat, DVec3};
use thiserror::Error;

use crate::geometry::Se3;
use crate::pointcloud::PointCloud;

/// PCD read errors; every variant names the file (or the name given to [`read_pcd_bytes`]).
#[derive(Debug, Error)]
pub enum PcdError {
    #[error("{file}: {source}")]
    Io {
        file: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{file}: bad PCD header (line {line}): {reason}")]
    BadHeader {
        file: String,
        line: usize,
        reason: String,
    },
    #[error("{file}: unsupported PCD: {reason}")]
    Unsupported { file: String, reason: String },
    #[error("{file}: header claims {points} points of {point_bytes} bytes, but only {available} bytes of data follow")]
    CountTooLarge {
        file: String,
        points: u64,
        point_bytes: u64,
        available: u64,
    },
    #[error("{file}: truncated PCD data: {reason}")]
    Truncated { file: String, reason: String },
    #[error("{file}: bad value at point {point}, field '{field}': {reason}")]
    BadValue {
        file: String,
        point: u64,
        field: String,
        reason: String,
    },
    #[error("{file}: corrupt binary_compressed data: {reason}")]
    Lzf { file: String, reason: String },
    #[error("{file}: no x, y and z fields")]
    MissingXyz { file: String },
}

/// A PCD file's cloud plus the header facts the cloud type has no place for.
#[derive(Clone, Debug, PartialEq)]
pub struct PcdCloud {
    /// Positions (NaN points kept, as in organised clouds), `colors` from an `rgb`/`rgba` field, and every
    /// other single-valued field (`intensity`, `ring`, `t`, ...) as a named scalar.
    pub cloud: PointCloud,
    /// VIEWPOINT as `T_world_sensor` (identity when absent).
    pub viewpoint: Se3,
    pub width: u64,
    pub height: u64,
    /// Field names in file order.
    pub fields: Vec<String>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    I,
    U,
    F,
}

#[derive(Clone, Debug)]
struct Field {
    name: String,
    size: usize,
    kind: Kind,
    count: usize,
    /// Byte offset inside one point (binary layout).
    offset: usize,
}

impl Field {
    fn bytes(&self) -> usize {
        self.size * self.count
    }

    /// Element 0 from little-endian bytes.
    fn read(&self, b: &[u8]) -> f64 {
        match (self.kind, self.size) {
            (Kind::I, 1) => b[0] as i8 as f64,
            (Kind::U, 1) => b[0] as f64,
            (Kind::I, 2) => i16::from_le_bytes([b[0], b[1]]) as f64,
            (Kind::U, 2) => u16::from_le_bytes([b[0], b[1]]) as f64,
            (Kind::I, 4) => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            (Kind::U, 4) => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            (Kind::F, 4) => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            (Kind::I, _) => i64::from_le_bytes(le8(b)) as f64,
            (Kind::U, _) => u64::from_le_bytes(le8(b)) as f64,
            (Kind::F, _) => f64::from_le_bytes(le8(b)),
        }
    }

    /// The packed 0x00RRGGBB of an `rgb`/`rgba` field (PCL stores it as the bits of a float or u32).
    fn read_rgb(&self, b: &[u8]) -> [u8; 3] {
        // Little endian: b = [B, G, R, A].
        [b[2], b[1], b[0]]
    }
}

fn le8(b: &[u8]) -> [u8; 8] {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[..8]);
    a
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum DataKind {
    Ascii,
    Binary,
    Compressed,
}

/// Reads a PCD file.
pub fn read_pcd(path: &Path) -> Result<PcdCloud, PcdError> {
    let file = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|source| PcdError::Io {
        file: file.clone(),
        source,
    })?;
    read_pcd_bytes(&bytes, &file)
}

/// Reads PCD bytes; `name` is used in errors.
pub fn read_pcd_bytes(bytes: &[u8], name: &str) -> Result<PcdCloud, PcdError> {
    let file = name.to_string();
    let bad = |line: usize, reason: String| PcdError::BadHeader {
        file: file.clone(),
        line,
        reason,
    };

    // --- header: ASCII lines up to and including DATA ---
    let mut pos = 0usize;
    let mut line_no = 0usize;
    let mut names: Option<Vec<String>> = None;
    let mut sizes: Option<Vec<usize>> = None;
    let mut kinds: Option<Vec<Kind>> = None;
    let mut counts: Option<Vec<usize>> = None;
    let (mut width, mut height, mut points): (Option<u64>, Option<u64>, Option<u64>) =
        (None, None, None);
    let mut viewpoint = Se3::IDENTITY;
    let data_kind = loop {
        if pos >= bytes.len() {
            return Err(bad(line_no, "header ends before the DATA line".into()));
        }
        let end = bytes[pos..]
            .iter()
            .position(|&b| b == b'\n')
            .map_or(bytes.len(), |i| pos + i);
        let raw = &bytes[pos..end];
        pos = (end + 1).min(bytes.len());
        line_no += 1;
        let text = std::str::from_utf8(raw)
            .map_err(|_| bad(line_no, "header line is not text".into()))?
            .trim();
        if text.is_empty() || text.starts_with('#') {
            continue;
        }
        let mut it = text.split_whitespace();
        let key = it.next().unwrap_or("").to_ascii_uppercase();
        let vals: Vec<&str> = it.collect();
        let one_u64 = |what: &str| -> Result<u64, PcdError> {
            match vals.as_slice() {
                [v] => v.parse::<u64>().map_err(|_| {
                    bad(
                        line_no,
                        format!("{what} '{v}' is not a non-negative integer"),
                    )
                }),
                _ => Err(bad(line_no, format!("{what} needs one value"))),
            }
        };
        match key.as_str() {
            "VERSION" => {}
            "FIELDS" | "COLUMNS" => names = Some(vals.iter().map(|s| s.to_string()).collect()),
            "SIZE" => {
                let mut v = Vec::new();
                for s in &vals {
                    match s.parse::<usize>() {
                        Ok(n @ (1 | 2 | 4 | 8)) => v.push(n),
                        _ => return Err(bad(line_no, format!("SIZE '{s}' is not 1, 2, 4 or 8"))),
                    }
                }
                sizes = Some(v);
            }
            "TYPE" => {
                let mut v = Vec::new();
                for s in &vals {
                    v.push(match *s {
                        "I" | "i" => Kind::I,
                        "U" | "u" => Kind::U,
                        "F" | "f" => Kind::F,
                        _ => return Err(bad(line_no, format!("TYPE '{s}' is not I, U or F"))),
                    });
                }
                kinds = Some(v);
            }
            "COUNT" => {
                let mut v = Vec::new();
                for s in &vals {
                    match s.parse::<usize>() {
                        Ok(n) if (1..=1 << 16).contains(&n) => v.push(n),
                        _ => return Err(bad(line_no, format!("COUNT '{s}' is not in 1..=65536"))),
                    }
                }
                counts = Some(v);
            }
            "WIDTH" => width = Some(one_u64("WIDTH")?),
            "HEIGHT" => height = Some(one_u64("HEIGHT")?),
            "POINTS" => points = Some(one_u64("POINTS")?),
            "VIEWPOINT" => {
                let v: Result<Vec<f64>, _> = vals.iter().map(|s| s.parse::<f64>()).collect();
                match v.as_deref() {
                    Ok([tx, ty, tz, qw, qx, qy, qz]) => {
                        let q = DQuat::from_xyzw(*qx, *qy, *qz, *qw);
                        if !(q.is_finite()
                            && q.length() > 0.0
                            && tx.is_finite()
                            && ty.is_finite()
                            && tz.is_finite())
                        {
                            return Err(bad(line_no, "VIEWPOINT is not a finite pose".into()));
                        }
                        viewpoint = Se3::new(q, DVec3::new(*tx, *ty, *tz));
                    }
                    _ => {
                        return Err(bad(
                            line_no,
                            "VIEWPOINT needs 7 numbers (tx ty tz qw qx qy qz)".into(),
                        ))
                    }
                }
            }
            "DATA" => {
                break match vals.first().copied() {
                    Some("ascii") => DataKind::Ascii,
                    Some("binary") => DataKind::Binary,
                    Some("binary_compressed") => DataKind::Compressed,
                    other => {
                        return Err(PcdError::Unsupported {
                            file: file.clone(),
                            reason: format!("DATA {}", other.unwrap_or("(missing)")),
                        })
                    }
                };
            }
            other => return Err(bad(line_no, format!("unknown header keyword '{other}'"))),
        }
    };

    let names = names.ok_or_else(|| bad(line_no, "no FIELDS line".into()))?;
    let sizes = sizes.ok_or_else(|| bad(line_no, "no SIZE line".into()))?;
    let kinds = kinds.ok_or_else(|| bad(line_no, "no TYPE line".into()))?;
    let counts = counts.unwrap_or_else(|| vec![1; names.len()]);
    if names.is_empty()
        || sizes.len() != names.len()
        || kinds.len() != names.len()
        || counts.len() != names.len()
    {
        return Err(bad(
            line_no,
            format!(
                "FIELDS ({}), SIZE ({}), TYPE ({}) and COUNT ({}) differ in length",
                names.len(),
                sizes.len(),
                kinds.len(),
                counts.len()
            ),
        ));
    }
    let mut fields = Vec::with_capacity(names.len());
    let mut offset = 0usize;
    for (((name, size), kind), count) in names.iter().zip(&sizes).zip(&kinds).zip(&counts) {
        if *kind == Kind::F && *size < 4 {
            return Err(bad(
                line_no,
                format!("field '{name}': float of {size} bytes"),
            ));
        }
        fields.push(Field {
            name: name.clone(),
            size: *size,
            kind: *kind,
            count: *count,
            offset,
        });
        offset += size * count;
    }
    let point_bytes = offset;
    let width = width.ok_or_else(|| bad(line_no, "no WIDTH line".into()))?;
    let height = height.unwrap_or(1);
    let wh = width
        .checked_mul(height)
        .ok_or_else(|| bad(line_no, "WIDTH x HEIGHT overflows".into()))?;
    let n = points.unwrap_or(wh);
    if n != wh {
        return Err(bad(
            line_no,
            format!("POINTS {n} differs from WIDTH {width} x HEIGHT {height}"),
        ));
    }
    let find = |name: &str| fields.iter().position(|f| f.name == name);
    let (Some(ix), Some(iy), Some(iz)) = (find("x"), find("y"), find("z")) else {
        return Err(PcdError::MissingXyz { file });
    };
    let irgb = find("rgb")
        .or_else(|| find("rgba"))
        .filter(|&i| fields[i].size == 4);

    let data = &bytes[pos..];
    let available = data.len() as u64;
    let too_many = || PcdError::CountTooLarge {
        file: file.clone(),
        points: n,
        point_bytes: point_bytes as u64,
        available,
    };

    let mut positions = Vec::new();
    // Every other single-valued field (intensity, ring, time, ...) becomes a named scalar.
    let extra: Vec<usize> = (0..fields.len())
        .filter(|&i| {
            ![Some(ix), Some(iy), Some(iz), irgb].contains(&Some(i)) && fields[i].count == 1
        })
        .collect();
    let mut scalars: Vec<Vec<f32>> = extra.iter().map(|_| Vec::new()).collect();
    let mut colors = irgb.map(|_| Vec::new());
    match data_kind {
        DataKind::Binary => {
            let need = n.checked_mul(point_bytes as u64).ok_or_else(too_many)?;
            if need > available {
                return Err(too_many());
            }
            let n = n as usize;
            positions.reserve_exact(n);
            for k in 0..n {
                let p = &data[k * point_bytes..(k + 1) * point_bytes];
                let get = |i: usize| fields[i].read(&p[fields[i].offset..]);
                positions.push(DVec3::new(get(ix), get(iy), get(iz)));
                for (&i, v) in extra.iter().zip(scalars.iter_mut()) {
                    v.push(get(i) as f32);
                }
                if let (Some(i), Some(v)) = (irgb, colors.as_mut()) {
                    v.push(fields[i].read_rgb(&p[fields[i].offset..]));
                }
            }
        }
        DataKind::Compressed => {
            let lzf = |reason: String| PcdError::Lzf {
                file: file.clone(),
                reason,
            };
            if data.len() < 8 {
                return Err(PcdError::Truncated {
                    file: file.clone(),
                    reason: format!(
                        "{} bytes after DATA, need an 8-byte size header",
                        data.len()
                    ),
                });
            }
            let csize = u32::from_le_bytes([data[0], data[1], data[2], data[3]]) as u64;
            let usize_ = u32::from_le_bytes([data[4], data[5], data[6], data[7]]) as u64;
            let need = n.checked_mul(point_bytes as u64).ok_or_else(too_many)?;
            if usize_ != need {
                return Err(lzf(format!(
                    "uncompressed size {usize_} differs from {n} points x {point_bytes} bytes = {need}"
                )));
            }
            if csize > available - 8 {
                return Err(PcdError::Truncated {
                    file: file.clone(),
                    reason: format!("compressed size {csize} but {} bytes follow", available - 8),
                });
            }
            if usize_ > csize.saturating_mul(LZF_MAX_RATIO) + 64 {
                return Err(too_many());
            }
            let raw = lzf_decompress(&data[8..8 + csize as usize], usize_ as usize).map_err(lzf)?;
            // Field-major layout: all x, then all y, ...
            let n = n as usize;
            let base = |i: usize| fields[i].offset * n;
            let get = |i: usize, k: usize| {
                let f = &fields[i];
                f.read(&raw[base(i) + k * f.bytes()..])
            };
            positions.reserve_exact(n);
            for k in 0..n {
                positions.push(DVec3::new(get(ix, k), get(iy, k), get(iz, k)));
                for (&i, v) in extra.iter().zip(scalars.iter_mut()) {
                    v.push(get(i, k) as f32);
                }
                if let (Some(i), Some(v)) = (irgb, colors.as_mut()) {
                    let f = &fields[i];
                    v.push(f.read_rgb(&raw[base(i) + k * f.bytes()..]));
                }
            }
        }
        DataKind::Ascii => {
            let values: usize = fields.iter().map(|f| f.count).sum();
            // Each value needs at least one character and one separator.
            if n.saturating_mul(values as u64) > available / 2 + 1 {
                return Err(too_many());
            }
            let text = std::str::from_utf8(data).map_err(|_| PcdError::BadValue {
                file: file.clone(),
                point: 0,
                field: String::new(),
                reason: "ascii data is not text".into(),
            })?;
            positions.reserve_exact(n as usize);
            let mut lines = text.lines().filter(|l| !l.trim().is_empty());
            let mut toks: Vec<&str> = Vec::with_capacity(values);
            for k in 0..n {
                let line = lines.next().ok_or_else(|| PcdError::Truncated {
                    file: file.clone(),
                    reason: format!("ascii data ends after {k} of {n} points"),
                })?;
                toks.clear();
                toks.extend(line.split_whitespace());
                if toks.len() < values {
                    return Err(PcdError::BadValue {
                        file: file.clone(),
                        point: k,
                        field: String::new(),
                        reason: format!("{} values on the line, expected {values}", toks.len()),
                    });
                }
                let tok = |i: usize| toks[fields[..i].iter().map(|f| f.count).sum::<usize>()];
                let num = |i: usize| -> Result<f64, PcdError> {
                    let s = tok(i);
                    parse_ascii(s).ok_or_else(|| PcdError::BadValue {
                        file: file.clone(),
                        point: k,
                        field: fields[i].name.clone(),
                        reason: format!("'{s}' is not a number"),
                    })
                };
                positions.push(DVec3::new(num(ix)?, num(iy)?, num(iz)?));
                for (&i, v) in extra.iter().zip(scalars.iter_mut()) {
                    v.push(num(i)? as f32);
                }
                if let (Some(i), Some(v)) = (irgb, colors.as_mut()) {
                    let s = tok(i);
                    // PCL prints a float-typed rgb as the float whose bits are the packed colour.
                    let bits = match fields[i].kind {
                        Kind::F => s.parse::<f32>().ok().map(f32::to_bits),
                        _ => s.parse::<u32>().ok(),
                    };
                    let bits = bits.ok_or_else(|| PcdError::BadValue {
                        file: file.clone(),
                        point: k,
                        field: fields[i].name.clone(),
                        reason: format!("'{s}' is not a packed colour"),
                    })?;
                    v.push([(bits >> 16) as u8, (bits >> 8) as u8, bits as u8]);
                }
            }
        }
    }
    let mut cloud = PointCloud::from_positions(positions);
    cloud.colors = colors;
    for (&i, v) in extra.iter().zip(scalars) {
        cloud.scalars.push((fields[i].name.clone(), v));
    }
    Ok(PcdCloud {
        cloud,
        viewpoint,
        width,
        height,
        fields: names,
    })
}

/// ASCII numbers as PCL prints them, including `nan`/`inf` in any case.
fn parse_ascii(s: &str) -> Option<f64> {
    s.parse::<f64>()
        .ok()
        .or_else(|| match s.to_ascii_lowercase().as_str() {
            "nan" | "-nan" | "+nan" => Some(f64::NAN),
            _ => None,
        })
}

/// The most an LZF stream can expand: a 3-byte back reference yields up to 264 bytes.
const LZF_MAX_RATIO: u64 = 88;

/// Decompresses an LZF stream (liblzf format, as PCL writes it) that must produce exactly `out_len`
/// bytes. Any overrun, back reference before the start, or length mismatch is an error.
/// A binary PCD (v0.7) of `cloud`: x y z as F4, then every scalar as F4, VIEWPOINT = `viewpoint`
/// (`T_world_sensor`). What PCL and Oxford Spires' tools read.
pub fn write_pcd_bytes(cloud: &PointCloud, viewpoint: &Se3) -> Vec<u8> {
    let names: Vec<&str> = ["x", "y", "z"]
        .into_iter()
        .chain(cloud.scalars.iter().map(|(n, _)| n.as_str()))
        .collect();
    let k = names.len();
    let n = cloud.positions.len();
    let q = viewpoint.rot;
    let t = viewpoint.trans;
    let mut out = format!(
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {}\nSIZE {}\nTYPE {}\nCOUNT {}\n\
         WIDTH {n}\nHEIGHT 1\nVIEWPOINT {} {} {} {} {} {} {}\nPOINTS {n}\nDATA binary\n",
        names.join(" "),
        vec!["4"; k].join(" "),
        vec!["F"; k].join(" "),
        vec!["1"; k].join(" "),
        t.x,
        t.y,
        t.z,
        q.w,
        q.x,
        q.y,
        q.z
    )
    .into_bytes();
    out.reserve(n * k * 4);
    for (i, p) in cloud.positions.iter().enumerate() {
        for v in [p.x, p.y, p.z] {
            out.extend_from_slice(&(v as f32).to_le_bytes());
        }
        for (_, s) in &cloud.scalars {
            out.extend_from_slice(&s.get(i).copied().unwrap_or(f32::NAN).to_le_bytes());
        }
    }
    out
}

pub fn lzf_decompress(input: &[u8], out_len: usize) -> Result<Vec<u8>, String> {
    let mut out: Vec<u8> = Vec::with_capacity(out_len);
    let mut ip = 0usize;
    while ip < input.len() {
        let ctrl = input[ip] as usize;
        ip += 1;
        if ctrl < 32 {
            let len = ctrl + 1;
            if ip + len > input.len() {
                return Err(format!(
                    "literal run of {len} at input byte {} runs past the end",
                    ip - 1
                ));
            }
            if out.len() + len > out_len {
                return Err(format!("output exceeds the expected {out_len} bytes"));
            }
            out.extend_from_slice(&input[ip..ip + len]);
            ip += len;
        } else {
            let mut len = ctrl >> 5;
            if len == 7 {
                let extra = *input
                    .get(ip)
                    .ok_or_else(|| "back reference length runs past the end".to_string())?;
                len += extra as usize;
                ip += 1;
            }
            let low = *input
                .get(ip)
                .ok_or_else(|| "back reference offset runs past the end".to_string())?;
            ip += 1;
            let back = ((ctrl & 0x1f) << 8) + low as usize + 1;
            len += 2;
            if back > out.len() {
                return Err(format!(
                    "back reference {back} bytes before output byte {}",
                    out.len()
                ));
            }
            if out.len() + len > out_len {
                return Err(format!("output exceeds the expected {out_len} bytes"));
            }
            let start = out.len() - back;
            // Overlapping copies repeat the pattern, so copy byte by byte.
            for j in 0..len {
                let b = out[start + j];
                out.push(b);
            }
        }
    }
    if out.len() != out_len {
        return Err(format!(
            "stream produced {} bytes, expected {out_len}",
            out.len()
        ));
    }
    Ok(out)
}

/// LZF compression (greedy, 3-byte hash), compatible with liblzf's decoder. Used to write
/// `binary_compressed` PCDs and to test the decoder.
pub fn lzf_compress(input: &[u8]) -> Vec<u8> {
    const HBITS: usize = 14;
    let mut table = vec![usize::MAX; 1 << HBITS];
    let mut out = Vec::with_capacity(input.len() + input.len() / 32 + 1);
    let mut lit: Vec<u8> = Vec::with_capacity(32);
    let flush = |lit: &mut Vec<u8>, out: &mut Vec<u8>| {
        if !lit.is_empty() {
            out.push((lit.len() - 1) as u8);
            out.extend_from_slice(lit);
            lit.clear();
        }
    };
    let n = input.len();
    let mut i = 0;
    while i < n {
        if i + 2 < n {
            let h =
                ((input[i] as usize) << 16 | (input[i + 1] as usize) << 8 | input[i + 2] as usize)
                    .wrapping_mul(2654435761)
                    >> 8
                    & ((1 << HBITS) - 1);
            let cand = table[h];
            table[h] = i;
            if cand != usize::MAX && i - cand <= 8192 && input[cand..cand + 3] == input[i..i + 3] {
                let max = (n - i).min(264);
                let mut len = 3;
                while len < max && input[cand + len] == input[i + len] {
                    len += 1;
                }
                flush(&mut lit, &mut out);
                let off = i - cand - 1;
                let l = len - 2;
                if l < 7 {
                    out.push((l << 5 | off >> 8) as u8);
                } else {
                    out.push((7 << 5 | off >> 8) as u8);
                    out.push((l - 7) as u8);
                }
                out.push((off & 0xff) as u8);
                i += len;
                continue;
            }
        }
        lit.push(input[i]);
        if lit.len() == 32 {
            flush(&mut lit, &mut out);
        }
        i += 1;
    }
    flush(&mut lit, &mut out);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lzf_round_trip_and_known_stream() {
        // Literal "abc" then a back reference of 6 bytes at distance 3: "abcabcabc".
        let stream = [2, b'a', b'b', b'c', (4 << 5), 2];
        assert_eq!(lzf_decompress(&stream, 9).unwrap(), b"abcabcabc");
        for data in [
            Vec::new(),
            b"a".to_vec(),
            vec![7u8; 10_000],
            (0..5000u32).flat_map(|i| (i % 97).to_le_bytes()).collect(),
            (0..3000u32)
                .map(|i| (i.wrapping_mul(2654435761) >> 13) as u8)
                .collect(),
        ] {
            let c = lzf_compress(&data);
            assert_eq!(lzf_decompress(&c, data.len()).unwrap(), data);
        }
        let c = lzf_compress(&vec![7u8; 10_000]);
        assert!(c.len() < 200, "runs compress ({} bytes)", c.len());
    }

    #[test]
    fn lzf_rejects_corrupt_streams() {
        let data: Vec<u8> = (0..2000u32).flat_map(|i| (i % 50).to_le_bytes()).collect();
        let c = lzf_compress(&data);
        for n in 0..c.len() {
            assert!(lzf_decompress(&c[..n], data.len()).is_err(), "prefix {n}");
        }
        assert!(lzf_decompress(&c, data.len() - 1).is_err());
        assert!(lzf_decompress(&c, data.len() + 1).is_err());
        // A back reference before the start of the output.
        assert!(lzf_decompress(&[0, b'x', (1 << 5), 5], 4).is_err());
    }

    #[test]
    fn written_pcd_reads_back_with_scalars_and_viewpoint() {
        let mut pc = PointCloud::from_positions(vec![
            DVec3::new(1.0, -2.5, 0.25),
            DVec3::new(40.0, 3.0, -1.0),
        ]);
        pc.set_scalar("intensity", vec![3.0, 250.0]);
        pc.set_scalar("ring", vec![0.0, 15.0]);
        let vp = Se3::new(DQuat::from_rotation_z(0.3), DVec3::new(10.0, -4.0, 1.5));
        let back = read_pcd_bytes(&write_pcd_bytes(&pc, &vp), "w.pcd").unwrap();
        assert_eq!(back.cloud.positions, pc.positions);
        assert_eq!(back.cloud.scalars, pc.scalars);
        assert!(back.viewpoint.distance_to(&vp) < 1e-6 && back.viewpoint.angle_to(&vp) < 1e-6);
        assert_eq!(back.fields, ["x", "y", "z", "intensity", "ring"]);
    }
}
