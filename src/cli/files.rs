//! Reading files readi does not trust: every command reads weights, variants, specs,
//! manifests, samples and inputs through these two functions, so a device (`/dev/zero`),
//! a pipe, a directory or a file over its kind's limit is refused before it is read.

use std::io::Read;
use std::path::Path;

/// Most bytes a weights file (base, variant, PEFT adapter) may have: 16 GiB.
pub const MAX_WEIGHTS_BYTES: u64 = 16 << 30;
/// Most bytes of a PEFT `adapter_config.json` or a deployment manifest: 1 MiB.
pub const MAX_CONFIG_BYTES: u64 = 1 << 20;

/// Checks that `path` is a regular file of at most `limit` bytes and returns its length.
pub fn check_file(path: &Path, limit: u64) -> Result<u64, String> {
    let shown = path.display();
    let meta = std::fs::metadata(path).map_err(|e| format!("cannot read {shown}: {e}"))?;
    if meta.is_dir() {
        return Err(format!("cannot read {shown}: it is a directory"));
    }
    if !meta.is_file() {
        return Err(format!("cannot read {shown}: it is not a regular file (a device, a pipe or a socket)"));
    }
    if meta.len() > limit {
        return Err(too_large(path, meta.len(), limit));
    }
    Ok(meta.len())
}

/// Reads a file after [`check_file`], refusing it too if it grows past `limit` while it
/// is read.
pub fn read_bounded(path: &Path, limit: u64) -> Result<Vec<u8>, String> {
    let len = check_file(path, limit)?;
    let mut bytes = Vec::with_capacity(len as usize);
    std::fs::File::open(path)
        .and_then(|f| f.take(limit.saturating_add(1)).read_to_end(&mut bytes))
        .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    if bytes.len() as u64 > limit {
        return Err(too_large(path, bytes.len() as u64, limit));
    }
    Ok(bytes)
}

fn too_large(path: &Path, n: u64, limit: u64) -> String {
    format!("{} is {n} bytes, over the limit of {limit} bytes for this kind of file", path.display())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn devices_directories_and_large_files_are_refused_before_reading() {
        let e = read_bounded(Path::new("/dev/zero"), 1 << 20).expect_err("a device");
        assert!(e.contains("not a regular file"), "{e}");
        let dir = std::env::temp_dir();
        let e = read_bounded(&dir, 1 << 20).expect_err("a directory");
        assert!(e.contains("is a directory"), "{e}");
        let f = dir.join(format!("readi-files-{}.bin", std::process::id()));
        std::fs::write(&f, [7u8; 100]).expect("write");
        assert_eq!(read_bounded(&f, 100).expect("at the limit"), vec![7u8; 100]);
        let e = read_bounded(&f, 99).expect_err("over the limit");
        assert!(e.contains("100 bytes, over the limit of 99"), "{e}");
        std::fs::remove_file(&f).expect("remove");
    }
}
