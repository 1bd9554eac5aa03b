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
    // The shape ceiling lists the very matmuls the FLOP count counts (QMIX and VDN; none for
    // QPLEX), each timed.
    let ceilings = v["shape_ceiling"].as_array().expect("shape_ceiling");
    let mixers: Vec<&str> = ceilings.iter().map(|c| c["mixer"].as_str().unwrap()).collect();
    assert_eq!(mixers, ["qmix", "vdn"], "{}", v["shape_ceiling"]);
    for c in ceilings {
        let matmuls = c["matmuls"].as_array().unwrap();
        let listed: f64 = matmuls
            .iter()
            .map(|m| ["m", "k", "n", "batch", "per_update"].iter().map(|k| m[*k].as_f64().unwrap()).product::<f64>() * 2.0 / 1e9)
            .sum();
        let counted = gflop(c["mixer"].as_str().unwrap());
        assert!((listed - counted).abs() < 1e-9 * counted, "{}: the ceiling lists {listed} GFLOP, the count says {counted}", c["mixer"]);
        assert!(matmuls.iter().all(|m| m["ms_each"].as_f64().unwrap() > 0.0) && c["ms_if_every_matmul_ran_alone"].as_f64().unwrap() > 0.0);
    }
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

/// `--algo` times a method's agent network on the same shape: LMAC's module (more work than
/// the plain agent it wraps, FLOPs counted), every method's FLOPs counted, an algorithm that
/// names its backbone runs on that one only, `--two-cores` adds the update as `--preset paper`
/// runs it, and inputs that do not fit are refused.
#[test]
fn the_learner_bench_times_a_methods_agent_network() {
    let run = |extra: &[&str]| {
        lmac()
            .args(["bench", "learner", "--batch", "4", "--steps", "5", "--state", "20", "--mixers", "vdn"])
            .args(["--rounds", "1", "--updates", "2", "--no-stepwise", "--json"])
            .args(extra)
            .output()
            .unwrap()
    };
    let ok = |out: &std::process::Output| -> serde_json::Value {
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        serde_json::from_slice(&out.stdout).unwrap()
    };
    let plain = ok(&run(&[]));
    let lmac_v = ok(&run(&["--algo", "lmac", "--messages", "10", "--critical", "8", "--method", "encoder=\"gru-gate\""]));
    assert_eq!(lmac_v["method"]["algo"], "lmac");
    assert_eq!(lmac_v["method"]["critical_dims"], 8);
    // LMAC's FLOPs are counted (its module on top of the agent it wraps): more than the plain
    // agent's on the same shape.
    let fig = &lmac_v["figures"][0];
    assert!(fig["gflops"].as_f64().unwrap() > 0.0 && fig["median_ms"].as_f64().unwrap() > 0.0, "{fig}");
    let gflop = |v: &serde_json::Value| v["flops"][0]["gflop_per_update"].as_f64().unwrap();
    assert!(gflop(&lmac_v) > gflop(&plain), "{} vs {}", lmac_v["flops"], plain["flops"]);
    assert!(plain["figures"][0]["gflops"].as_f64().unwrap() > 0.0);
    // Every method's networks on top of the agent are counted.
    let ndq = ok(&run(&["--algo", "ndq"]));
    assert!(ndq["figures"][0]["gflops"].as_f64().unwrap() > 0.0 && gflop(&ndq) > gflop(&plain), "{}", ndq["flops"]);
    let t2mac = ok(&run(&["--algo", "t2mac"]));
    assert!(gflop(&t2mac) > gflop(&plain), "{}", t2mac["flops"]);
    let maic = ok(&run(&["--algo", "maic"]));
    assert!(gflop(&maic) > gflop(&plain), "{}", maic["flops"]);
    for algo in ["masia", "cola"] {
        let v = ok(&run(&["--algo", algo]));
        assert!(v["figures"][0]["gflops"].as_f64().unwrap() > 0.0 && gflop(&v) > gflop(&plain), "{algo}: {}", v["flops"]);
    }

    let two = ok(&run(&["--algo", "lmac", "--messages", "10", "--critical", "8", "--two-cores"]));
    let names: Vec<&str> = two["figures"].as_array().unwrap().iter().map(|f| f["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["lmac", "lmac-two-cores"], "{}", two["figures"]);
    assert!(two["figures"][1]["median_ms"].as_f64().unwrap() > 0.0);
    // LMAC's shape ceiling (window encoder) lists its matmuls: with the window attention's
    // FLOPs (no matmul: per row 2 x 2 x min(W, T) x attention width, in the online forward,
    // twice in the backward and in the target forward), exactly the FLOP count.
    let ceiling = &two["shape_ceiling"][0];
    let listed = ceiling["gflop_of_these_matmuls"].as_f64().unwrap();
    let rows = 4.0 * 5.0 * 2.0; // 4 episodes x 5 steps x 2 agents (lbf8x8)
    let attention = rows * (2.0 * 2.0 * 5.0 * 64.0) * 4.0 / 1e9;
    assert!((listed + attention - gflop(&two)).abs() < 1e-9 * gflop(&two), "{listed} + {attention} vs {}", gflop(&two));
    assert!(
        ceiling["matmuls"].as_array().unwrap().iter().any(|m| m["what"].as_str().unwrap().starts_with("LMAC window q, k, v")),
        "{ceiling}"
    );
    // So does the gru-gate encoder's, whose every counted FLOP is a matmul (the gate's dot
    // product is not counted): exactly the FLOP count.
    let gate = &lmac_v["shape_ceiling"][0];
    let listed = gate["gflop_of_these_matmuls"].as_f64().unwrap();
    assert!((listed - gflop(&lmac_v)).abs() < 1e-9 * gflop(&lmac_v), "{listed} vs {}", gflop(&lmac_v));
    assert!(
        gate["matmuls"].as_array().unwrap().iter().any(|m| m["what"].as_str().unwrap().starts_with("LMAC encoder GRU hidden")),
        "{gate}"
    );

    let fixed = ok(&run(&["--algo", "qplex"]));
    let mixers: Vec<&str> = fixed["figures"].as_array().unwrap().iter().map(|f| f["mixer"].as_str().unwrap()).collect();
    assert_eq!(mixers, ["qplex"], "--algo qplex fixes its mixer whatever --mixers says");

    for (extra, says) in [
        (&["--messages", "3"][..], "give --algo"),
        (&["--algo", "lmac", "--messages", "500"][..], "--messages 500"),
        (&["--algo", "lmac", "--critical", "21"][..], "--critical 21"),
        (&["--algo", "lmac", "--method", "encoder"][..], "KEY=VALUE"),
        (&["--algo", "lmac", "--method", "nope=1"][..], "nope"),
        (&["--algo", "nosuch"][..], "unknown algorithm"),
        (&["--algo", "lmac", "--against", "torch"][..], "drop --algo"),
    ] {
        let out = run(extra);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.contains(says), "{extra:?}: {err}");
    }
}
