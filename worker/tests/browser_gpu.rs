//! The engine's GPU code inside a real browser: WebGPU in a dedicated Worker of headless Chromium
//! (SwiftShader), the way the studio runs it.
//!
//! ```text
//! CARGO_TARGET_WASM32_UNKNOWN_UNKNOWN_RUNNER=wasm-bindgen-test-runner CHROMEDRIVER=/usr/bin/chromedriver \
//!   cargo test -p silvr-worker --target wasm32-unknown-unknown
//! ```
//! Chromium's WebGPU flags come from `worker/webdriver.json`; without them no adapter is found and these fail.
#![cfg(target_arch = "wasm32")]

use silvr_core::camera::{CameraModel, Distortion};
use silvr_core::gpu::{Gpu, GpuOptions};
use silvr_core::lidar::project;
use silvr_worker::{check_camera, handle, FromPage, ToPage};
use wasm_bindgen_test::*;

wasm_bindgen_test_configure!(run_in_dedicated_worker);

async fn gpu() -> Gpu {
    // Poison output buffers so a kernel that skips an element cannot hide behind zeroed memory.
    Gpu::new(GpuOptions {
        poison: Some(0xDEAD_BEEF),
        ..Default::default()
    })
    .await
    .unwrap_or_else(|e| {
        panic!("no WebGPU device in the worker (are the webdriver.json flags set?): {e}")
    })
}

#[wasm_bindgen_test]
async fn adapter_found_and_fisheye_projection_matches_cpu() {
    let gpu = gpu().await;
    let report = gpu.report();
    assert!(!report.name.is_empty(), "{report:?}");
    assert_eq!(report.backend, "BrowserWebGpu", "{report:?}");
    assert!(
        report.max_compute_invocations_per_workgroup >= 256,
        "{report:?}"
    );

    let check = project::self_check(&gpu, &check_camera(), 7, 4000)
        .await
        .unwrap();
    assert_eq!(check.winner_mismatches, 0, "{check:?}");
    assert!(check.filled_pixels > 0, "{check:?}");
    assert_eq!(check.points, 4000, "{check:?}");
    assert!(check.passed(), "{check:?}");
}

#[wasm_bindgen_test]
async fn radtan_pinhole_projection_matches_cpu() {
    let gpu = gpu().await;
    let camera = CameraModel {
        width: 200,
        height: 150,
        fx: 160.0,
        fy: 158.5,
        cx: 101.3,
        cy: 74.6,
        distortion: Distortion::RadTan {
            k1: -0.28,
            k2: 0.07,
            p1: 1e-3,
            p2: -2e-3,
            k3: 0.01,
        },
    };
    let check = project::self_check(&gpu, &camera, 1234, 6000)
        .await
        .unwrap();
    assert_eq!(check.winner_mismatches, 0, "{check:?}");
    assert!(check.filled_pixels > 0, "{check:?}");
    assert!(check.passed(), "{check:?}");

    // And a plain pinhole with an odd size.
    let camera = CameraModel::pinhole(97, 61, 80.0, 82.0, 48.3, 30.1);
    let check = project::self_check(&gpu, &camera, 99, 3000).await.unwrap();
    assert_eq!(check.winner_mismatches, 0, "{check:?}");
    assert!(check.passed(), "{check:?}");
}

#[wasm_bindgen_test]
async fn worker_protocol_answers_run_check() {
    let gpu = gpu().await;
    let msg = FromPage::RunCheck {
        id: Some(5),
        n: Some(1500),
        seed: Some(21),
    };
    match handle(&gpu, msg).await {
        ToPage::Projection {
            id,
            n,
            seed,
            passed,
            check,
            ..
        } => {
            assert_eq!((id, n, seed), (Some(5), 1500, 21));
            assert!(passed, "{check:?}");
        }
        other => panic!("expected a projection message, got {other:?}"),
    }
    // Oversized requests are refused with an error message, not attempted.
    let msg = FromPage::RunCheck {
        id: Some(6),
        n: Some(silvr_worker::MAX_CHECK_POINTS + 1),
        seed: None,
    };
    assert!(matches!(
        handle(&gpu, msg).await,
        ToPage::Error { id: Some(6), .. }
    ));
}
