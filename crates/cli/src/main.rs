//! The `vesselflow` program: everything lives in the library so that the Python
//! package can expose the same command line (see `vesselflow_cli::run_with`).

/// Large blocks mapped on their own (see `vesselflow::allocator`).
#[global_allocator]
static ALLOCATOR: vesselflow::allocator::Allocator = vesselflow::allocator::Allocator;

fn main() {
    std::process::exit(vesselflow_cli::run(std::env::args_os()))
}
