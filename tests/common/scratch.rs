//! Scratch directories for tests, shared by the workspace's test crates (the runtime's
//! tests include this file too).

use std::path::Path;

/// A directory of a test's own, `readi-<tag>-XXXXXX` under the system's temp dir, removed
/// when dropped: when the test ends, passed or failed (a test failing by panic unwinds).
/// Derefs to its path.
pub struct Scratch(tempfile::TempDir);

impl Scratch {
    pub fn new(tag: &str) -> Scratch {
        Scratch(tempfile::Builder::new().prefix(&format!("readi-{tag}-")).tempdir().expect("temp dir"))
    }
}

impl std::ops::Deref for Scratch {
    type Target = Path;
    fn deref(&self) -> &Path {
        self.0.path()
    }
}

impl AsRef<Path> for Scratch {
    fn as_ref(&self) -> &Path {
        self.0.path()
    }
}
