//! The `vesselflow` program: everything lives in the library so that the Python
//! package can expose the same command line (see `vesselflow_cli::run_with`).

fn main() {
    std::process::exit(vesselflow_cli::run(std::env::args_os()))
}
