//! `silvr reconstruct --scheduler slurm` on a real (one-node) Slurm, after the poses stage: one array of
//! submap tasks, the same merged map as the local scheduler's (the poses stage is deterministic too), and
//! a task killed mid-run (`scancel`) reported with its log and resubmitted alone on the rerun, which ends
//! with the same merged map. `scripts/test.sh` starts a private
//! one-node Slurm (`scripts/slurm.sh up`, as root: its own config, munge, ports and state), points
//! `SLURM_CONF` at it and sets `SILVR_REQUIRE_SLURM=1`. The test uses no other Slurm: where `SLURM_CONF`
//! does not name a config that `scripts/slurm.sh` wrote (a cluster's, or none), it skips (or fails, with
//! `SILVR_REQUIRE_SLURM=1`) and submits nothing. Submaps train on the CPU reference (`--backend cpu`,
//! asserted per submap): bit-for-bit reproducible, which the equality needs; this checks scheduling, not
//! the engine.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use silvr_tests::build_silvr;

fn ok(args: &[&str]) -> String {
    let out = Command::new(build_silvr()).args(args).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "silvr {args:?}: {err}");
    err
}

fn json(p: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap()
}

/// The first line of every slurm.conf that `scripts/slurm.sh up` writes.
const MARK: &str = "# SiLVR Studio scripts/slurm.sh: a private one-node Slurm";

/// The private Slurm of `scripts/slurm.sh` that `slurm_conf` (the value of `SLURM_CONF`) names, answering;
/// otherwise why not. A config without the script's first line is a Slurm this test did not start (a
/// cluster's): it is never used.
fn our_slurm(slurm_conf: Option<std::ffi::OsString>) -> Result<(), String> {
    let conf = slurm_conf.ok_or(
        "SLURM_CONF is unset: no Slurm of scripts/slurm.sh here (`scripts/slurm.sh up` starts a \
         one-node one as root; a cluster's Slurm is never used)",
    )?;
    let conf = Path::new(&conf);
    let text =
        std::fs::read_to_string(conf).map_err(|e| format!("SLURM_CONF={}: {e}", conf.display()))?;
    if !text.starts_with(MARK) {
        return Err(format!(
            "SLURM_CONF={} was not written by scripts/slurm.sh: a Slurm the tests did not start is \
             not used",
            conf.display()
        ));
    }
    let answers = Command::new("sinfo")
        .arg("-h")
        .env("SLURM_CONF", conf)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if !answers {
        return Err(format!(
            "the Slurm of SLURM_CONF={} does not answer (sinfo)",
            conf.display()
        ));
    }
    Ok(())
}

/// A cluster's configuration (anything `scripts/slurm.sh` did not write) is refused before any Slurm
/// command runs, as is an unset `SLURM_CONF`.
#[test]
fn a_slurm_the_tests_did_not_start_is_not_used() {
    let tmp = tempfile::tempdir().unwrap();
    let conf = tmp.path().join("slurm.conf");
    std::fs::write(&conf, "ClusterName=production\nSlurmctldHost=head\n").unwrap();
    let err = our_slurm(Some(conf.clone().into())).unwrap_err();
    assert!(err.contains("not written by scripts/slurm.sh"), "{err}");
    assert!(our_slurm(None).unwrap_err().contains("SLURM_CONF is unset"));
    // Marked as the script's, the check goes on to ask it (nothing answers at this path).
    std::fs::write(&conf, format!("{MARK}; ...\nClusterName=silvr-ci\n")).unwrap();
    let err = our_slurm(Some(conf.into())).unwrap_err();
    assert!(err.contains("does not answer"), "{err}");
}

#[test]
fn slurm_array_equals_local_and_a_killed_task_is_resubmitted() {
    if let Err(why) = our_slurm(std::env::var_os("SLURM_CONF")) {
        silvr_tests::skip("SILVR_REQUIRE_SLURM", &why);
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("micro");
    let d = data.to_str().unwrap();
    ok(&["synth", "--preset", "micro", "--seed", "2", "--out", d]);
    let run = |out: &Path, scheduler: &str| -> Vec<String> {
        [
            "reconstruct",
            d,
            "--out",
            out.to_str().unwrap(),
            "--count",
            "3",
            "--model",
            "tiny",
            "--steps",
            "300",
            "--rays",
            "256",
            "--backend",
            "cpu",
            "--export-rays",
            "4096",
            "--uncertainty-batches",
            "1",
            "--renders",
            "2",
            "--scheduler",
            scheduler,
            "--jobs",
            "2",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect()
    };
    fn args(v: &[String]) -> Vec<&str> {
        v.iter().map(String::as_str).collect()
    }

    // The local scheduler, two child tasks at once.
    let local = tmp.path().join("local");
    ok(&args(&run(&local, "local")));

    // Slurm: submitted as one array; task 1 cancelled while it runs.
    let out = tmp.path().join("slurm");
    let argv = run(&out, "slurm");
    let child = Command::new(build_silvr())
        .args(&argv)
        .stderr(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    let t = Instant::now();
    let job = loop {
        assert!(t.elapsed() < Duration::from_secs(120), "no job submitted");
        if let Ok(b) = std::fs::read(out.join("slurm/submitted.json")) {
            let v: serde_json::Value = serde_json::from_slice(&b).unwrap();
            break v["job"].as_str().unwrap().to_string();
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let task = format!("{job}_1");
    loop {
        assert!(
            t.elapsed() < Duration::from_secs(300),
            "task {task} never ran"
        );
        let q = Command::new("squeue")
            .args(["-h", "-r", "-j", &job, "-o", "%i %T"])
            .output()
            .unwrap();
        let q = String::from_utf8_lossy(&q.stdout);
        if q.lines().any(|l| l.trim() == format!("{task} RUNNING")) {
            break;
        }
        assert!(
            !out.join("train/submap_01/task.json").exists(),
            "task 1 finished before it could be cancelled: {q}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let cancel = Command::new("scancel").arg(&task).status().unwrap();
    assert!(cancel.success());
    let killed = child.wait_with_output().unwrap();
    let said = String::from_utf8_lossy(&killed.stderr).into_owned();
    assert!(!killed.status.success(), "{said}");
    assert!(
        said.contains(&format!("submap_01 failed as slurm task {task}"))
            && said.contains("CANCELLED")
            && said.contains(&format!("logs/slurm-{task}.out")),
        "{said}"
    );
    assert!(said.contains("1 of 3 submaps failed (submap_01)"), "{said}");
    let report = json(&out.join("report.json"));
    assert_eq!(report["failed"][0]["name"], "submap_01", "{report}");
    assert!(!out.join("train/submap_01/task.json").exists());

    // The rerun resubmits only the cancelled task and ends with the local scheduler's map.
    let said = ok(&args(&argv));
    assert!(
        said.contains("submap_00 (1/3): done earlier")
            && said.contains("submap_02 (3/3): done earlier")
            && said.contains(": 1 of 3 submaps (1)"),
        "{said}"
    );
    let report = json(&out.join("report.json"));
    assert!(report["failed"].as_array().unwrap().is_empty(), "{report}");
    // The poses stage ran first (once: the rerun reused it), and the cut used its shared tracks.
    assert_eq!(report["poses"]["registered"], 36, "{report}");
    assert!(said.contains("poses: reusing"), "{said}");
    assert_eq!(report["submaps"]["covis_source"], "tracks", "{report}");
    for s in report["per_submap"].as_array().unwrap() {
        assert_eq!(s["backend"], "cpu", "{s}");
    }
    for f in ["merged.ply", "merged_unfiltered.ply"] {
        assert!(
            std::fs::read(local.join(f)).unwrap() == std::fs::read(out.join(f)).unwrap(),
            "{f} differs between the local and the Slurm run"
        );
    }
    // The blended renders (drawn here from the submaps' checkpoints) agree too: the same views from the
    // same submaps, the same scores (distances to the last bits aside: a rerun reads the poses stage's
    // alignment back from JSON).
    let views = |dir: &Path| -> Vec<String> {
        json(&dir.join("renders/report.json"))["views"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| {
                format!(
                    "{} {} {} {} {} {}",
                    v["name"],
                    v["nearest"],
                    v["second"],
                    v["nearest_only"]["psnr"],
                    v["blended_silvr"]["psnr"],
                    v["blended_idw"]["psnr"]
                )
            })
            .collect()
    };
    assert_eq!(views(&local), views(&out));
    assert_eq!(views(&out).len(), 2, "{report}");
    let job_sh = std::fs::read_to_string(out.join("slurm/job.sh")).unwrap();
    assert!(job_sh.contains("reconstruct-task") && job_sh.contains("#SBATCH --output="));
}
