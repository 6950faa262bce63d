//! Hostile sizes natively: a PLY claiming 2^31 vertices in 1 KB, an `.npz` claiming 10 GB (by its zip
//! entry's declared size, by its `.npy` shape, and as a zip bomb) and a tar entry claiming terabytes are
//! each refused with an error naming the file, while the heap stays below [`BOUND`]: this test binary's
//! global allocator records the peak of live bytes while each input is read.
//!
//! The same inputs go through the worker's code paths in the browser in `worker/tests/bounded_wasm.rs`.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};
use std::sync::Mutex;

use silvr_core::ingest::npz;
use silvr_core::pointcloud;
use silvr_core::source::Files;

/// Most the heap may grow while one hostile input is refused.
const BOUND: usize = 64 << 20;

struct Counting;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            let live = LIVE.fetch_add(layout.size(), Relaxed) + layout.size();
            PEAK.fetch_max(live, Relaxed);
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) };
        LIVE.fetch_sub(layout.size(), Relaxed);
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            if new_size >= layout.size() {
                let live =
                    LIVE.fetch_add(new_size - layout.size(), Relaxed) + new_size - layout.size();
                PEAK.fetch_max(live, Relaxed);
            } else {
                LIVE.fetch_sub(layout.size() - new_size, Relaxed);
            }
        }
        p
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// One measurement at a time (the test harness runs tests on several threads).
static SERIAL: Mutex<()> = Mutex::new(());

/// Runs `f` and returns its result and how far the heap grew above where it was when `f` started.
fn peak_growth<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let _one = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let base = LIVE.load(Relaxed);
    PEAK.store(base, Relaxed);
    let out = f();
    (out, PEAK.load(Relaxed).saturating_sub(base))
}

fn assert_refused<E: std::fmt::Display>(
    what: &str,
    r: (Result<impl Sized, E>, usize),
    names: &str,
) {
    let (result, grew) = r;
    let e = match result {
        Ok(_) => panic!("{what}: accepted"),
        Err(e) => e.to_string(),
    };
    assert!(
        e.contains(names),
        "{what}: the error does not name {names}: {e}"
    );
    assert!(
        grew < BOUND,
        "{what}: the heap grew by {} MiB (bound {} MiB) before: {e}",
        grew >> 20,
        BOUND >> 20
    );
    eprintln!(
        "{what}: refused with the heap {} KiB higher: {e}",
        grew >> 10
    );
}

/// A binary PLY header claiming `count` vertices of `props` (`float x`, …), then `pad` zero bytes.
fn ply(count: u64, props: &[&str], pad: usize) -> Vec<u8> {
    let mut b = format!("ply\nformat binary_little_endian 1.0\nelement vertex {count}\n");
    for p in props {
        b.push_str(&format!("property {p}\n"));
    }
    b.push_str("end_header\n");
    let mut b = b.into_bytes();
    b.resize(b.len() + pad, 0);
    b
}

#[test]
fn a_ply_claiming_2_31_vertices_in_1_kb_is_refused_within_the_bound() {
    let bytes = ply(1 << 31, &["float x", "float y", "float z"], 1024);
    let r = peak_growth(|| pointcloud::read_ply_bytes(&bytes, "claims.ply"));
    assert_refused("2^31 vertices", r, "claims.ply");
    // And in a file on disk (read fallibly, same reader).
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("claims.ply");
    std::fs::write(&path, &bytes).unwrap();
    let r = peak_growth(|| pointcloud::read_ply(&path));
    assert_refused("2^31 vertices, from disk", r, "claims.ply");
    // 2^22 vertices (100 MB of positions, which the allocator would grant): refused by the bytes left,
    // not by a failed reservation. Without that bound this case grows the heap past the bound (checked).
    let bytes = ply(1 << 22, &["float x", "float y", "float z"], 1024);
    let r = peak_growth(|| pointcloud::read_ply_bytes(&bytes, "claims.ply"));
    assert_refused("2^22 vertices", r, "claims.ply");
}

/// A PLY whose count the bytes do allow, with one-byte coordinates and sixty unused one-byte
/// properties: read for the studio, only positions are stored (24 bytes a point), not the sixty
/// scalars (240 bytes a point).
#[test]
fn properties_not_asked_for_are_not_stored() {
    let n = 100_000u64;
    let mut props = vec!["uchar x", "uchar y", "uchar z"];
    let names: Vec<String> = (0..60).map(|i| format!("uchar f_rest_{i}")).collect();
    props.extend(names.iter().map(String::as_str));
    let bytes = ply(n, &props, 63 * n as usize);
    let opts = pointcloud::PlyReadOptions::only(&["log_std_combined"]);
    let (cloud, grew) = peak_growth(|| pointcloud::read_ply_bytes_with(&bytes, "splat.ply", &opts));
    let cloud = cloud.unwrap();
    assert_eq!((cloud.len(), cloud.scalars.len()), (n as usize, 0));
    assert!(grew < 4 << 20, "the heap grew by {} KiB", grew >> 10);
    // Everything, for comparison: the sixty scalars are there and cost what they cost.
    let (all, grew_all) = peak_growth(|| pointcloud::read_ply_bytes(&bytes, "splat.ply"));
    assert_eq!(all.unwrap().scalars.len(), 60);
    assert!(grew_all > 24 << 20, "{} KiB", grew_all >> 10);
}

/// A single-entry zip of `data` (deflated) that declares `declared` bytes uncompressed.
fn npz(data: &[u8], declared: u32) -> Vec<u8> {
    let name = b"data.npy";
    let mut z = b"PK\x03\x04\x14\0\0\0\x08\0".to_vec();
    z.extend_from_slice(&[0; 8]);
    z.extend_from_slice(&(data.len() as u32).to_le_bytes());
    z.extend_from_slice(&declared.to_le_bytes());
    z.extend_from_slice(&(name.len() as u16).to_le_bytes());
    z.extend_from_slice(&[0; 2]);
    z.extend_from_slice(name);
    z.extend_from_slice(data);
    let cd = z.len();
    z.extend_from_slice(b"PK\x01\x02\x14\0\x14\0\0\0\x08\0");
    z.extend_from_slice(&[0; 8]);
    z.extend_from_slice(&(data.len() as u32).to_le_bytes());
    z.extend_from_slice(&declared.to_le_bytes());
    z.extend_from_slice(&(name.len() as u16).to_le_bytes());
    z.extend_from_slice(&[0; 16]);
    z.extend_from_slice(name);
    let cd_len = z.len() - cd;
    z.extend_from_slice(b"PK\x05\x06\0\0\0\0\x01\0\x01\0");
    z.extend_from_slice(&(cd_len as u32).to_le_bytes());
    z.extend_from_slice(&(cd as u32).to_le_bytes());
    z.extend_from_slice(&[0; 2]);
    z
}

/// An `.npy` header of `shape` float64s (no data).
fn npy_header(shape: &str) -> Vec<u8> {
    let mut h = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': {shape}, }}");
    while !(10 + h.len() + 1).is_multiple_of(64) {
        h.push(' ');
    }
    h.push('\n');
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend_from_slice(&(h.len() as u16).to_le_bytes());
    b.extend_from_slice(h.as_bytes());
    b
}

/// The raw deflate stream of `head` followed by `zeros_mib` MiB of zeros, built a MiB at a time.
fn deflate_bomb(head: &[u8], zeros_mib: usize) -> Vec<u8> {
    use std::io::Write;
    let mut e = flate2::write::DeflateEncoder::new(Vec::new(), flate2::Compression::best());
    e.write_all(head).unwrap();
    let zeros = vec![0u8; 1 << 20];
    for _ in 0..zeros_mib {
        e.write_all(&zeros).unwrap();
    }
    e.finish().unwrap()
}

#[test]
fn an_npz_claiming_10_gb_is_refused_within_the_bound() {
    // 10 GB by its shape (1.25e9 float64s), in an entry that declares 1 KB and really inflates to 256 MiB.
    let header = npy_header("(1250000000,)");
    let bomb = npz(&deflate_bomb(&header, 256), 1000);
    let r = peak_growth(|| npz::parse_npz(&bomb, "data", "shape.npz"));
    assert_refused("10 GB by shape", r, "shape.npz/data.npy");
    // The same stream declaring its full 4 GiB: refused before inflating.
    let big = npz(&deflate_bomb(&header, 256), u32::MAX);
    let r = peak_growth(|| npz::parse_npz(&big, "data", "declared.npz"));
    assert_refused("4 GiB declared", r, "declared.npz/data.npy");
    // A 1 GB shape declared honestly (under the 4 GiB a zip entry can declare, over the cap).
    let header = npy_header("(134217728, 2)");
    let honest = npz(&deflate_bomb(&header, 256), (2 << 30) + header.len() as u32);
    let r = peak_growth(|| npz::parse_npz(&honest, "data", "honest.npz"));
    assert_refused("2 GiB declared and shaped", r, "honest.npz/data.npy");
}

#[test]
fn a_tar_entry_claiming_terabytes_is_refused_within_the_bound() {
    let mut h = tar::Header::new_gnu();
    h.set_path("transforms.json").unwrap();
    h.set_size(1 << 40);
    h.set_mode(0o644);
    h.set_entry_type(tar::EntryType::Regular);
    h.set_cksum();
    let mut bytes = h.as_bytes().to_vec();
    bytes.extend_from_slice(b"{\"frames\": []}");
    bytes.resize(4096, 0);
    let r = peak_growth(|| Files::from_tar("huge.tar", bytes));
    assert_refused("1 TiB entry", r, "huge.tar");
}
