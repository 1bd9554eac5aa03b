//! Truncated or corrupt schema files are refused with an error naming the file and the field,
//! before any size from them is used to allocate or index; one agent is a valid schema.
use lmac_shm_schema::layout::{LayoutParams, SlotLayout};
use lmac_shm_schema::schema::{EnvSchema, MAX_DIM, MAX_FILE_BYTES};
use std::path::{Path, PathBuf};

/// A small valid schema (also the end-to-end schema tests' good example).
const TOY: &str = include_str!("data/toy.toml");

const FILE: &str = "schemas/toy/one.toml";

fn refused(text: &str) -> String {
    let e = EnvSchema::parse(text, Path::new(FILE)).expect_err("must be refused").to_string();
    assert!(e.starts_with(FILE), "the error names the file: {e}");
    e
}

fn lbf_path() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../env-server/schemas/lbf/8x8-2p-2f-s1-coop.toml")
}

#[test]
fn every_truncation_of_a_real_schema_is_refused_naming_the_file() {
    let full = std::fs::read_to_string(lbf_path()).unwrap();
    let mut cut_at = 0;
    while cut_at < full.len() {
        let prefix = &full[..cut_at];
        match EnvSchema::parse(prefix, Path::new(FILE)) {
            // Only a cut in the trailing whitespace leaves the whole schema.
            Ok(_) => assert_eq!(prefix.trim_end(), full.trim_end(), "a truncated schema parsed (cut at byte {cut_at})"),
            Err(e) => {
                let e = e.to_string();
                assert!(e.starts_with(FILE), "cut at {cut_at}: {e}");
            }
        }
        // Every byte would take a while in a debug build; a step of 3 still cuts inside every
        // key, string and table header.
        cut_at = (cut_at + 3..=full.len()).find(|&k| full.is_char_boundary(k)).unwrap_or(full.len());
    }
}

#[test]
fn truncations_name_what_is_missing() {
    let at_task = TOY.find("A toy").unwrap();
    let e = refused(&TOY[..at_task + 3]);
    assert!(e.contains("not valid TOML") && e.contains("line 2"), "{e}");
    let e = refused(&TOY[..TOY.find("[[state_dims]]").unwrap()]);
    assert!(e.contains("state_dims") && e.contains("missing"), "{e}");
    let e = refused(&TOY[..TOY.rfind("meaning").unwrap()]);
    assert!(e.contains("state_dims[0]") || e.contains("meaning"), "{e}");
}

#[test]
fn corrupt_values_are_named_by_their_path() {
    let e = refused(&TOY.replace("n_agents = 2", "n_agents = -1"));
    assert!(e.contains(&format!("{FILE}: n_agents:")), "{e}");
    let e = refused(&TOY.replace("count = 1\n", "count = \"x\"\n"));
    assert!(e.contains(&format!("{FILE}: obs_dims[1].count:")), "{e}");
    let e = refused(&TOY.replace("shape = [2, 2]", "shape = [2, \"2\"]"));
    assert!(e.contains("state_dims[0].shape"), "{e}");
}

#[test]
fn huge_sizes_are_refused_before_anything_is_allocated() {
    // Each would ask for terabytes if a description or a slot column were made per dimension.
    let big = 1usize << 40;
    let e = refused(&TOY.replace("obs_dim = 3", &format!("obs_dim = {big}")).replace("count = 1\n", &format!("count = {}\n", big - 2)));
    assert!(e.contains(&format!("obs_dim: {big} is more than the supported {MAX_DIM}")), "{e}");
    assert!(e.contains("obs_dims[1].count"), "{e}");
    let e = refused(&TOY.replace("shape = [2, 2]", "shape = [4294967296, 4294967296, 4294967296]"));
    assert!(e.contains("state_dims[0]: shape") && e.contains("more dimensions than fit"), "{e}");
    let e = refused(&TOY.replace("message_columns = 10", &format!("message_columns = {big}")));
    assert!(e.contains("message_columns"), "{e}");
    let e = refused(&TOY.replace("episode_limit = 10", &format!("episode_limit = {big}")));
    assert!(e.contains("episode_limit"), "{e}");
}

#[test]
fn unreadable_files_are_refused_naming_the_file() {
    let dir = std::env::temp_dir().join(format!("lmac-hostile-schema-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let not_text = dir.join("binary.toml");
    let mut bytes = TOY.as_bytes().to_vec();
    bytes[20] = 0xff;
    std::fs::write(&not_text, &bytes).unwrap();
    let e = EnvSchema::load(&not_text).unwrap_err().to_string();
    assert!(e.contains("binary.toml") && e.contains("not UTF-8"), "{e}");
    let huge = dir.join("huge.toml");
    let f = std::fs::File::create(&huge).unwrap();
    f.set_len(MAX_FILE_BYTES + 1).unwrap(); // sparse: nothing is written
    let e = EnvSchema::load(&huge).unwrap_err().to_string();
    assert!(e.contains("huge.toml") && e.contains("at most"), "{e}");
    let cut = dir.join("cut.toml");
    std::fs::write(&cut, &TOY[..TOY.len() / 2]).unwrap();
    let e = EnvSchema::load(&cut).unwrap_err().to_string();
    assert!(e.contains("cut.toml"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn one_agent_is_a_valid_schema_without_message_columns() {
    let one = TOY.replace("n_agents = 2", "n_agents = 1").replace("message_columns = 10", "message_columns = 0");
    let s = EnvSchema::parse(&one, Path::new(FILE)).expect("one agent validates");
    assert_eq!(s.n_agents, 1);
    assert_eq!(s.fullcomm_columns(), 0, "fullcomm has no one to send to");
    let l = SlotLayout::new(&s, LayoutParams { num_envs: 2, msg_dim: s.fullcomm_columns(), n_slots: 2 });
    assert_eq!(l.row_width, s.obs_dim);
    // Zero agents stays an error, and the column count does not underflow on it.
    let zero = EnvSchema { n_agents: 0, ..s };
    assert_eq!(zero.fullcomm_columns(), 0);
    assert!(zero.validate(Path::new(FILE)).unwrap_err().to_string().contains("n_agents: must be at least 1"));
}

/// A group of 65536 dimensions with a 1 MB meaning fits every per-field bound, but its
/// descriptions would need 64 GiB (the process aborted). Refused at parse time, naming the group.
#[test]
fn descriptions_that_would_expand_past_memory_are_refused_naming_the_group() {
    let meaning = "x".repeat(1 << 20);
    let text = TOY
        .replace("obs_dim = 3", "obs_dim = 65538")
        .replace("count = 1\nmeaning = \"speed\"", &format!("count = 65536\nmeaning = \"{meaning} {{k}}\""));
    let e = refused(&text);
    assert!(e.contains("obs_dims[1].meaning") && e.contains("expand to more than"), "{e}");
    assert!(!e.contains("groups describe"), "one error, not a follow-on one: {e}");
    // The real schemas stay far below the bound.
    let lbf = EnvSchema::load(&lbf_path()).unwrap();
    assert!(lbf.obs_meanings().iter().map(String::len).sum::<usize>() < 1 << 20);
}
