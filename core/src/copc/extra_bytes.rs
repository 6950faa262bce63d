//! LAS extra-bytes dimensions (LAS 1.4 R15 §2.6.3): the descriptors of the `LASF_Spec`/4 VLR and the
//! values they locate in a point record. Shared by the LAS/LAZ reader of `eval` and the COPC node decoder
//! (which the studio's worker runs, so this builds for wasm32).

/// One numeric extra-bytes dimension of a LAS file (LAS 1.4 R15 §2.6.3): where it sits in a point's extra
/// bytes, its type, and the scale and offset its descriptor states.
#[derive(Clone, Debug, PartialEq)]
pub struct ExtraDim {
    pub name: String,
    /// Byte offset within the point's extra bytes.
    pub at: usize,
    pub data_type: u8,
    pub scale: f64,
    pub offset: f64,
}

/// Bytes of an extra-bytes data type: 1–10 the scalars, 11–30 the deprecated 2- and 3-arrays of them, 0
/// an undefined run of `options` bytes.
fn extra_type_bytes(data_type: u8, options: u8) -> Option<usize> {
    const BASE: [usize; 10] = [1, 1, 2, 2, 4, 4, 8, 8, 4, 8];
    match data_type {
        0 => Some(options as usize),
        1..=10 => Some(BASE[data_type as usize - 1]),
        11..=20 => Some(2 * BASE[data_type as usize - 11]),
        21..=30 => Some(3 * BASE[data_type as usize - 21]),
        _ => None,
    }
}

/// The scalar (types 1–10) extra dimensions an extra-bytes VLR's descriptors (`data`, 192 bytes each)
/// name, within `extra_bytes` bytes a point; a descriptor of an unknown type ends the list (what follows
/// cannot be located).
pub fn descriptors(data: &[u8], extra_bytes: usize) -> Vec<ExtraDim> {
    let f64_at = |d: &[u8], k: usize| f64::from_le_bytes(d[k..k + 8].try_into().unwrap_or([0; 8]));
    let mut out = Vec::new();
    let mut at = 0usize;
    for d in data.chunks_exact(192) {
        let (data_type, options) = (d[2], d[3]);
        let Some(size) = extra_type_bytes(data_type, options) else {
            break;
        };
        if at + size > extra_bytes {
            break;
        }
        if (1..=10).contains(&data_type) {
            let name_bytes = &d[4..36];
            let end = name_bytes.iter().position(|&b| b == 0).unwrap_or(32);
            let name = String::from_utf8_lossy(&name_bytes[..end])
                .trim()
                .to_string();
            let scale = if options & 0b1000 != 0 {
                f64_at(d, 112)
            } else {
                1.0
            };
            let offset = if options & 0b1_0000 != 0 {
                f64_at(d, 136)
            } else {
                0.0
            };
            if !name.is_empty() && scale.is_finite() && offset.is_finite() {
                out.push(ExtraDim {
                    name,
                    at,
                    data_type,
                    scale,
                    offset,
                });
            }
        }
        at += size;
    }
    out
}

impl ExtraDim {
    /// The value in a point's extra bytes (`extra` holds at least `at` + the type's size bytes), scaled.
    pub fn value(&self, extra: &[u8]) -> f32 {
        let b = &extra[self.at..];
        let raw = match self.data_type {
            1 => b[0] as f64,
            2 => b[0] as i8 as f64,
            3 => u16::from_le_bytes([b[0], b[1]]) as f64,
            4 => i16::from_le_bytes([b[0], b[1]]) as f64,
            5 => u32::from_le_bytes(b[..4].try_into().unwrap_or([0; 4])) as f64,
            6 => i32::from_le_bytes(b[..4].try_into().unwrap_or([0; 4])) as f64,
            7 => u64::from_le_bytes(b[..8].try_into().unwrap_or([0; 8])) as f64,
            8 => i64::from_le_bytes(b[..8].try_into().unwrap_or([0; 8])) as f64,
            9 => f32::from_le_bytes(b[..4].try_into().unwrap_or([0; 4])) as f64,
            _ => f64::from_le_bytes(b[..8].try_into().unwrap_or([0; 8])),
        };
        // A float stored as float stays bit-exact; the rest go through their stated scale and offset.
        if self.data_type == 9 && self.scale == 1.0 && self.offset == 0.0 {
            return f32::from_le_bytes(b[..4].try_into().unwrap_or([0; 4]));
        }
        (raw * self.scale + self.offset) as f32
    }
}
