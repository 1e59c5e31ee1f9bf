//! The commands of `readi`, one module per command (`ir` also holds `graph` and
//! `passes`); `main.rs` parses the command line and dispatches to them.

use std::path::Path;
use std::process::ExitCode;
use std::sync::Arc;

use readi_runtime::exec::SessionOptions;
use readi_runtime::plan::Plan;

pub mod adapt_bn;
pub mod args;
pub mod ast;
pub mod bench;
pub mod check;
pub mod compile;
pub mod demo;
pub mod deploy;
pub mod files;
pub mod frontend;
pub mod inspect;
pub mod ir;
pub mod params;
pub mod run;
pub mod simulate;
pub mod tensor_io;

/// `--threads`, or every core.
pub fn threads_or_default(threads: Option<usize>) -> usize {
    threads.unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)).max(1)
}

/// `--threads` and `--max-memory` as session options (defaults: every core, half the
/// physical memory).
pub fn session_options(threads: Option<usize>, max_memory: Option<usize>) -> SessionOptions {
    let options = SessionOptions::default().threads(threads_or_default(threads));
    match max_memory {
        Some(bytes) => options.max_memory(bytes),
        None => options,
    }
}

/// Seeded uniform numbers in [0, 1) (a 64-bit LCG's top 24 bits): the commands' synthetic
/// inputs and the demos' sensor data, the same every run.
pub fn uniform(seed: u64) -> impl FnMut() -> f32 {
    let mut state = seed;
    move || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (state >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// Loads a plan file; the error is printed.
pub fn load_plan(path: &Path) -> Result<Arc<Plan>, ExitCode> {
    match Plan::load(path) {
        Ok(p) => Ok(Arc::new(p)),
        Err(e) => {
            eprintln!("error: {e}");
            Err(ExitCode::FAILURE)
        }
    }
}
