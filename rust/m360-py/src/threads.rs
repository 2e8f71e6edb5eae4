//! One explicitly sized rayon pool for every heavy call, entered without the GIL.
//!
//! Maps a call needs are built before its work enters the pool (`Plan::prepare` from the
//! calling thread), never by a job inside it: see `rust/m360-core/src/plan.rs` for the deadlock
//! this avoids.

use crate::errors::{input_error, internal_error};
use m360_core::options::MAX_THREADS;
use m360_core::plan::{Need, Plan};
use pyo3::prelude::*;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Arc, PoisonError, RwLock};

static POOL: RwLock<Option<Arc<rayon::ThreadPool>>> = RwLock::new(None);

fn default_threads() -> usize {
    std::env::var("M360_NUM_THREADS")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
        .filter(|&n| (1..=MAX_THREADS).contains(&n))
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
}

fn build_pool(threads: usize) -> PyResult<Arc<rayon::ThreadPool>> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(|i| format!("m360-{i}"))
        .build()
        .map(Arc::new)
        .map_err(|e| internal_error(format!("cannot start {threads} threads: {e}")))
}

fn pool() -> PyResult<Arc<rayon::ThreadPool>> {
    if let Some(pool) = POOL.read().unwrap_or_else(PoisonError::into_inner).clone() {
        return Ok(pool);
    }
    let mut guard = POOL.write().unwrap_or_else(PoisonError::into_inner);
    if let Some(pool) = guard.as_ref() {
        return Ok(pool.clone());
    }
    let pool = build_pool(default_threads())?;
    *guard = Some(pool.clone());
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
    py.detach(|| {
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
    })
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
    *POOL.write().unwrap_or_else(PoisonError::into_inner) = Some(pool);
    Ok(())
}

/// Number of worker threads of m360's compiled core.
#[pyfunction]
pub(crate) fn get_num_threads() -> PyResult<usize> {
    Ok(pool()?.current_num_threads())
}
