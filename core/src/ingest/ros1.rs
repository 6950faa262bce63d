//! ROS 1 messages, read through the message definitions a bag carries: each connection of a ROS 1 bag
//! stores the full `.msg` text of its type and of every type it uses, so a message is walked field by
//! field from that text (not from offsets hard-coded per type) and rewritten as ROS 2 CDR. The ROS 2
//! decoders in [`super::ros`] then read it exactly as they read an MCAP or `.db3` bag.
//!
//! Why transcode rather than decode twice: the ROS 1 and ROS 2 layouts of the sensor messages differ only
//! in their serialisation (no alignment, strings without NUL, `time` as two u32) and in `std_msgs/Header`,
//! whose ROS 1 form has a `seq` counter first — the same rule the Python `rosbags` package applies. One
//! set of type-specific decoders then serves every container. The cost is one copy of each decoded
//! message (bulk `memcpy` for `uint8[]` and primitive arrays).
//!
//! Input is untrusted: counts are checked against the bytes left before anything is reserved, nesting
//! is bounded, and every error says which field of which type failed.

use std::collections::HashMap;

use super::cdr::CdrWriter;

/// Nesting depth beyond which a definition is refused (ROS types nest a handful of levels; a cycle in a
/// hostile definition would otherwise recurse without end).
const MAX_DEPTH: usize = 32;
/// Largest element count of an array whose elements may take no bytes (e.g. `std_msgs/Empty[]`), which
/// the remaining bytes cannot bound.
const MAX_EMPTY_ELEMENTS: usize = 1 << 16;

/// A primitive field type of the ROS 1 `.msg` language.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Prim {
    Bool,
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    I64,
    U64,
    F32,
    F64,
    String,
    Time,
    Duration,
}

impl Prim {
    fn parse(name: &str) -> Option<Self> {
        Some(match name {
            "bool" => Prim::Bool,
            "int8" | "byte" => Prim::I8,
            "uint8" | "char" => Prim::U8,
            "int16" => Prim::I16,
            "uint16" => Prim::U16,
            "int32" => Prim::I32,
            "uint32" => Prim::U32,
            "int64" => Prim::I64,
            "uint64" => Prim::U64,
            "float32" => Prim::F32,
            "float64" => Prim::F64,
            "string" => Prim::String,
            "time" => Prim::Time,
            "duration" => Prim::Duration,
            _ => return None,
        })
    }

    /// Bytes in ROS 1 (for a string: its length prefix).
    fn size(self) -> usize {
        match self {
            Prim::Bool | Prim::I8 | Prim::U8 => 1,
            Prim::I16 | Prim::U16 => 2,
            Prim::I32 | Prim::U32 | Prim::F32 | Prim::String => 4,
            Prim::I64 | Prim::U64 | Prim::F64 | Prim::Time | Prim::Duration => 8,
        }
    }

    /// CDR alignment (= size for the fixed-size scalars).
    fn align(self) -> usize {
        match self {
            Prim::Time | Prim::Duration | Prim::String => 4,
            p => p.size(),
        }
    }
}

#[derive(Clone, Debug, PartialEq, Eq)]
enum FieldType {
    Prim(Prim),
    /// A message type by its full name `pkg/Type`.
    Msg(String),
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Array {
    No,
    Var,
    Fixed(usize),
}

#[derive(Clone, Debug)]
struct Field {
    name: String,
    ty: FieldType,
    array: Array,
}

/// A connection's message definition: its type and every type it uses, parsed.
#[derive(Clone, Debug)]
pub struct Definition {
    root: String,
    types: HashMap<String, Vec<Field>>,
}

/// `pkg/msg/Type` or `pkg/Type` → `pkg/Type`.
fn short_name(name: &str) -> String {
    match name.split('/').collect::<Vec<_>>()[..] {
        [pkg, "msg", ty] => format!("{pkg}/{ty}"),
        _ => name.to_string(),
    }
}

impl Definition {
    /// Parses the `message_definition` of a connection whose type is `msg_type` (`pkg/Type`). Dependent
    /// types follow the root's text, each after a line of `=` and a line `MSG: pkg/Type`.
    pub fn parse(msg_type: &str, text: &str) -> Result<Self, String> {
        let root = short_name(msg_type);
        if !root.contains('/') {
            return Err(format!("type '{msg_type}' is not of the form pkg/Type"));
        }
        let mut types = HashMap::new();
        let mut current = root.clone();
        let mut fields = Vec::new();
        for (no, raw) in text.lines().enumerate() {
            let line = raw.trim();
            if line.starts_with("===") {
                types.insert(std::mem::take(&mut current), std::mem::take(&mut fields));
                continue;
            }
            if let Some(name) = line.strip_prefix("MSG:") {
                current = short_name(name.trim());
                continue;
            }
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let package = current.split('/').next().unwrap_or("").to_string();
            if let Some(f) = parse_field(line, &package)
                .map_err(|e| format!("message definition of {root}, line {}: {e}", no + 1))?
            {
                fields.push(f);
            }
        }
        types.insert(current, fields);
        types.remove("");
        let def = Definition { root, types };
        def.check()?;
        Ok(def)
    }

    /// Every referenced type is defined and nesting is bounded.
    fn check(&self) -> Result<(), String> {
        fn visit(d: &Definition, ty: &str, depth: usize) -> Result<(), String> {
            if depth > MAX_DEPTH {
                return Err(format!(
                    "types nest deeper than {MAX_DEPTH} (a cycle?) at {ty}"
                ));
            }
            let fields = d.types.get(ty).ok_or_else(|| {
                format!("type {ty} is used but not defined in the message definition")
            })?;
            for f in fields {
                if let FieldType::Msg(t) = &f.ty {
                    visit(d, t, depth + 1)?;
                }
            }
            Ok(())
        }
        visit(self, &self.root, 0)
    }

    /// The root type, `pkg/Type`.
    pub fn root(&self) -> &str {
        &self.root
    }

    /// Rewrites a ROS 1 serialised message as ROS 2 CDR (little endian), dropping `std_msgs/Header.seq`.
    pub fn to_cdr(&self, ros1: &[u8]) -> Result<Vec<u8>, String> {
        let mut r = Reader { b: ros1, pos: 0 };
        let mut w = CdrWriter::new();
        self.walk(&self.root, &mut r, &mut w, 0)
            .map_err(|e| format!("{} at byte {}: {e}", self.root, r.pos))?;
        if r.pos != ros1.len() {
            return Err(format!(
                "{}: {} bytes left after the last field (the message does not match its definition)",
                self.root,
                ros1.len() - r.pos
            ));
        }
        Ok(w.finish())
    }

    /// Smallest ROS 1 size of one value of `ty` (bounds array counts before any work).
    fn min_size(&self, ty: &FieldType, depth: usize) -> usize {
        match ty {
            FieldType::Prim(p) => p.size(),
            FieldType::Msg(t) if depth <= MAX_DEPTH => self.types.get(t).map_or(0, |fs| {
                fs.iter()
                    .map(|f| match f.array {
                        Array::No => self.min_size(&f.ty, depth + 1),
                        Array::Var => 4,
                        Array::Fixed(n) => n.saturating_mul(self.min_size(&f.ty, depth + 1)),
                    })
                    .fold(0usize, usize::saturating_add)
            }),
            FieldType::Msg(_) => 0,
        }
    }

    fn walk(
        &self,
        ty: &str,
        r: &mut Reader,
        w: &mut CdrWriter,
        depth: usize,
    ) -> Result<(), String> {
        if depth > MAX_DEPTH {
            return Err(format!("nesting deeper than {MAX_DEPTH}"));
        }
        let fields = self
            .types
            .get(ty)
            .ok_or_else(|| format!("type {ty} not defined"))?;
        let header = ty == "std_msgs/Header";
        for (i, f) in fields.iter().enumerate() {
            if header && i == 0 && f.name == "seq" && f.ty == FieldType::Prim(Prim::U32) {
                r.take(4, "std_msgs/Header.seq")?;
                continue;
            }
            let count = match f.array {
                Array::No => {
                    self.value(&f.ty, r, w, depth)
                        .map_err(|e| format!("{ty}.{}: {e}", f.name))?;
                    continue;
                }
                Array::Fixed(n) => n,
                Array::Var => {
                    let n = r.u32(&f.name)? as usize;
                    w.seq_len(n);
                    n
                }
            };
            let min = self.min_size(&f.ty, depth + 1);
            let fits = if min == 0 {
                count <= MAX_EMPTY_ELEMENTS
            } else {
                count.checked_mul(min).is_some_and(|b| b <= r.left())
            };
            if !fits {
                return Err(format!(
                    "{ty}.{}: {count} elements do not fit in the {} bytes left",
                    f.name,
                    r.left()
                ));
            }
            match f.ty {
                // Fixed-size primitives: one aligned bulk copy (both sides little endian).
                FieldType::Prim(p)
                    if p != Prim::String && p != Prim::Time && p != Prim::Duration =>
                {
                    let bytes = r.take(count * p.size(), &f.name)?;
                    if count > 0 {
                        w.align(p.align());
                    }
                    w.raw(bytes);
                }
                _ => {
                    for _ in 0..count {
                        self.value(&f.ty, r, w, depth)
                            .map_err(|e| format!("{ty}.{}[]: {e}", f.name))?;
                    }
                }
            }
        }
        Ok(())
    }

    fn value(
        &self,
        ty: &FieldType,
        r: &mut Reader,
        w: &mut CdrWriter,
        depth: usize,
    ) -> Result<(), String> {
        match ty {
            FieldType::Msg(t) => self.walk(t, r, w, depth + 1),
            FieldType::Prim(Prim::String) => {
                let n = r.u32("string length")? as usize;
                let s = r.take(n, "string")?;
                w.seq_len(n + 1).raw(s).u8(0);
                Ok(())
            }
            FieldType::Prim(Prim::Time | Prim::Duration) => {
                let b = r.take(8, "time")?;
                w.align(4);
                w.raw(b);
                Ok(())
            }
            FieldType::Prim(p) => {
                let b = r.take(p.size(), "value")?;
                w.align(p.align());
                w.raw(b);
                Ok(())
            }
        }
    }
}

/// One field line (`type name`, `type[] name`, `type[N] name`); `None` for a constant (`type NAME=value`).
fn parse_field(line: &str, package: &str) -> Result<Option<Field>, String> {
    let mut parts = line.splitn(2, char::is_whitespace);
    let ty = parts.next().unwrap_or("");
    let rest = parts.next().unwrap_or("").trim_start();
    let name_end = rest
        .find(|c: char| c.is_whitespace() || c == '=' || c == '#')
        .unwrap_or(rest.len());
    let name = &rest[..name_end];
    if rest[name_end..].trim_start().starts_with('=') {
        return Ok(None);
    }
    if name.is_empty() {
        return Err(format!("'{line}' has no field name"));
    }
    let (base, array) = match ty.split_once('[') {
        None => (ty, Array::No),
        Some((base, n)) => {
            let n = n
                .strip_suffix(']')
                .ok_or_else(|| format!("bad array type '{ty}'"))?;
            if n.is_empty() {
                (base, Array::Var)
            } else {
                let n: usize = n.parse().map_err(|_| format!("bad array size in '{ty}'"))?;
                (base, Array::Fixed(n))
            }
        }
    };
    let ty = match Prim::parse(base) {
        Some(p) => FieldType::Prim(p),
        None if base == "Header" => FieldType::Msg("std_msgs/Header".into()),
        None if base.contains('/') => FieldType::Msg(short_name(base)),
        None if base.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') && !base.is_empty() => {
            FieldType::Msg(format!("{package}/{base}"))
        }
        None => return Err(format!("bad type '{base}'")),
    };
    Ok(Some(Field {
        name: name.to_string(),
        ty,
        array,
    }))
}

/// A bounds-checked little-endian cursor over ROS 1 bytes.
struct Reader<'a> {
    b: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn left(&self) -> usize {
        self.b.len() - self.pos
    }

    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], String> {
        if n > self.left() {
            return Err(format!(
                "{what}: needs {n} bytes, {} left (truncated message)",
                self.left()
            ));
        }
        let s = &self.b[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    fn u32(&mut self, what: &str) -> Result<u32, String> {
        let b = self.take(4, what)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ingest::ros::{self, PointField, RosMessage};

    const HEADER: &str = "uint32 seq\ntime stamp\nstring frame_id\n";

    fn pc2_definition() -> String {
        let sep = "=".repeat(80);
        format!(
            "# comment\nHeader header\nuint32 height\nuint32 width\nPointField[] fields\nbool is_bigendian\n\
             uint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n{sep}\nMSG: std_msgs/Header\n\
             {HEADER}{sep}\nMSG: sensor_msgs/PointField\nuint8 INT8    = 1\nuint8 FLOAT32 = 7\n\
             string name\nuint32 offset\nuint8 datatype\nuint32 count\n"
        )
    }

    struct W(Vec<u8>);
    impl W {
        fn u32(&mut self, v: u32) -> &mut Self {
            self.0.extend_from_slice(&v.to_le_bytes());
            self
        }
        fn u8(&mut self, v: u8) -> &mut Self {
            self.0.push(v);
            self
        }
        fn s(&mut self, s: &str) -> &mut Self {
            self.u32(s.len() as u32);
            self.0.extend_from_slice(s.as_bytes());
            self
        }
    }

    /// A ROS 1 PointCloud2 with two xyz points, written by hand from the ROS 1 serialisation rules.
    fn pc2_ros1() -> Vec<u8> {
        let mut w = W(Vec::new());
        w.u32(7).u32(12).u32(500).s("velo"); // header: seq, stamp, frame_id
        w.u32(1).u32(2).u32(3); // height, width, 3 fields
        for (i, n) in ["x", "y", "z"].iter().enumerate() {
            w.s(n).u32(4 * i as u32).u8(7).u32(1);
        }
        w.u8(0).u32(12).u32(24).u32(24);
        for v in [1.0f32, 2.0, 3.0, -1.0, -2.0, -3.0] {
            w.0.extend_from_slice(&v.to_le_bytes());
        }
        w.u8(1);
        w.0
    }

    #[test]
    fn pointcloud2_transcodes_to_the_cdr_our_decoder_reads() {
        let def = Definition::parse("sensor_msgs/PointCloud2", &pc2_definition()).unwrap();
        let cdr = def.to_cdr(&pc2_ros1()).unwrap();
        let Some(Ok(RosMessage::PointCloud2(pc))) =
            ros::decode("sensor_msgs/msg/PointCloud2", &cdr)
        else {
            panic!("not decoded");
        };
        assert_eq!(pc.header.stamp.sec, 12);
        assert_eq!(pc.header.stamp.nanosec, 500);
        assert_eq!(pc.header.frame_id, "velo");
        assert_eq!((pc.height, pc.width, pc.point_step), (1, 2, 12));
        assert_eq!(pc.fields[1], PointField::new("y", 4, 7));
        assert_eq!(pc.data.len(), 24);
        assert!(pc.is_dense);
        // Byte-identical to our own CDR encoder's output for the same message.
        assert_eq!(cdr, pc.encode());
    }

    #[test]
    fn damaged_messages_and_definitions_are_errors_not_panics() {
        let def = Definition::parse("sensor_msgs/PointCloud2", &pc2_definition()).unwrap();
        let msg = pc2_ros1();
        for cut in 0..msg.len() {
            assert!(def.to_cdr(&msg[..cut]).is_err(), "cut at {cut}");
        }
        let mut long = msg.clone();
        long.push(0);
        assert!(def.to_cdr(&long).unwrap_err().contains("left after"));
        // A huge array count is refused before any work.
        let mut huge = msg.clone();
        huge[28..32].copy_from_slice(&u32::MAX.to_le_bytes()); // the fields count, after header, height, width
        let e = def.to_cdr(&huge).unwrap_err();
        assert!(e.contains("do not fit"), "{e}");
        // A type that is used but not defined, and a cycle.
        let e = Definition::parse("a/B", "C c\n").unwrap_err();
        assert!(e.contains("a/C"), "{e}");
        let sep = "=".repeat(80);
        let e = Definition::parse("a/B", &format!("C c\n{sep}\nMSG: a/C\nB b\n")).unwrap_err();
        assert!(e.contains("nest"), "{e}");
        assert!(Definition::parse("a/B", "uint8[x] v\n").is_err());
        assert!(Definition::parse("nopackage", "uint8 v\n").is_err());
    }

    #[test]
    fn constants_comments_and_package_relative_types_parse() {
        let sep = "=".repeat(80);
        let text = format!(
            "string NAME=a # b = c\nint32 X = 3 # comment\nPoint p # the point\nfloat64[3] v\n\
             {sep}\nMSG: geo/Point\nfloat64 x\n"
        );
        let def = Definition::parse("geo/msg/Thing", &text).unwrap();
        assert_eq!(def.root(), "geo/Thing");
        let f = &def.types["geo/Thing"];
        assert_eq!(f.len(), 2);
        assert_eq!(f[0].ty, FieldType::Msg("geo/Point".into()));
        assert_eq!(f[1].array, Array::Fixed(3));
        let mut b = Vec::new();
        for v in [1.0f64, 2.0, 3.0, 4.0] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        let cdr = def.to_cdr(&b).unwrap();
        assert_eq!(&cdr[4..], &b[..]);
    }
}
