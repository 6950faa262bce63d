//! A zero-copy reader and a small writer for ROS 2 CDR (OMG XCDR1, as written by rmw_fastrtps / cyclonedds).
//!
//! Why our own: PointCloud2 and Image payloads are megabytes, and a serde-based decoder copies `uint8[]`
//! element by element. The reader borrows `&[u8]` for byte sequences and checks every length against the
//! bytes that are left *before* allocating, so a corrupt or hostile payload is an `Err`, never a panic or a
//! multi-gigabyte `Vec`.
//!
//! Layout: a 4-byte encapsulation header (`00 01` = little endian, `00 00` = big endian, then two option
//! bytes), then the body. Primitives align to their own size **relative to the first body byte**; strings
//! are a u32 length that counts the trailing NUL; sequences are a u32 element count; fixed arrays have no
//! count.

use thiserror::Error;

/// Byte order of a CDR body.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Endian {
    Little,
    Big,
}

/// Why a CDR payload could not be read. Offsets are body offsets (after the 4-byte header).
#[derive(Clone, Debug, PartialEq, Eq, Error)]
pub enum CdrError {
    #[error("payload of {0} bytes is shorter than the 4-byte CDR encapsulation header")]
    NoHeader(usize),
    #[error("unsupported CDR encapsulation {id:#06x} ({name}); only plain CDR (XCDR1) LE/BE is supported")]
    UnsupportedEncapsulation { id: u16, name: &'static str },
    #[error("truncated at byte {at}: {what} needs {need} bytes, {left} left")]
    Truncated {
        what: &'static str,
        at: usize,
        need: usize,
        left: usize,
    },
    #[error("{what} at byte {at} claims {count} elements of {elem_size} bytes, but only {left} bytes are left")]
    CountTooLarge {
        what: &'static str,
        at: usize,
        count: u64,
        elem_size: usize,
        left: usize,
    },
    #[error("string at byte {at} is not NUL-terminated")]
    StringNotTerminated { at: usize },
    #[error("string at byte {at} is not valid UTF-8")]
    StringNotUtf8 { at: usize },
    #[error("{0}")]
    Invalid(String),
}

/// Encapsulation identifiers (DDS-XTypes 1.3, 7.6.3.1.2).
fn encapsulation(id: u16) -> Result<Endian, CdrError> {
    let unsupported = |name| Err(CdrError::UnsupportedEncapsulation { id, name });
    match id {
        0x0000 => Ok(Endian::Big),
        0x0001 => Ok(Endian::Little),
        0x0002 => unsupported("PL_CDR_BE, parameter list"),
        0x0003 => unsupported("PL_CDR_LE, parameter list"),
        0x0006 => unsupported("CDR2_BE, XCDR2"),
        0x0007 => unsupported("CDR2_LE, XCDR2"),
        0x0008 => unsupported("D_CDR2_BE, delimited XCDR2"),
        0x0009 => unsupported("D_CDR2_LE, delimited XCDR2"),
        0x000a => unsupported("PL_CDR2_BE, parameter list XCDR2"),
        0x000b => unsupported("PL_CDR2_LE, parameter list XCDR2"),
        _ => unsupported("unknown"),
    }
}

/// A cursor over a CDR body. Every read checks bounds; reads that fail leave the position unspecified
/// (callers stop at the first error).
#[derive(Clone, Debug)]
pub struct CdrReader<'a> {
    body: &'a [u8],
    pos: usize,
    endian: Endian,
}

impl<'a> CdrReader<'a> {
    /// Reads the encapsulation header of a full serialized message and positions the cursor on the body.
    pub fn new(payload: &'a [u8]) -> Result<Self, CdrError> {
        if payload.len() < 4 {
            return Err(CdrError::NoHeader(payload.len()));
        }
        let id = u16::from_be_bytes([payload[0], payload[1]]);
        let endian = encapsulation(id)?;
        Ok(Self::from_body(&payload[4..], endian))
    }

    /// A reader over a body without the header (alignment origin = `body[0]`).
    pub fn from_body(body: &'a [u8], endian: Endian) -> Self {
        Self {
            body,
            pos: 0,
            endian,
        }
    }

    pub fn endian(&self) -> Endian {
        self.endian
    }

    /// Offset of the cursor in the body.
    pub fn position(&self) -> usize {
        self.pos
    }

    /// Bytes after the cursor.
    pub fn remaining(&self) -> usize {
        self.body.len() - self.pos
    }

    /// Skips the padding up to the next multiple of `n` (a power of two). Padding past the end is an
    /// error only when something is read after it, so a message may end on unaligned bytes.
    pub fn align(&mut self, n: usize) {
        let next = (self.pos + n - 1) & !(n - 1);
        self.pos = next.min(self.body.len());
    }

    fn aligned_take(&mut self, n: usize, what: &'static str) -> Result<&'a [u8], CdrError> {
        let start = (self.pos + n - 1) & !(n - 1);
        self.take_at(start, n, what)
    }

    fn take_at(
        &mut self,
        start: usize,
        n: usize,
        what: &'static str,
    ) -> Result<&'a [u8], CdrError> {
        let left = self.body.len().saturating_sub(start);
        if n > left {
            return Err(CdrError::Truncated {
                what,
                at: start,
                need: n,
                left,
            });
        }
        self.pos = start + n;
        Ok(&self.body[start..start + n])
    }

    /// `n` raw bytes with no alignment (fixed `uint8[N]`).
    pub fn bytes(&mut self, n: usize, what: &'static str) -> Result<&'a [u8], CdrError> {
        self.take_at(self.pos, n, what)
    }

    pub fn u8(&mut self) -> Result<u8, CdrError> {
        Ok(self.aligned_take(1, "uint8")?[0])
    }

    pub fn i8(&mut self) -> Result<i8, CdrError> {
        Ok(self.u8()? as i8)
    }

    /// A CDR boolean: one byte, any non-zero value is true.
    pub fn bool(&mut self) -> Result<bool, CdrError> {
        Ok(self.aligned_take(1, "bool")?[0] != 0)
    }

    pub fn u16(&mut self) -> Result<u16, CdrError> {
        let b = self.aligned_take(2, "uint16")?;
        let a = [b[0], b[1]];
        Ok(match self.endian {
            Endian::Little => u16::from_le_bytes(a),
            Endian::Big => u16::from_be_bytes(a),
        })
    }

    pub fn i16(&mut self) -> Result<i16, CdrError> {
        Ok(self.u16()? as i16)
    }

    pub fn u32(&mut self) -> Result<u32, CdrError> {
        let b = self.aligned_take(4, "uint32")?;
        let a = [b[0], b[1], b[2], b[3]];
        Ok(match self.endian {
            Endian::Little => u32::from_le_bytes(a),
            Endian::Big => u32::from_be_bytes(a),
        })
    }

    pub fn i32(&mut self) -> Result<i32, CdrError> {
        Ok(self.u32()? as i32)
    }

    pub fn u64(&mut self) -> Result<u64, CdrError> {
        let b = self.aligned_take(8, "uint64")?;
        let mut a = [0u8; 8];
        a.copy_from_slice(b);
        Ok(match self.endian {
            Endian::Little => u64::from_le_bytes(a),
            Endian::Big => u64::from_be_bytes(a),
        })
    }

    pub fn i64(&mut self) -> Result<i64, CdrError> {
        Ok(self.u64()? as i64)
    }

    pub fn f32(&mut self) -> Result<f32, CdrError> {
        Ok(f32::from_bits(self.u32()?))
    }

    pub fn f64(&mut self) -> Result<f64, CdrError> {
        Ok(f64::from_bits(self.u64()?))
    }

    /// A `string`: u32 length including the NUL, the bytes, the NUL. A length of 0 (written by some
    /// implementations for an empty string) reads as "".
    pub fn string(&mut self) -> Result<&'a str, CdrError> {
        let len = self.seq_len(1, "string")?;
        let at = self.pos - 4;
        if len == 0 {
            return Ok("");
        }
        let raw = self.bytes(len, "string")?;
        let (last, text) = raw
            .split_last()
            .ok_or(CdrError::StringNotTerminated { at })?;
        if *last != 0 {
            return Err(CdrError::StringNotTerminated { at });
        }
        std::str::from_utf8(text).map_err(|_| CdrError::StringNotUtf8 { at })
    }

    /// A sequence header: the u32 element count, checked against the bytes left assuming each element
    /// needs at least `min_elem_size` bytes (use 1 for structs of unknown size: the check then still
    /// bounds any allocation by the payload size).
    pub fn seq_len(&mut self, min_elem_size: usize, what: &'static str) -> Result<usize, CdrError> {
        let count = self.u32()?;
        let at = self.pos - 4;
        let left = self.remaining();
        let elem = min_elem_size.max(1);
        // The first element may need alignment padding (< elem bytes), which is never counted here so a
        // valid message cannot fail; over-claims are still caught to within one element.
        if (count as u64) * (elem as u64) > left as u64 + (elem as u64 - 1) {
            return Err(CdrError::CountTooLarge {
                what,
                at,
                count: count as u64,
                elem_size: elem,
                left,
            });
        }
        Ok(count as usize)
    }

    /// A `uint8[]` / `byte[]` sequence, borrowed.
    pub fn byte_seq(&mut self, what: &'static str) -> Result<&'a [u8], CdrError> {
        let n = self.seq_len(1, what)?;
        self.bytes(n, what)
    }

    /// A `float64[]` sequence.
    pub fn f64_seq(&mut self, what: &'static str) -> Result<Vec<f64>, CdrError> {
        let n = self.seq_len(8, what)?;
        (0..n).map(|_| self.f64()).collect()
    }

    /// A fixed `float64[N]` array.
    pub fn f64_array<const N: usize>(&mut self) -> Result<[f64; N], CdrError> {
        let mut out = [0.0; N];
        for v in &mut out {
            *v = self.f64()?;
        }
        Ok(out)
    }
}

/// A CDR writer (little endian by default). Used by tests and by our own bag writer.
#[derive(Clone, Debug)]
pub struct CdrWriter {
    buf: Vec<u8>,
    endian: Endian,
}

impl Default for CdrWriter {
    fn default() -> Self {
        Self::new()
    }
}

impl CdrWriter {
    /// A little-endian (CDR_LE) message, as ROS 2 writes on every common platform.
    pub fn new() -> Self {
        Self::with_endian(Endian::Little)
    }

    /// A message in the given byte order (big endian exists in the wild only from exotic hosts; tests use it).
    pub fn with_endian(endian: Endian) -> Self {
        let id: u8 = match endian {
            Endian::Little => 1,
            Endian::Big => 0,
        };
        Self {
            buf: vec![0, id, 0, 0],
            endian,
        }
    }

    /// Body length so far (alignment origin is the first body byte).
    fn body_len(&self) -> usize {
        self.buf.len() - 4
    }

    pub fn align(&mut self, n: usize) {
        while !self.body_len().is_multiple_of(n) {
            self.buf.push(0);
        }
    }

    fn put(&mut self, le: &[u8], be: &[u8]) {
        self.align(le.len());
        match self.endian {
            Endian::Little => self.buf.extend_from_slice(le),
            Endian::Big => self.buf.extend_from_slice(be),
        }
    }

    pub fn u8(&mut self, v: u8) -> &mut Self {
        self.buf.push(v);
        self
    }

    pub fn i8(&mut self, v: i8) -> &mut Self {
        self.u8(v as u8)
    }

    pub fn bool(&mut self, v: bool) -> &mut Self {
        self.u8(v as u8)
    }

    pub fn u16(&mut self, v: u16) -> &mut Self {
        self.put(&v.to_le_bytes(), &v.to_be_bytes());
        self
    }

    pub fn i16(&mut self, v: i16) -> &mut Self {
        self.u16(v as u16)
    }

    pub fn u32(&mut self, v: u32) -> &mut Self {
        self.put(&v.to_le_bytes(), &v.to_be_bytes());
        self
    }

    pub fn i32(&mut self, v: i32) -> &mut Self {
        self.u32(v as u32)
    }

    pub fn u64(&mut self, v: u64) -> &mut Self {
        self.put(&v.to_le_bytes(), &v.to_be_bytes());
        self
    }

    pub fn i64(&mut self, v: i64) -> &mut Self {
        self.u64(v as u64)
    }

    pub fn f32(&mut self, v: f32) -> &mut Self {
        self.u32(v.to_bits())
    }

    pub fn f64(&mut self, v: f64) -> &mut Self {
        self.u64(v.to_bits())
    }

    /// Raw bytes, no alignment, no count.
    pub fn raw(&mut self, b: &[u8]) -> &mut Self {
        self.buf.extend_from_slice(b);
        self
    }

    /// A sequence/string count. Lengths above u32::MAX cannot be represented in CDR; they saturate
    /// (and the reader then rejects the message), since a writer panic would be worse.
    pub fn seq_len(&mut self, n: usize) -> &mut Self {
        self.u32(u32::try_from(n).unwrap_or(u32::MAX))
    }

    pub fn string(&mut self, s: &str) -> &mut Self {
        self.seq_len(s.len() + 1);
        self.buf.extend_from_slice(s.as_bytes());
        self.buf.push(0);
        self
    }

    pub fn byte_seq(&mut self, b: &[u8]) -> &mut Self {
        self.seq_len(b.len());
        self.raw(b)
    }

    pub fn f64_seq(&mut self, v: &[f64]) -> &mut Self {
        self.seq_len(v.len());
        for &x in v {
            self.f64(x);
        }
        self
    }

    pub fn f64_array(&mut self, v: &[f64]) -> &mut Self {
        for &x in v {
            self.f64(x);
        }
        self
    }

    /// The serialized message, header included.
    pub fn finish(self) -> Vec<u8> {
        self.buf
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(endian: Endian) -> Vec<u8> {
        let mut w = CdrWriter::with_endian(endian);
        w.u8(7)
            .u32(0xdead_beef)
            .i16(-3)
            .f64(1.5)
            .string("frame")
            .byte_seq(&[1, 2, 3])
            .f64_seq(&[0.25, -2.0])
            .bool(true)
            .i64(-9);
        w.finish()
    }

    fn read_sample(bytes: &[u8]) -> Result<(), CdrError> {
        let mut r = CdrReader::new(bytes)?;
        assert_eq!(r.u8()?, 7);
        assert_eq!(r.u32()?, 0xdead_beef);
        assert_eq!(r.i16()?, -3);
        assert_eq!(r.f64()?, 1.5);
        assert_eq!(r.string()?, "frame");
        assert_eq!(r.byte_seq("data")?, &[1, 2, 3]);
        assert_eq!(r.f64_seq("d")?, vec![0.25, -2.0]);
        assert!(r.bool()?);
        assert_eq!(r.i64()?, -9);
        assert_eq!(r.remaining(), 0);
        Ok(())
    }

    #[test]
    fn round_trip_both_endiannesses() {
        for e in [Endian::Little, Endian::Big] {
            let b = sample(e);
            read_sample(&b).unwrap();
            assert_eq!(CdrReader::new(&b).unwrap().endian(), e);
        }
    }

    #[test]
    fn layout_matches_cdr_alignment_rules() {
        let b = sample(Endian::Little);
        assert_eq!(&b[..4], &[0, 1, 0, 0]);
        let body = &b[4..];
        // u8 @0, pad to 4, u32 @4, i16 @8, pad to 16, f64 @16, string len @24, "frame\0" @28..34.
        assert_eq!(body[0], 7);
        assert_eq!(&body[1..4], &[0, 0, 0]);
        assert_eq!(&body[4..8], &0xdead_beefu32.to_le_bytes());
        assert_eq!(&body[8..10], &(-3i16).to_le_bytes());
        assert_eq!(&body[16..24], &1.5f64.to_le_bytes());
        assert_eq!(&body[24..28], &6u32.to_le_bytes());
        assert_eq!(&body[28..34], b"frame\0");
        let be = sample(Endian::Big);
        assert_eq!(&be[..4], &[0, 0, 0, 0]);
        assert_eq!(&be[8..12], &0xdead_beefu32.to_be_bytes());
    }

    #[test]
    fn every_prefix_is_an_error_not_a_panic() {
        for e in [Endian::Little, Endian::Big] {
            let b = sample(e);
            for n in 0..b.len() {
                assert!(
                    read_sample(&b[..n]).is_err(),
                    "prefix {n} of {} read",
                    b.len()
                );
            }
        }
    }

    #[test]
    fn rejects_parameter_lists_and_xcdr2() {
        for id in [2u8, 3, 7, 9, 0x0b, 0x42] {
            let e = CdrReader::new(&[0, id, 0, 0]).unwrap_err();
            assert!(
                matches!(e, CdrError::UnsupportedEncapsulation { .. }),
                "{e}"
            );
        }
        assert!(CdrReader::new(&[0, 3, 0, 0])
            .unwrap_err()
            .to_string()
            .contains("PL_CDR_LE"));
        assert_eq!(CdrReader::new(&[0, 1]).unwrap_err(), CdrError::NoHeader(2));
    }

    #[test]
    fn absurd_counts_are_errors_before_allocation() {
        let mut w = CdrWriter::new();
        w.u32(u32::MAX).raw(&[0; 16]);
        let b = w.finish();
        assert!(matches!(
            CdrReader::new(&b).unwrap().byte_seq("data"),
            Err(CdrError::CountTooLarge { .. })
        ));
        assert!(matches!(
            CdrReader::new(&b).unwrap().f64_seq("d"),
            Err(CdrError::CountTooLarge { .. })
        ));
        assert!(CdrReader::new(&b).unwrap().string().is_err());
    }

    #[test]
    fn strings_must_be_terminated_utf8() {
        let mut w = CdrWriter::new();
        w.u32(3).raw(b"abc");
        let b = w.finish();
        assert!(matches!(
            CdrReader::new(&b).unwrap().string(),
            Err(CdrError::StringNotTerminated { .. })
        ));
        let mut w = CdrWriter::new();
        w.u32(3).raw(&[0xff, 0xfe, 0]);
        let b = w.finish();
        assert!(matches!(
            CdrReader::new(&b).unwrap().string(),
            Err(CdrError::StringNotUtf8 { .. })
        ));
        let mut w = CdrWriter::new();
        w.u32(0).u32(5);
        let b = w.finish();
        let mut r = CdrReader::new(&b).unwrap();
        assert_eq!(r.string().unwrap(), "");
        assert_eq!(r.u32().unwrap(), 5);
    }
}
