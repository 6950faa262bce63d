//! Hostile sizes in the browser, through the code paths the worker runs: a PLY claiming 2^31 vertices in
//! 1 KB opened as a layer (`studio::parse_layer`, what a dropped or fetched cloud goes through), a tar
//! whose entry claims a terabyte read as a training dataset (`Files::from_tar`, what a dropped or fetched
//! submap archive goes through) and an `.npz` claiming 10 GB (the core's reader, built for wasm32). Each
//! must be an error naming the file while the worker's wasm memory grows by less than [`BOUND`] — a
//! wasm32 heap that runs out aborts the worker, which the studio promises never happens.
//!
//! The native side of the same checks, with an exact peak: `core/tests/bounded_alloc.rs`. Runs with the
//! browser tests (`scripts/browser-tests.sh`); no GPU needed.
#![cfg(target_arch = "wasm32")]

use silvr_core::ingest::npz;
use silvr_core::source::Files;
use silvr_worker::studio::parse_layer;
use wasm_bindgen_test::*;

wasm_bindgen_test_configure!(run_in_dedicated_worker);

/// Most the wasm memory may grow while one hostile input is refused.
const BOUND: usize = 64 << 20;

/// The wasm memory's size in bytes (it only ever grows: a peak of the heap).
fn memory_bytes() -> usize {
    core::arch::wasm32::memory_size(0) * 65536
}

/// Runs `f`, asserts it failed with an error naming `names`, and that memory grew by less than [`BOUND`].
fn assert_refused<T, E: std::fmt::Display>(
    what: &str,
    names: &str,
    f: impl FnOnce() -> Result<T, E>,
) {
    let before = memory_bytes();
    let result = f();
    let grew = memory_bytes() - before;
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
        "{what}: wasm memory grew by {} MiB (bound {} MiB) before: {e}",
        grew >> 20,
        BOUND >> 20
    );
}

#[wasm_bindgen_test]
fn a_ply_claiming_2_31_vertices_is_refused_within_the_bound() {
    let ply = |count: usize| {
        format!(
            "ply\nformat binary_little_endian 1.0\nelement vertex {count}\nproperty float x\n\
             property float y\nproperty float z\nproperty float log_std_combined\nend_header\n"
        )
        .into_bytes()
    };
    let mut claims = ply(1 << 31);
    claims.resize(1024, 0);
    assert_refused("2^31 vertices", "claims.ply", || {
        parse_layer(&claims, "claims.ply", "file:claims.ply", 0).map(|_| ())
    });
    // 2^25 vertices (512 MiB of these four floats) is a reservation wasm32 could make: only the bound by
    // the bytes left refuses it before memory grows (2^31 alone would fail `try_reserve` on wasm32 anyway).
    let mut claims = ply(1 << 25);
    claims.resize(1024, 0);
    assert_refused("2^25 vertices", "claims25.ply", || {
        parse_layer(&claims, "claims25.ply", "file:claims25.ply", 0).map(|_| ())
    });
    // Not a reader that refuses everything: the count those bytes hold opens.
    let mut fits = ply(50);
    fits.resize(fits.len() + 16 * 50, 0);
    assert_eq!(
        parse_layer(&fits, "fits.ply", "", 0).unwrap().info.total,
        50
    );
}

#[wasm_bindgen_test]
fn a_tar_entry_claiming_a_terabyte_is_refused_within_the_bound() {
    // A GNU header: name, mode, sizes in base-256 (1 TiB), checksum.
    let mut h = [0u8; 512];
    h[..15].copy_from_slice(b"transforms.json");
    h[100..107].copy_from_slice(b"0000644");
    h[124] = 0x80; // base-256: the other 11 bytes are the size, big-endian
    h[130] = 0x01; // 1 << 40
    h[156] = b'0';
    h[257..265].copy_from_slice(b"ustar  \0");
    h[148..156].fill(b' ');
    let sum: u32 = h.iter().map(|&b| b as u32).sum();
    h[148..155].copy_from_slice(format!("{sum:06o}\0").as_bytes());
    let mut tar = h.to_vec();
    tar.extend_from_slice(b"{\"frames\": []}");
    tar.resize(4096, 0);
    assert_refused("1 TiB entry", "huge.tar", || {
        Files::from_tar("huge.tar", tar).and_then(Files::rooted_at_transforms)
    });
}

/// A single-entry zip holding `data` with `method` (0 stored, 8 deflated), declaring `declared` bytes.
fn zip(data: &[u8], method: u16, declared: u32) -> Vec<u8> {
    let name = b"data.npy";
    let mut z = b"PK\x03\x04\x14\0\0\0".to_vec();
    z.extend_from_slice(&method.to_le_bytes());
    z.extend_from_slice(&[0; 8]);
    z.extend_from_slice(&(data.len() as u32).to_le_bytes());
    z.extend_from_slice(&declared.to_le_bytes());
    z.extend_from_slice(&(name.len() as u16).to_le_bytes());
    z.extend_from_slice(&[0; 2]);
    z.extend_from_slice(name);
    z.extend_from_slice(data);
    let cd = z.len();
    z.extend_from_slice(b"PK\x01\x02\x14\0\x14\0\0\0");
    z.extend_from_slice(&method.to_le_bytes());
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

#[wasm_bindgen_test]
fn an_npz_claiming_10_gb_is_refused_within_the_bound() {
    // A .npy header of 1.25e9 float64s (10 GB) and no data.
    let mut h = "{'descr': '<f8', 'fortran_order': False, 'shape': (1250000000,), }".to_string();
    while !(10 + h.len() + 1).is_multiple_of(64) {
        h.push(' ');
    }
    h.push('\n');
    let mut npy = b"\x93NUMPY\x01\x00".to_vec();
    npy.extend_from_slice(&(h.len() as u16).to_le_bytes());
    npy.extend_from_slice(h.as_bytes());
    // Stored, declaring what is there: the shape needs more than the bytes present.
    let stored = zip(&npy, 0, npy.len() as u32);
    assert_refused("10 GB by shape, stored", "shape.npz/data.npy", || {
        npz::parse_npz(&stored, "data", "shape.npz")
    });
    // Deflated as one stored deflate block, declaring 1 KB: the shape needs more than declared.
    let mut block = vec![1u8];
    block.extend_from_slice(&(npy.len() as u16).to_le_bytes());
    block.extend_from_slice(&(!(npy.len() as u16)).to_le_bytes());
    block.extend_from_slice(&npy);
    let small = zip(&block, 8, 1000);
    assert_refused("10 GB by shape, deflated", "small.npz/data.npy", || {
        npz::parse_npz(&small, "data", "small.npz")
    });
    // Declaring 4 GiB uncompressed: refused before anything is inflated.
    let declared = zip(&block, 8, u32::MAX);
    assert_refused("4 GiB declared", "declared.npz/data.npy", || {
        npz::parse_npz(&declared, "data", "declared.npz")
    });
}
