//! `vesselflow._core`: the Python extension of vesselflow.
//!
//! Conversion only: NumPy masks are borrowed and handed to the Rust core with the GIL
//! released, results come back as NumPy arrays and dicts, and core errors become
//! Python exceptions in one place ([`errors`]). The user-facing API is the
//! `vesselflow` Python package, which wraps this module.

mod binarise;
mod blocks;
mod cli;
mod errors;
mod graph_io;
mod memory;
mod params;
mod prune;
mod skeletonizer;
mod watch;

use pyo3::prelude::*;

/// Large blocks mapped on their own (see `vesselflow::allocator`).
#[global_allocator]
static ALLOCATOR: vesselflow::allocator::Allocator = vesselflow::allocator::Allocator;

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_class::<skeletonizer::PySkeletonizer>()?;
    m.add_function(wrap_pyfunction!(binarise::binarise, m)?)?;
    m.add_function(wrap_pyfunction!(params::param_defaults, m)?)?;
    m.add_function(wrap_pyfunction!(memory::memory_estimate, m)?)?;
    m.add_function(wrap_pyfunction!(memory::usable_memory, m)?)?;
    m.add_function(wrap_pyfunction!(graph_io::write_graph, m)?)?;
    m.add_function(wrap_pyfunction!(graph_io::to_frame, m)?)?;
    m.add_function(wrap_pyfunction!(prune::prune_spurs, m)?)?;
    m.add_function(wrap_pyfunction!(cli::cli_main, m)?)?;
    blocks::register(m)?;
    Ok(())
}
