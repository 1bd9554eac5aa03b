//! Hostile protocol input: deep mixed nesting is refused quickly, and a file larger than any
//! protocol is refused without being read whole.

use lmac_protocol_runner::protocol::*;
use std::time::{Duration, Instant};

/// Alternating `[..]` and `{"neg": ..}` nesting, `depth` levels deep.
fn nested(depth: usize) -> String {
    let mut open = String::new();
    let mut close = String::new();
    for k in 0..depth {
        if k % 3 == 0 {
            open.push('[');
            close.insert(0, ']');
        } else {
            open.push_str("{\"neg\":");
            close.insert(0, '}');
        }
    }
    format!("{open}0{close}")
}

#[test]
fn deep_mixed_nesting_is_refused_quickly() {
    for depth in [100, 1000, 3000] {
        let text = nested(depth);
        let t = Instant::now();
        let r = parse_str(&text);
        let parse = t.elapsed();
        let t = Instant::now();
        let r2 = parse_llm_text(&text);
        let llm = t.elapsed();
        eprintln!("depth {depth}: parse_str {parse:?} ok={} parse_llm_text {llm:?} ok={}", r.is_ok(), r2.is_ok());
        assert!(r.is_err() && r2.is_err());
        assert!(parse + llm < Duration::from_millis(500), "depth {depth}: {parse:?} + {llm:?}");
    }
}

#[test]
fn oversized_protocol_files_are_refused_naming_the_file() {
    let dir = std::env::temp_dir().join(format!("lmac-protocol-hostile-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("huge.json");
    let f = std::fs::File::create(&path).unwrap();
    // Sparse: the size is what counts, not the bytes.
    f.set_len(MAX_FILE_BYTES + 1).unwrap();
    let e = read_protocol_file(&path).unwrap_err().to_string();
    assert!(e.contains("huge.json") && e.contains("more than the 16 MiB"), "{e}");
    let env = ProtocolEnv::new(2, 5, 4, 3, 50);
    let errs = check_file(&path, &env).unwrap_err();
    assert_eq!(errs[0].kind, ErrorKind::Io);
    let e = lmac_protocol_runner::load_phases(&[path.to_str().unwrap()], &env).unwrap_err().to_string();
    assert!(e.contains("huge.json"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A protocol saved with a byte-order mark (some editors write one) parses as without it.
#[test]
fn a_leading_byte_order_mark_is_not_part_of_the_json() {
    let file = concat!(env!("CARGO_MANIFEST_DIR"), "/../protocols/paper/smaclite_1o_10b_vs_1r/phase0/protocol.json");
    let text = std::fs::read_to_string(file).unwrap();
    let plain = parse_str(&text).expect("the shipped protocol parses");
    let with_bom = parse_str(&format!("\u{feff}{text}")).expect("the same text after a byte-order mark parses");
    assert_eq!(serde_json::to_value(&with_bom).unwrap(), serde_json::to_value(&plain).unwrap());
}
