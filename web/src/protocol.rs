//! How the page words what the worker sends. The messages themselves are the worker's types
//! (`silvr_worker::{FromPage, ToPage}`), defined once for both sides.

#![cfg_attr(not(target_arch = "wasm32"), allow(dead_code))]

use silvr_worker::Stage;

/// `1234567` → `"1,234,567"`.
pub fn group_digits(n: u64) -> String {
    let s = n.to_string();
    let mut out = String::with_capacity(s.len() + s.len() / 3);
    for (i, c) in s.chars().enumerate() {
        if i > 0 && (s.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}

/// A file size for people: exact bytes, and a binary-prefixed approximation above 1 KiB.
pub fn describe_size(bytes: u64) -> String {
    let exact = format!(
        "{} {}",
        group_digits(bytes),
        if bytes == 1 { "byte" } else { "bytes" }
    );
    const UNITS: [&str; 4] = ["KiB", "MiB", "GiB", "TiB"];
    if bytes < 1024 {
        return exact;
    }
    let mut v = bytes as f64 / 1024.0;
    let mut unit = 0;
    while v >= 1024.0 && unit + 1 < UNITS.len() {
        v /= 1024.0;
        unit += 1;
    }
    format!("{exact} ({v:.1} {})", UNITS[unit])
}

/// What a worker error means for someone looking at the page (one or two sentences; the worker's
/// technical detail is shown separately).
pub fn explain_error(stage: Stage, message: &str) -> String {
    match stage {
        Stage::Webgpu => "SiLVR Studio needs WebGPU, and this browser offers no usable adapter. Use a recent \
                     Chrome or Edge (or Chromium with --enable-unsafe-webgpu), or Firefox or Safari with \
                     WebGPU enabled."
            .to_string(),
        Stage::Panic => format!("The engine worker crashed; reload the page. ({message})"),
        _ => capitalize(message),
    }
}

/// `"the kernel"` → `"The kernel"`.
pub fn capitalize(s: &str) -> String {
    let mut c = s.chars();
    match c.next() {
        Some(first) => first.to_uppercase().chain(c).collect(),
        None => String::new(),
    }
}

#[cfg(all(test, not(target_arch = "wasm32")))]
mod tests {
    use super::*;
    use silvr_worker::ToPage;

    #[test]
    fn sizes_are_exact_and_readable() {
        assert_eq!(describe_size(0), "0 bytes");
        assert_eq!(describe_size(1), "1 byte");
        assert_eq!(describe_size(1023), "1,023 bytes");
        assert_eq!(describe_size(100_000), "100,000 bytes (97.7 KiB)");
        assert_eq!(describe_size(5 << 30), "5,368,709,120 bytes (5.0 GiB)");
        assert_eq!(group_digits(999), "999");
        assert_eq!(group_digits(1_000), "1,000");
        assert_eq!(group_digits(12_345_678), "12,345,678");
    }

    #[test]
    fn run_check_request_is_tagged() {
        let v = serde_json::to_value(silvr_worker::FromPage::RunCheck {
            id: Some(3),
            n: Some(20_000),
            seed: Some(3),
        })
        .unwrap();
        assert_eq!(v["type"], "run-check");
        assert_eq!(v["id"], 3);
        assert_eq!(v["n"], 20_000);
    }

    #[test]
    fn errors_read_well() {
        assert!(explain_error(Stage::Webgpu, "x").contains("needs WebGPU"));
        assert_eq!(
            explain_error(Stage::Projection, "the kernel failed"),
            "The kernel failed"
        );
    }

    #[test]
    fn worker_messages_parse() {
        let m: ToPage = serde_json::from_str(
            r#"{"type":"adapter","adapter":{"name":"SwiftShader","backend":"BrowserWebGpu",
                "device_type":"Cpu","driver":"","driver_info":"","software":true,
                "max_storage_buffer_binding_size":1073741824,"max_buffer_size":1073741824,
                "max_compute_workgroup_storage_size":32768,"max_compute_invocations_per_workgroup":256}}"#,
        )
        .unwrap();
        assert!(matches!(m, ToPage::Adapter { adapter, browser: None } if adapter.software));
        let m: ToPage = serde_json::from_str(
            r#"{"type":"projection","id":null,"seed":7,"n":4000,"elapsed_ms":12,"passed":true,
                "check":{"points":4000,"pixels":97200,"filled_pixels":3000,"winner_mismatches":0,
                "max_uv_error_px":0.0001,"max_range_rel_error":1e-7}}"#,
        )
        .unwrap();
        assert!(matches!(m, ToPage::Projection { passed: true, .. }));
    }
}
