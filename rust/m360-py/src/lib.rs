//! `m360._core`: the compiled module. Converts arrays, releases the GIL, maps errors; no
//! algorithm, and no option name, default or check of its own (those live in the core's types;
//! `CHOICES`, `LIMITS` and `DEFAULTS` export them to Python).
//!
//! The Python package checks argument *types* before calling in here; values are checked by the
//! core, so a bad value gives `m360.errors.InputError` naming the option, never a panic.

#![expect(
    clippy::needless_pass_by_value,
    reason = "pyo3 hands extracted arguments (arrays, bound objects) to functions by value"
)]

mod align;
mod arrays;
mod blend;
mod errors;
mod layout;
mod options;
mod stereo;
mod threads;
mod upsample;

#[pyo3::pymodule]
mod _core {
    #[pymodule_export]
    use super::blend::poisson_blend;
    #[pymodule_export]
    use super::layout::{icosahedron_cameras, Plan};
    #[pymodule_export]
    use super::options::stitch_options;
    #[pymodule_export]
    use super::stereo::{ods_defaults, ods_stereo};
    #[pymodule_export]
    use super::threads::{get_num_threads, set_num_threads};
    #[pymodule_export]
    use super::upsample::{
        bilinear_upsample, guided_fit, guided_upsample, refine_edges, upsample_planes,
    };

    #[pymodule_init]
    fn init(m: &pyo3::Bound<'_, pyo3::types::PyModule>) -> pyo3::PyResult<()> {
        use pyo3::types::PyModuleMethods;
        // faer would otherwise run its own thread pool inside calls that already run on m360's
        // rayon pool; m360 parallelises over its own data, so faer's kernels run sequentially.
        faer::set_global_parallelism(faer::Par::Seq);
        let py = m.py();
        m.add("__version__", env!("CARGO_PKG_VERSION"))?;
        m.add("CHOICES", super::options::choices(py)?)?;
        m.add("LIMITS", super::options::limits(py)?)?;
        m.add("DEFAULTS", super::options::defaults(py)?)?;
        m.add("PLAN_FILE_SUFFIX", m360_core::plan_cache::FILE_SUFFIX)?;
        m.add(
            "PLAN_FORMAT",
            format!(
                "v{}-{}",
                m360_core::plan_cache::FORMAT_VERSION,
                m360_core::plan_cache::BUILD_ID
            ),
        )?;
        Ok(())
    }
}
