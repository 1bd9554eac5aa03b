//! A slab header written by another process is checked, not trusted: a real slab is created in
//! /dev/shm, its header bytes are overwritten through the file, and `Slab::open` must refuse it
//! with an error naming the slab and the field, without panicking or mapping past the file.
use lmac_shm_schema::layout::LayoutParams;
use lmac_shm_schema::slab::{header_offsets as off, shm_file_path};
use lmac_shm_schema::{EnvSchema, Slab, SlabError, Stage};
use std::io::{Seek, SeekFrom, Write};
use std::path::Path;
use std::time::Duration;

fn schema() -> EnvSchema {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../env-server/schemas/lbf/8x8-2p-2f-s1-coop.toml");
    EnvSchema::load(&p).unwrap()
}

const PARAMS: LayoutParams = LayoutParams { num_envs: 4, msg_dim: 8, n_slots: 2 };

/// Create a slab, apply `damage` to its file, and open it as a peer would.
fn open_damaged(tag: &str, damage: impl FnOnce(&mut std::fs::File)) -> (String, Result<Slab, SlabError>) {
    let name = format!("lmac-test-hostile-{tag}-{}", std::process::id());
    let s = schema();
    let owner = Slab::create(&name, &s, PARAMS).unwrap();
    let mut f = std::fs::OpenOptions::new().read(true).write(true).open(shm_file_path(&name)).unwrap();
    damage(&mut f);
    let r = Slab::open(&name, &s, Duration::from_millis(200));
    drop(owner);
    (name, r)
}

fn write_at(f: &mut std::fs::File, at: usize, bytes: &[u8]) {
    f.seek(SeekFrom::Start(at as u64)).unwrap();
    f.write_all(bytes).unwrap();
}

/// The error text names the slab and contains `field`.
fn refused(tag: &str, field: &str, damage: impl FnOnce(&mut std::fs::File)) -> SlabError {
    let (name, r) = open_damaged(tag, damage);
    let e = r.err().unwrap_or_else(|| panic!("{tag}: a damaged header must be refused"));
    let text = e.to_string();
    assert!(text.contains(&name) && text.contains(field), "{tag}: {text}");
    e
}

#[test]
fn undamaged_slab_opens() {
    let (_, r) = open_damaged("ok", |_| {});
    assert_eq!(r.unwrap().layout().params(), PARAMS);
}

#[test]
fn damaged_header_fields_are_named() {
    let e = refused("magic", "magic", |f| write_at(f, off::MAGIC, b"NOTASLAB"));
    assert!(matches!(e, SlabError::BadMagic { .. }));
    let e = refused("version", "layout version", |f| write_at(f, off::LAYOUT_VERSION, &99u32.to_le_bytes()));
    assert!(matches!(e, SlabError::Version { found: 99, .. }));
    let e = refused("state", "state", |f| write_at(f, off::STATE, &7u32.to_le_bytes()));
    assert!(matches!(e, SlabError::Corrupt { field: "state", .. }));
    for (tag, at, value, field) in [
        ("slots0", off::N_SLOTS, 0, "n_slots"),
        ("slotsbig", off::N_SLOTS, u32::MAX, "n_slots"),
        ("envs0", off::NUM_ENVS, 0, "num_envs"),
        ("envsbig", off::NUM_ENVS, u32::MAX, "num_envs"),
        ("msgbig", off::MSG_DIM, u32::MAX, "msg_dim"),
    ] {
        let e = refused(tag, field, |f| write_at(f, at, &value.to_le_bytes()));
        assert!(matches!(e, SlabError::Corrupt { field: f, .. } if f == field), "{tag}: {e}");
    }
    // Fewer slots than the file holds: a consistent-looking header whose hash cannot match.
    let e = refused("slots1", "schema hash", |f| write_at(f, off::N_SLOTS, &1u32.to_le_bytes()));
    assert!(matches!(e, SlabError::SchemaMismatch { .. }));
    let e = refused("hash", "schema hash", |f| write_at(f, off::HASH, &[0xff; 4]));
    assert!(matches!(e, SlabError::SchemaMismatch { .. }));
}

#[test]
fn resized_file_is_refused() {
    let e = refused("short", "bytes", |f| f.set_len(4096 + 64).unwrap());
    assert!(matches!(e, SlabError::Size { .. }));
    let e = refused("long", "bytes", |f| {
        let n = f.metadata().unwrap().len();
        f.set_len(n + 4096).unwrap()
    });
    assert!(matches!(e, SlabError::Size { .. }));
}

#[test]
fn out_of_range_slot_is_an_error() {
    let name = format!("lmac-test-hostile-range-{}", std::process::id());
    let slab = Slab::create(&name, &schema(), PARAMS).unwrap();
    let e = slab.slot(PARAMS.n_slots, Stage::Env).err().expect("slot index out of range");
    assert!(matches!(e, SlabError::SlotRange { slot: 2, n_slots: 2, .. }), "{e}");
    // A corrupt stage word in a slot header is an unknown owner, not a panic.
    let mut f = std::fs::OpenOptions::new().write(true).open(shm_file_path(&name)).unwrap();
    let stage_at = slab.layout().slot_offset(0) + 16;
    write_at(&mut f, stage_at, &9u32.to_le_bytes());
    assert_eq!(slab.stage(0), None);
    let e = slab.slot(0, Stage::Env).err().expect("unknown owner");
    assert!(e.to_string().contains("unknown stage"), "{e}");
}

/// A slab larger than /dev/shm can hold is refused when it is created, naming the bytes it
/// needs and the bytes free, and leaves no file behind (before, the file was created sparse and
/// the first write past the free space killed the writer with SIGBUS).
#[test]
fn a_slab_larger_than_dev_shm_is_refused_at_creation() {
    let (free, total) = lmac_shm_schema::slab::shm_space().expect("statvfs /dev/shm");
    let s = schema();
    // Past the file system's total size: refused before a single page is reserved.
    let bytes = |n_slots| lmac_shm_schema::layout::SlotLayout::new(&s, LayoutParams { n_slots, ..PARAMS }).slab_bytes as u64;
    let per_slot = bytes(2) - bytes(1);
    let n_slots = (total / per_slot + 2) as usize;
    assert!(bytes(n_slots) > total);
    let name = format!("lmac-test-nospace-{}", std::process::id());
    let e = Slab::create(&name, &s, LayoutParams { n_slots, ..PARAMS }).err().expect("a slab past /dev/shm's size must be refused");
    let text = e.to_string();
    assert!(matches!(e, SlabError::NoSpace { .. }), "{text}");
    assert!(text.contains(&name) && text.contains("/dev/shm") && text.contains(&format!("of {total}")), "{text}");
    assert!(free <= total);
    assert!(!Path::new(&shm_file_path(&name)).exists(), "the refused slab's file must be removed");
}

/// Start-up and `lmac clean` touch only files named as lmac names its slabs (a 12-hex-digit run
/// id) that carry lmac's header: another program's `lmac-<anything>-s<N>` file, or a file of
/// lmac's name without lmac's magic number, is neither removed nor counted as dead.
#[test]
fn cleanup_never_takes_another_programs_file_for_a_slab() {
    use lmac_shm_schema::leftovers::survey;
    use lmac_shm_schema::slab::{header_state, parse_slab_name, SlabHeaderState};
    let pid = std::process::id();
    let other = format!("lmac-otherapp{pid}-s1");
    let lookalike = format!("lmac-{:012x}-s0", 0xfeed_0000_0000u64 + pid as u64);
    for n in [&other, &lookalike] {
        std::fs::write(shm_file_path(n), vec![0u8; 4096]).unwrap();
    }
    assert_eq!(parse_slab_name(&other), None);
    assert!(parse_slab_name(&lookalike).is_some());
    assert_eq!(header_state(&lookalike), SlabHeaderState::Foreign);
    let s = survey();
    let listed = |name: &str| s.dead.iter().chain(&s.kept).filter(|f| f.name == name).map(|f| f.why.clone()).collect::<Vec<_>>();
    assert!(listed(&other).is_empty(), "{:?}", listed(&other));
    assert!(!s.dead.iter().any(|f| f.name == lookalike));
    assert_eq!(listed(&lookalike), vec!["not an lmac slab (no lmac header)".to_string()]);
    for n in [&other, &lookalike] {
        std::fs::remove_file(shm_file_path(n)).unwrap();
    }
}
