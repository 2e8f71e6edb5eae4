//! One explicitly sized rayon pool for every heavy call, entered without the GIL.
//!
//! Maps a call needs are built before its work enters the pool (`Plan::prepare` from the
//! calling thread), never by a job inside it: see `rust/m360-core/src/plan.rs` for the deadlock
//! this avoids.
//!
//! A forked child inherits the pool's handle but none of its threads: work sent there would wait
//! forever. The pool therefore remembers the process that started it, and a child starts its
//! own on first use (the parent's is leaked, never dropped: its threads are not there to stop).

use crate::errors::{input_error, internal_error};
use m360_core::options::MAX_THREADS;
use m360_core::plan::{Need, Plan};
use pyo3::prelude::*;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Arc, PoisonError, RwLock};

/// m360's pool and the id of the process that started it.
static POOL: RwLock<Option<(u32, Arc<rayon::ThreadPool>)>> = RwLock::new(None);

fn default_threads() -> usize {
    std::env::var("M360_NUM_THREADS")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
        .filter(|&n| (1..=MAX_THREADS).contains(&n))
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, std::num::NonZero::get))
}

fn build_pool(threads: usize) -> PyResult<Arc<rayon::ThreadPool>> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(|i| format!("m360-{i}"))
        .build()
        .map(Arc::new)
        .map_err(|e| internal_error(format!("cannot start {threads} threads: {e}")))
}

/// The pool of this process, started on first use (or first use after a fork).
fn pool() -> PyResult<Arc<rayon::ThreadPool>> {
    let pid = std::process::id();
    let ours = |slot: &Option<(u32, Arc<rayon::ThreadPool>)>| match slot {
        Some((owner, pool)) if *owner == pid => Some(pool.clone()),
        _ => None,
    };
    if let Some(pool) = ours(&POOL.read().unwrap_or_else(PoisonError::into_inner)) {
        return Ok(pool);
    }
    let mut guard = POOL.write().unwrap_or_else(PoisonError::into_inner);
    if let Some(pool) = ours(&guard) {
        return Ok(pool);
    }
    // After a fork, the same number of threads as the parent's pool had.
    let threads = guard
        .as_ref()
        .map_or_else(default_threads, |(_, p)| p.current_num_threads());
    let pool = build_pool(threads)?;
    if let Some(inherited) = guard.replace((pid, pool.clone())) {
        std::mem::forget(inherited);
    }
    Ok(pool)
}

/// Run heavy work without the GIL on m360's pool, after building the maps of `plan` that it
/// `needs` (outside the pool); a panic becomes `M360Error`, never a crash.
pub(crate) fn on_pool<T: Send>(
    py: Python<'_>,
    plan: Option<(&Plan, &[Need])>,
    work: impl FnOnce() -> T + Send,
) -> PyResult<T> {
    let pool = pool()?;
    let result = py
        .detach(|| {
            catch_unwind(AssertUnwindSafe(|| {
                if let Some((plan, needs)) = plan {
                    plan.prepare(needs, |build| pool.install(build));
                }
                pool.install(work)
            }))
        })
        .map_err(|panic| {
            let msg = panic
                .downcast_ref::<&str>()
                .map(|s| (*s).to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown panic".into());
            internal_error(format!(
                "internal error in m360's core (please report): {msg}"
            ))
        });
    if let Some((plan, _)) = plan {
        log_disk_notes(py, plan)?;
    }
    result
}

/// Report rejected or unwritable plan cache files as warnings of the `m360.plan_cache` logger.
fn log_disk_notes(py: Python<'_>, plan: &Plan) -> PyResult<()> {
    let notes = plan.take_disk_notes();
    if !notes.is_empty() {
        let logger = py
            .import("logging")?
            .call_method1("getLogger", ("m360.plan_cache",))?;
        for note in notes {
            logger.call_method1("warning", (note,))?;
        }
    }
    Ok(())
}

/// Set the number of worker threads of m360's compiled core (None: `M360_NUM_THREADS` or all
/// cores), at most `LIMITS["max_threads"]`. Results do not depend on it.
#[pyfunction]
#[pyo3(signature = (threads=None))]
pub(crate) fn set_num_threads(threads: Option<&Bound<'_, PyAny>>) -> PyResult<()> {
    let threads = match threads {
        None => default_threads(),
        Some(value) => {
            let bad = || {
                let shown = value.repr().map_or_else(|_| "?".into(), |r| r.to_string());
                input_error(format!(
                    "threads must be an integer in [1, {MAX_THREADS}] or None, got {shown}"
                ))
            };
            if value.is_instance_of::<pyo3::types::PyBool>() {
                return Err(bad());
            }
            match value.extract::<usize>() {
                Ok(n) if (1..=MAX_THREADS).contains(&n) => n,
                _ => return Err(bad()),
            }
        }
    };
    let pool = build_pool(threads)?;
    let pid = std::process::id();
    let mut guard = POOL.write().unwrap_or_else(PoisonError::into_inner);
    if let Some((owner, inherited)) = guard.replace((pid, pool)) {
        if owner != pid {
            std::mem::forget(inherited);
        }
    }
    Ok(())
}

/// Number of worker threads of m360's compiled core.
#[pyfunction]
pub(crate) fn get_num_threads() -> PyResult<usize> {
    Ok(pool()?.current_num_threads())
}
