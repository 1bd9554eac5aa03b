//! `lmac bench learner` end to end on a small shape: the report has a figure per mixer for the
//! fused recurrence and burn's per-step cell, FLOPs that grow with the mixer, the phases of an
//! update with `--profile`; a missing PyTorch anchor and an unknown shape are clear errors.

use lmac_e2e::harness::lmac;

#[test]
fn the_learner_bench_reports_each_mixer_and_refuses_what_it_cannot_run() {
    let out = lmac()
        .args(["bench", "learner", "--shape", "lbf8x8", "--batch", "4", "--steps", "5", "--state", "20"])
        .args(["--rounds", "1", "--updates", "1", "--profile", "--json"])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let figures = v["figures"].as_array().unwrap();
    for mixer in ["qmix", "vdn", "qplex"] {
        for name in ["lmac", "lmac-stepwise"] {
            let f = figures.iter().find(|f| f["mixer"] == mixer && f["name"] == name).unwrap_or_else(|| panic!("no {name} {mixer} figure"));
            assert!(f["median_ms"].as_f64().unwrap() > 0.0 && f["gflops"].as_f64().unwrap() > 0.0, "{f}");
        }
    }
    let gflop = |m: &str| v["flops"].as_array().unwrap().iter().find(|f| f["mixer"] == m).unwrap()["gflop_per_update"].as_f64().unwrap();
    assert!(gflop("vdn") < gflop("qmix") && gflop("qmix") < gflop("qplex"), "{}", v["flops"]);
    let phases = v["profiles"][0]["phases_ms"].as_array().unwrap();
    assert!(phases.iter().any(|p| p["phase"] == "backward"), "{phases:?}");
    assert_eq!(v["shape"]["batch"], 4);
    // the FLOPs are those of the shape given (4 episodes x 5 steps), not of the default batch
    let small = gflop("vdn");
    let big = lmac()
        .args([
            "bench",
            "learner",
            "--batch",
            "8",
            "--steps",
            "5",
            "--state",
            "20",
            "--mixers",
            "vdn",
            "--rounds",
            "1",
            "--updates",
            "1",
            "--no-stepwise",
            "--json",
        ])
        .output()
        .unwrap();
    assert!(big.status.success(), "{}", String::from_utf8_lossy(&big.stderr));
    let big: serde_json::Value = serde_json::from_slice(&big.stdout).unwrap();
    let ratio = big["flops"][0]["gflop_per_update"].as_f64().unwrap() / small;
    assert!((ratio - 2.0).abs() < 1e-9, "twice the episodes, {ratio}x the FLOPs");

    let missing = lmac()
        .args(["bench", "learner", "--mixers", "vdn", "--rounds", "1", "--updates", "1", "--no-stepwise", "--against", "torch"])
        .args(["--python", "/nonexistent/python"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&missing.stderr);
    assert!(!missing.status.success() && err.contains("benches/torch/setup.sh"), "{err}");

    let bad = lmac().args(["bench", "learner", "--shape", "nope"]).output().unwrap();
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(!bad.status.success() && err.contains("unknown shape"), "{err}");
}
