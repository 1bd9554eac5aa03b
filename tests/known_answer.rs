//! A communication game with a known answer and agents that differ
//! (`lmac_env.examples.signal:observer-2actors`): an observer that sees the goal but cannot act,
//! two actors that are rewarded for naming the goal but cannot see it, and a bystander. The
//! default offline designer (routing by need) sends the goal from the observer to the two actors only;
//! LMAC trained with that design earns all of the reward where QMIX, without messages, can only
//! guess (a third of it).

use lmac_e2e::harness::lmac;
use std::path::{Path, PathBuf};
use std::process::Stdio;

const ENV: &str = "lmac_env.examples.signal:observer-2actors";

fn run(dir: &Path, args: &[&str]) -> String {
    let out = lmac().args(args).current_dir(dir).stdin(Stdio::null()).output().unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "lmac {args:?}: {text}");
    text
}

/// The one directory under `dir` that holds `file`, however deep.
fn find(dir: &Path, file: &str) -> PathBuf {
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        if d.join(file).exists() {
            return d;
        }
        stack.extend(std::fs::read_dir(&d).unwrap().map(|e| e.unwrap().path()).filter(|p| p.is_dir()));
    }
    panic!("no {file} under {}", dir.display())
}

/// The mean test return of a run's last two test phases.
fn final_test_return(run: &Path) -> f64 {
    let rows: Vec<serde_json::Value> = std::fs::read_to_string(find(run, "metrics.jsonl").join("metrics.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let tests: Vec<f64> = rows.iter().filter_map(|r| r["test_return_mean"].as_f64()).collect();
    assert!(tests.len() >= 2, "{rows:?}");
    tests[tests.len() - 2..].iter().sum::<f64>() / 2.0
}

#[test]
fn by_default_the_observer_tells_the_actors_and_lmac_beats_qmix() {
    let dir = std::env::temp_dir().join(format!("lmac-known-answer-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let small = ["--envs", "8", "--servers", "1", "--seed", "0"];
    let small_run = ["--set", "run.envs=8", "--set", "run.servers=1", "--set", "run.test_interval=2500", "--seeds", "0"];
    let mut design = vec!["design", "--env", ENV, "--llm", "offline"];
    design.extend(["--pretrain-steps", "20000", "--dataset-episodes", "200", "--dataset-epsilon", "0.05"]);
    design.extend(["--disc-updates", "300", "--phases", "1", "--out", "design"]);
    design.extend(small);
    let log = run(&dir, &design);
    let d = find(&dir.join("design"), "final_protocol.txt");
    // The log says per agent what it needs, who supplies it best and what it receives.
    let line = |i: usize| log.lines().find(|l| l.starts_with(&format!("lmac: agent {i}: "))).unwrap_or_else(|| panic!("{log}")).to_string();
    assert!(line(1).contains("needs s[") && line(1).contains("best from agent 0") && line(1).contains("from agent 0"), "{}", line(1));
    assert!(line(3).ends_with("receives nothing"), "{}", line(3));

    // The design: the observer sends the goal, to the two actors only.
    let p: serde_json::Value = serde_json::from_slice(&std::fs::read(d.join("phase0/protocol.json")).unwrap()).unwrap();
    let fields = p["fields"].as_array().unwrap();
    assert!(!fields.is_empty(), "{p}");
    for f in fields {
        assert_eq!(f["senders"], serde_json::json!([0]), "only the observer sends: {p}");
        assert_eq!(f["receivers"]["peer"][0]["to"], serde_json::json!([1, 2]), "to the actors, not the bystander: {p}");
    }
    assert!(fields.iter().any(|f| f["value"]["obs"].as_array().unwrap().contains(&serde_json::json!(0))), "the goal is sent: {p}");
    // Each agent's need, said in the design's summary: the actors need the goal, the others not.
    let summary: serde_json::Value = serde_json::from_slice(&std::fs::read(d.join("summary.json")).unwrap()).unwrap();
    let needs = summary["designer_measurements"]["needs"].as_array().unwrap_or_else(|| panic!("{summary}"));
    let need = |i: usize| needs[i]["dims"].as_array().unwrap().iter().map(|x| x["need"].as_f64().unwrap()).sum::<f64>();
    assert!(need(1) > 10.0 * need(0).max(need(3)) && need(2) > 10.0 * need(0).max(need(3)), "{needs:?}");
    // And what each receives: the actors the goal from the observer, the others nothing.
    let received = summary["received"].as_array().unwrap_or_else(|| panic!("{summary}"));
    let senders =
        |i: usize| -> Vec<u64> { received[i]["receives"].as_array().unwrap().iter().map(|x| x["sender"].as_u64().unwrap()).collect() };
    assert!(!senders(1).is_empty() && senders(1).iter().chain(&senders(2)).all(|&s| s == 0), "{received:?}");
    assert!(senders(0).is_empty() && senders(3).is_empty(), "{received:?}");

    // Trained: LMAC with the design finds the goal; QMIX, without messages, can only guess.
    let protocol = std::fs::read_to_string(d.join("final_protocol.txt")).unwrap();
    let train = |algo: &str, extra: &[&str]| {
        let mut a = vec!["train", "--env", ENV, "--algo", algo, "--steps", "15k", "--out", algo];
        a.extend(extra);
        a.extend(small_run);
        run(&dir, &a);
        final_test_return(&dir.join(algo))
    };
    let with_messages = train("lmac", &["--protocol", protocol.trim()]);
    let guessing = train("qmix", &[]);
    // 12 steps: all of the reward is 12, a guess earns about 4.
    eprintln!("final test return: LMAC {with_messages:.2}, QMIX {guessing:.2}");
    assert!(with_messages > 9.0 && guessing < 6.0, "LMAC {with_messages:.2}, QMIX {guessing:.2}");
    let _ = std::fs::remove_dir_all(&dir);
}
