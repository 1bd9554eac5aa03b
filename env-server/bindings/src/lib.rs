//! `lmac_shm`: the Python side of lmac's data plane, over the same Rust crate as the runner and
//! trainer (one schema definition, one iceoryx2 version on both sides).
//!
//! - `Slab.create(...)` / `Slab.open(...)`: the shared-memory slab of one env server.
//! - `slab.lease(i, "env")`: a lease on slot `i`; its numpy arrays *are* the slot memory.
//!   After `lease.release(...)` every attribute raises `SlotReleasedError`, and `release`
//!   refuses (raising `SlotViewsAliveError`) while any numpy view of the lease is still alive,
//!   so Python never reads or writes a slot another process owns.
//! - `Port(...)`: the iceoryx2 control plane (handshake, receive, hand over, goodbye).

use lmac_shm_schema::layout::{LayoutParams, Section};
use lmac_shm_schema::ring::{self, Port as RingPort, RingError, RingSpec, KIND_BYE, KIND_HELLO, KIND_SLOT};
use lmac_shm_schema::{EnvSchema, Slab as RSlab, Stage};
use numpy::ndarray::{ArrayView, IxDyn, ShapeBuilder};
use numpy::{Element, PyArray, PyArrayDyn};
use pyo3::create_exception;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

create_exception!(lmac_shm, SlotReleasedError, PyRuntimeError, "The slot was handed over; its views are gone.");
create_exception!(lmac_shm, SlotViewsAliveError, PyRuntimeError, "Numpy views of the slot are still alive.");
create_exception!(lmac_shm, PeerError, PyRuntimeError, "A peer process of the ring died or vanished.");
create_exception!(lmac_shm, StoppedError, PyRuntimeError, "The process was asked to stop.");
create_exception!(
    lmac_shm,
    RefusedError,
    PyValueError,
    "lmac refused to use a setting or a shared resource (an iceoryx2 directory that is not this user's alone, say); the message says which and why."
);

fn parse_stage(s: &str) -> PyResult<Stage> {
    match s {
        "env" => Ok(Stage::Env),
        "runner" => Ok(Stage::Runner),
        "trainer" => Ok(Stage::Trainer),
        _ => Err(PyValueError::new_err(format!("stage must be 'env', 'runner' or 'trainer', got {s:?}"))),
    }
}

fn load_schema(path: &str) -> PyResult<EnvSchema> {
    EnvSchema::load(Path::new(path)).map_err(|e| PyValueError::new_err(e.to_string()))
}

fn ring_err(e: RingError) -> PyErr {
    match e {
        RingError::Stopped => StoppedError::new_err(e.to_string()),
        // A peer that sends a message that does not fit the ring is as broken as a dead one.
        RingError::PeerDied { .. } | RingError::PeerGone { .. } | RingError::PeerMissing { .. } | RingError::BadMessage { .. } => {
            PeerError::new_err(e.to_string())
        }
        RingError::Usage(_) => RefusedError::new_err(e.to_string()),
        _ => PyRuntimeError::new_err(e.to_string()),
    }
}

#[pyclass(frozen)]
struct Slab {
    inner: Arc<RSlab>,
}

#[pymethods]
impl Slab {
    /// Create the slab (owner-only, mode 0600) for the schema file at `schema_path`.
    #[staticmethod]
    fn create(name: &str, schema_path: &str, num_envs: usize, msg_dim: usize, n_slots: usize) -> PyResult<Slab> {
        let schema = load_schema(schema_path)?;
        if num_envs == 0 || n_slots == 0 {
            return Err(PyValueError::new_err("num_envs and n_slots must be at least 1"));
        }
        let slab = RSlab::create(name, &schema, LayoutParams { num_envs, msg_dim, n_slots })
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
        Ok(Slab { inner: Arc::new(slab) })
    }

    /// Open a peer's slab, waiting up to `timeout` seconds for it.
    #[staticmethod]
    #[pyo3(signature = (name, schema_path, timeout=10.0))]
    fn open(name: &str, schema_path: &str, timeout: f64) -> PyResult<Slab> {
        let schema = load_schema(schema_path)?;
        let slab = RSlab::open(name, &schema, Duration::from_secs_f64(timeout)).map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
        Ok(Slab { inner: Arc::new(slab) })
    }

    #[getter]
    fn name(&self) -> String {
        self.inner.name().to_string()
    }
    #[getter]
    fn num_envs(&self) -> usize {
        self.inner.layout().num_envs
    }
    #[getter]
    fn n_slots(&self) -> usize {
        self.inner.layout().n_slots
    }
    #[getter]
    fn msg_dim(&self) -> usize {
        self.inner.layout().msg_dim
    }
    #[getter]
    fn slot_bytes(&self) -> usize {
        self.inner.layout().slot_stride
    }
    #[getter]
    fn schema_hash(&self) -> String {
        self.inner.layout().hash_hex()
    }

    /// The stage that owns slot `i` now.
    fn stage(&self, i: usize) -> PyResult<String> {
        self.check_index(i)?;
        Ok(self
            .inner
            .stage(i)
            .map_or("unknown", |s| match s {
                Stage::Env => "env",
                Stage::Runner => "runner",
                Stage::Trainer => "trainer",
            })
            .to_string())
    }

    /// Mark slot `i` as owned by `stage` (only at start-up, before the ring runs).
    fn set_stage(&self, i: usize, stage: &str) -> PyResult<()> {
        self.check_index(i)?;
        self.inner.set_stage(i, parse_stage(stage)?);
        Ok(())
    }

    /// Lease slot `i` as `stage`; fails unless that stage owns it.
    #[pyo3(signature = (i, stage="env"))]
    fn lease(&self, i: usize, stage: &str) -> PyResult<Lease> {
        self.check_index(i)?;
        let me = parse_stage(stage)?;
        self.inner.slot(i, me).map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
        Ok(Lease { slab: self.inner.clone(), slot: i, me, released: false, views: Arc::new(AtomicUsize::new(0)) })
    }
}

impl Slab {
    fn check_index(&self, i: usize) -> PyResult<()> {
        if i >= self.inner.layout().n_slots {
            return Err(PyValueError::new_err(format!("slot {i} out of range: the slab has {}", self.inner.layout().n_slots)));
        }
        Ok(())
    }
}

/// Keeps the mapping alive for as long as numpy views exist and counts them.
#[pyclass(frozen)]
struct ViewGuard {
    _slab: Arc<RSlab>,
    views: Arc<AtomicUsize>,
}

impl Drop for ViewGuard {
    fn drop(&mut self) {
        self.views.fetch_sub(1, Ordering::AcqRel);
    }
}

#[pyclass(unsendable)]
struct Lease {
    slab: Arc<RSlab>,
    slot: usize,
    me: Stage,
    released: bool,
    views: Arc<AtomicUsize>,
}

impl Lease {
    fn live(&self) -> PyResult<()> {
        if self.released {
            return Err(SlotReleasedError::new_err(format!(
                "slot {} of {} was handed over; take a new lease when it comes back",
                self.slot,
                self.slab.name()
            )));
        }
        Ok(())
    }

    /// A numpy view of `shape` (element strides `strides`) at byte `offset` inside the slot.
    fn view<'py, T: Element>(
        &self,
        py: Python<'py>,
        offset: usize,
        shape: &[usize],
        strides: &[usize],
    ) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
        self.live()?;
        let base = unsafe { self.slab.slot_ptr(self.slot).add(offset) } as *const T;
        let view = unsafe { ArrayView::from_shape_ptr(IxDyn(shape).strides(IxDyn(strides)), base) };
        self.views.fetch_add(1, Ordering::AcqRel);
        let guard = Bound::new(py, ViewGuard { _slab: self.slab.clone(), views: self.views.clone() })?;
        // SAFETY: the guard keeps the mapping alive; `release` refuses while views exist, so the
        // memory is only touched while this process's stage owns the slot.
        Ok(unsafe { PyArray::borrow_from_array(&view, guard.into_any()) })
    }

    fn section<'py, T: Element>(&self, py: Python<'py>, s: Section, shape: &[usize]) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
        let mut strides = vec![1usize; shape.len()];
        for d in (0..shape.len().saturating_sub(1)).rev() {
            strides[d] = strides[d + 1] * shape[d + 1];
        }
        debug_assert_eq!(shape.iter().product::<usize>() * std::mem::size_of::<T>(), s.bytes);
        self.view(py, s.offset, shape, &strides)
    }
}

#[pymethods]
impl Lease {
    #[getter]
    fn slot(&self) -> usize {
        self.slot
    }
    #[getter]
    fn released(&self) -> bool {
        self.released
    }
    /// Number of numpy views of this lease still alive.
    #[getter]
    fn live_views(&self) -> usize {
        self.views.load(Ordering::Acquire)
    }

    /// float32 (B, n_agents, obs_dim): the observation columns of every row.
    #[getter]
    fn obs<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let l = self.slab.layout();
        self.view(py, l.obs.offset, &[l.num_envs, l.n_agents, l.obs_dim], &[l.n_agents * l.row_width, l.row_width, 1])
    }
    /// float32 (B, n_agents, msg_dim): the message columns (written by the protocol runner).
    #[getter]
    fn msg<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let l = self.slab.layout();
        self.view(py, l.obs.offset + 4 * l.obs_dim, &[l.num_envs, l.n_agents, l.msg_dim], &[l.n_agents * l.row_width, l.row_width, 1])
    }
    /// float32 (B, n_agents, obs_dim + msg_dim): whole rows.
    #[getter]
    fn rows<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let l = self.slab.layout();
        self.section(py, l.obs, &[l.num_envs, l.n_agents, l.row_width])
    }
    #[getter]
    fn state<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let l = self.slab.layout();
        self.section(py, l.state, &[l.num_envs, l.state_dim])
    }
    #[getter]
    fn avail<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<u8>>> {
        let l = self.slab.layout();
        self.section(py, l.avail, &[l.num_envs, l.n_agents, l.n_actions])
    }
    #[getter]
    fn reward<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
        let l = self.slab.layout();
        self.section(py, l.reward, &[l.num_envs])
    }
    #[getter]
    fn terminated<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<u8>>> {
        let l = self.slab.layout();
        self.section(py, l.terminated, &[l.num_envs])
    }
    #[getter]
    fn truncated<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<u8>>> {
        let l = self.slab.layout();
        self.section(py, l.truncated, &[l.num_envs])
    }
    #[getter]
    fn last_actions<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<i32>>> {
        let l = self.slab.layout();
        self.section(py, l.last_actions, &[l.num_envs, l.n_agents])
    }
    #[getter]
    fn actions<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<i32>>> {
        let l = self.slab.layout();
        self.section(py, l.actions, &[l.num_envs, l.n_agents])
    }
    /// uint64 (B,): episode id of each env.
    #[getter]
    fn episode_id<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<u64>>> {
        let l = self.slab.layout();
        self.view(py, l.env_meta.offset, &[l.num_envs], &[2])
    }
    /// uint32 (B,): step within the episode of each env.
    #[getter]
    fn ep_step<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<u32>>> {
        let l = self.slab.layout();
        self.view(py, l.env_meta.offset + 8, &[l.num_envs], &[4])
    }
    /// uint32 (B,): flags of each env (bit 0: first step of an episode).
    #[getter]
    fn flags<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<u32>>> {
        let l = self.slab.layout();
        self.view(py, l.env_meta.offset + 12, &[l.num_envs], &[4])
    }

    /// Sequence number of the batched step in this slot.
    #[getter]
    fn get_seq(&self) -> PyResult<u64> {
        self.live()?;
        Ok(unsafe { (self.slab.slot_ptr(self.slot) as *const u64).read() })
    }
    #[setter]
    fn set_seq(&self, seq: u64) -> PyResult<()> {
        self.live()?;
        unsafe { (self.slab.slot_ptr(self.slot) as *mut u64).write(seq) };
        Ok(())
    }
    #[setter]
    fn set_step(&self, step: u64) -> PyResult<()> {
        self.live()?;
        unsafe { (self.slab.slot_ptr(self.slot).add(8) as *mut u64).write(step) };
        Ok(())
    }

    /// Hand the slot to `to` (default: the next stage). Refuses while numpy views are alive.
    #[pyo3(signature = (to=None))]
    fn release(&mut self, to: Option<&str>) -> PyResult<()> {
        self.live()?;
        let n = self.views.load(Ordering::Acquire);
        if n > 0 {
            return Err(SlotViewsAliveError::new_err(format!(
                "{n} numpy view(s) of slot {} are still alive; drop them (del) before handing the slot over",
                self.slot
            )));
        }
        let to = match to {
            Some(s) => parse_stage(s)?,
            None => self.me.next(),
        };
        self.slab.set_stage(self.slot, to);
        self.released = true;
        Ok(())
    }
}

#[pyclass(unsendable)]
struct Port {
    inner: RingPort,
}

#[pymethods]
impl Port {
    #[new]
    #[pyo3(signature = (run, role, member, n_members, n_slots, startup_timeout=60.0))]
    fn new(run: &str, role: &str, member: usize, n_members: usize, n_slots: usize, startup_timeout: f64) -> PyResult<Port> {
        let mut inner =
            RingPort::new(RingSpec { run: run.into(), n_members, n_slots, role: parse_stage(role)?, member }).map_err(ring_err)?;
        inner.set_startup_timeout(Duration::from_secs_f64(startup_timeout));
        Ok(Port { inner })
    }

    /// Env servers: wait until a start-up token has gone around the whole ring.
    fn handshake(&mut self, timeout: f64) -> PyResult<()> {
        self.inner.handshake(Duration::from_secs_f64(timeout)).map_err(ring_err)
    }

    /// Next message: None on timeout, else (kind, member, slot, seq) with kind "slot" or "bye".
    fn recv(&mut self, py: Python<'_>, timeout: f64) -> PyResult<Option<(String, u32, u32, u64)>> {
        let r = self.inner.recv(Duration::from_secs_f64(timeout)).map_err(ring_err)?;
        py.check_signals()?;
        Ok(r.map(|m| {
            let kind = match m.kind {
                KIND_SLOT => "slot",
                KIND_BYE => "bye",
                KIND_HELLO => "hello",
                _ => "unknown",
            };
            (kind.to_string(), m.member, m.slot, m.seq)
        }))
    }

    fn send_slot(&self, member: usize, slot: usize, seq: u64) -> PyResult<()> {
        self.inner.send_slot(member, slot, seq).map_err(ring_err)
    }

    fn send_bye(&mut self, member: usize) -> PyResult<()> {
        self.inner.send_bye(member).map_err(ring_err)
    }

    fn check_peers(&mut self) -> PyResult<()> {
        self.inner.check_peers().map_err(ring_err)
    }

    /// After forwarding the trainer's goodbye: wait up to `timeout_s` until the protocol runner
    /// is gone, so the goodbye stays readable until it has taken it. True when it is gone.
    fn wait_downstream_gone(&mut self, timeout_s: f64) -> bool {
        self.inner.wait_downstream_gone(Duration::from_secs_f64(timeout_s.max(0.0)))
    }
}

/// Ask this process's waits to stop (call from a signal handler).
#[pyfunction]
fn request_stop() {
    ring::request_stop();
}

/// Remove a slab's name (cleanup after a crash). Returns whether it existed.
#[pyfunction]
fn unlink(name: &str) -> bool {
    lmac_shm_schema::slab::unlink(name)
}

#[pymodule]
fn lmac_shm(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Slab>()?;
    m.add_class::<Lease>()?;
    m.add_class::<Port>()?;
    m.add_class::<ViewGuard>()?;
    m.add_function(wrap_pyfunction!(request_stop, m)?)?;
    m.add_function(wrap_pyfunction!(unlink, m)?)?;
    m.add("SlotReleasedError", m.py().get_type::<SlotReleasedError>())?;
    m.add("SlotViewsAliveError", m.py().get_type::<SlotViewsAliveError>())?;
    m.add("PeerError", m.py().get_type::<PeerError>())?;
    m.add("StoppedError", m.py().get_type::<StoppedError>())?;
    m.add("RefusedError", m.py().get_type::<RefusedError>())?;
    Ok(())
}
