//! Deterministic test data and comparison helpers for kernel tests.

pub use crate::testdata::data;

/// Asserts `got` and `want` agree within `tol`, absolute or relative to |want|.
#[track_caller]
pub fn assert_close(got: &[f32], want: &[f32], tol: f32) {
    assert_eq!(got.len(), want.len(), "lengths differ");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        let err = (g - w).abs();
        assert!(err <= tol * (1.0 + w.abs()), "element {i}: got {g}, want {w} (error {err})");
    }
}

/// A SIMD instruction set, to run explicit-SIMD kernel code on each one this CPU has
/// (the kernels themselves always dispatch to the widest, so without this the narrower
/// vector widths and the scalar fallback would go untested).
#[derive(Clone, Copy, Debug)]
pub enum Backend {
    Scalar,
    #[cfg(target_arch = "x86_64")]
    V3,
    #[cfg(target_arch = "x86_64")]
    V4,
}

/// Every backend this CPU can run, narrowest first.
pub fn backends() -> Vec<Backend> {
    #[allow(unused_mut)]
    let mut all = vec![Backend::Scalar];
    #[cfg(target_arch = "x86_64")]
    {
        if pulp::x86::V3::try_new().is_some() {
            all.push(Backend::V3);
        }
        if pulp::x86::V4::try_new().is_some() {
            all.push(Backend::V4);
        }
    }
    all
}

impl Backend {
    /// Runs `op` compiled for this backend.
    pub fn run<Op: pulp::WithSimd>(self, op: Op) -> Op::Output {
        use pulp::Simd;
        match self {
            Backend::Scalar => Simd::vectorize(pulp::Scalar::new(), op),
            #[cfg(target_arch = "x86_64")]
            Backend::V3 => Simd::vectorize(pulp::x86::V3::try_new().expect("listed by backends()"), op),
            #[cfg(target_arch = "x86_64")]
            Backend::V4 => Simd::vectorize(pulp::x86::V4::try_new().expect("listed by backends()"), op),
        }
    }
}
