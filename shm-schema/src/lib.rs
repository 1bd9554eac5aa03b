//! lmac's one contract between env servers, protocol runner and trainer:
//! - [`schema`]: environment schema files (dims, meanings, episode limit, alpha) and validation;
//! - [`layout`]: the byte layout of one batched step (a slot) computed from a schema;
//! - [`slab`]: K slots in POSIX shared memory, mapped read-write by every process;
//! - [`ring`]: the iceoryx2 control plane passing slot ownership around the ring;
//! - [`leftovers`]: what dead runs leave in shared memory, found and removed (`lmac clean`);
//! - [`safe_fs`]: how every lmac crate reads and writes files that others may have placed:
//!   bounded reads of regular files only, writes that never follow a planted link.
pub mod layout;
pub mod leftovers;
pub mod ring;
pub mod safe_fs;
pub mod schema;
pub mod slab;

pub use layout::{LayoutParams, SlotLayout, FLAG_FINAL, FLAG_FIRST, FLAG_PREV_WON};
pub use ring::{Port, RingError, RingSpec, SlotMsg};
pub use schema::EnvSchema;
pub use slab::{Slab, SlabError, Slot, Stage};
