//! The seeded short run of `lmac-fuzz` that CI runs: 2,000 hostile inputs per parser with a fixed
//! seed, through the real binary (child processes, watchdog, allocation cap). A panic, an abort, a
//! hang or an error that does not name its file fails the test, and the table says which input.

use std::process::Command;

fn fuzz(parsers: &str, cases: u64) -> serde_json::Value {
    let out = std::env::temp_dir().join(format!("lmac-fuzz-test-{parsers}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let res = Command::new(env!("CARGO_BIN_EXE_lmac-fuzz"))
        .args(["--parser", parsers, "--cases", &cases.to_string(), "--seed", "20261202", "--hang-secs", "10"])
        .arg("--out")
        .arg(&out)
        .output()
        .expect("lmac-fuzz runs");
    let table = String::from_utf8_lossy(&res.stdout);
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("fuzz.json")).expect("the JSON report")).expect("the report is JSON");
    assert!(res.status.success(), "lmac-fuzz found failures:\n{table}\n{}", String::from_utf8_lossy(&res.stderr));
    for p in report["parsers"].as_array().unwrap() {
        assert_eq!(p["cases"], cases, "{table}");
        // The generators must reach past the first checks, not only produce garbage.
        assert!(p["accepted"].as_u64().unwrap() > 0 || p["parser"] == "llm_reply", "{} accepted nothing:\n{table}", p["parser"]);
        assert!(p["distinct_errors"].as_u64().unwrap() > 3, "{} met few distinct errors:\n{table}", p["parser"]);
    }
    let _ = std::fs::remove_dir_all(&out);
    report
}

#[test]
fn text_parsers_survive_2000_hostile_inputs_each() {
    fuzz("schema,config,protocol,llm_reply,ring_message", 2000);
}

#[test]
fn dataset_reader_survives_2000_hostile_files() {
    fuzz("dataset", 2000);
}

#[test]
fn checkpoint_reader_survives_2000_hostile_files() {
    fuzz("checkpoint", 2000);
}
