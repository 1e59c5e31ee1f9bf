//! The readi runtime: loads a plan and runs it on CPU in f32.

pub mod calibrate;
pub mod conditions;
pub mod exec;
pub mod kernels;
pub mod peak;
pub mod plan;
#[doc(hidden)]
pub mod testdata;
